"""Build, load and run the C++ CPU kernels of :mod:`splat_train` (shared machinery).

Each kernel is one C++ source with a plain C ABI and no torch headers or OpenMP, compiled with
the system compiler (``$CXX``, else ``c++`` / ``g++``) on first use into a cache folder
(``$SPLAT_TRAIN_KERNEL_DIR``, else ``~/.cache/splat_train/kernels``), keyed by a hash of the
source, compiler and flags (:mod:`runtime.cbuild`), and loaded with ctypes. SIMD flags are chosen
at load time from the CPU's flags (``/proc/cpuinfo``): AVX-512 (F, DQ, BW, VL) where present,
else AVX2 + FMA, else none (SSE2, the x86-64 baseline, or the target's default); if that build
fails, the next level down is tried. ``$SPLAT_TRAIN_KERNEL_SIMD`` = ``avx512`` | ``avx2`` |
``none`` overrides; ``$SPLAT_TRAIN_KERNEL_FLAGS`` adds flags; ``SPLAT_TRAIN_NO_KERNEL=1``
disables every kernel (callers then use the torch code).

Threads: :func:`kernel_threads` Python threads run the same C entry and share an atomic work
counter (ctypes drops the GIL; no OpenMP runtime, so no spinning worker threads competing with
torch's on a loaded machine). Registered kernels: ``cpu`` (:mod:`splat_train.render.cpu.raster`),
``project`` (:mod:`splat_train.render.cpu.project`), ``ssim`` (:mod:`splat_train.render.cpu.ssim`), ``optim``
(:mod:`splat_train.render.cpu.optim`).
"""

from __future__ import annotations

import ctypes
import logging
import os
import subprocess
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from runtime.cbuild import build_shared, find_compiler

__all__ = ["KERNEL_REGISTRY", "Kernel", "set_kernel_threads", "kernel_threads", "run_threaded", "ptr", "suffix",
           "build_seconds", "build_all"]

log = logging.getLogger(__name__)

_HERE = Path(__file__).parent
_BASE_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-Wno-psabi"]
_SIMD_FLAGS = {
    "avx512": ["-mavx512f", "-mavx512dq", "-mavx512bw", "-mavx512vl", "-mavx2", "-mfma",
               "-mprefer-vector-width=512"],
    "avx2": ["-mavx2", "-mfma"],
    "none": [],
}
# Local headers the kernel sources include (part of every kernel's cache key).
_HEADERS = tuple(sorted(_HERE.glob("*.h")))


def _cpu_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def _simd_choices() -> list[str]:
    """SIMD levels to try, best first (the last one is always the portable build)."""
    env = os.environ.get("SPLAT_TRAIN_KERNEL_SIMD")
    if env:
        if env not in _SIMD_FLAGS:
            raise ValueError(f"SPLAT_TRAIN_KERNEL_SIMD must be one of {sorted(_SIMD_FLAGS)}, got {env!r}")
        return [env]
    flags = _cpu_flags()
    out = []
    if {"avx512f", "avx512dq", "avx512bw", "avx512vl", "avx2", "fma"} <= flags:
        out.append("avx512")
    if {"avx2", "fma"} <= flags:
        out.append("avx2")
    return out + ["none"]


def _extra_flags() -> list[str]:
    return os.environ.get("SPLAT_TRAIN_KERNEL_FLAGS", "").split()


class Kernel:
    """One kernel source: build (cached), load once, declare the ctypes signatures."""

    def __init__(self, name: str, source: str, abi: int, simd: bool, abi_fn: str, declare: Callable) -> None:
        self.name, self.source, self.abi, self.simd = name, _HERE / source, abi, simd
        self.abi_fn, self.declare = abi_fn, declare
        self.lib: ctypes.CDLL | None = None
        self.error: str | None = None
        self.tried = False
        self.lock = threading.Lock()

    def load(self) -> ctypes.CDLL | None:
        with self.lock:
            if self.tried:
                return self.lib
            self.tried = True
            if os.environ.get("SPLAT_TRAIN_NO_KERNEL"):
                self.error = "disabled by SPLAT_TRAIN_NO_KERNEL"
                return None
            cxx = find_compiler()
            if cxx is None:
                self.error = "no C++ compiler found (set $CXX or install g++)"
                log.warning("CPU rasterizer kernel %r unavailable: %s; using the slower torch tile path",
                            self.name, self.error)
                return None
            errors = []
            for level in (_simd_choices() if self.simd else ["none"]):
                flags = _BASE_FLAGS + _SIMD_FLAGS[level] + _extra_flags()
                try:
                    t0 = time.perf_counter()
                    try:
                        built = build_shared(self.source, flags, _cache_dir(), f"splat_{self.name}", cxx,
                                             headers=_HEADERS)
                    finally:
                        _add_build_seconds(time.perf_counter() - t0)
                    lib = ctypes.CDLL(str(built))
                    version = getattr(lib, self.abi_fn)()
                    if version != self.abi:
                        raise RuntimeError(f"kernel ABI version mismatch ({version} != {self.abi})")
                except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                    errors.append(f"{level}: {exc}")
                    continue
                self.lib = self.declare(lib)
                if errors:
                    log.warning("CPU kernel %r: SIMD build failed (%s); using %s", self.name, errors, level)
                return self.lib
            self.error = "; ".join(errors)
            log.warning("CPU rasterizer kernel %r unavailable (%s); using the slower torch tile path",
                        self.name, self.error)
            return None


_BUILD_SECONDS = [0.0]
_BUILD_LOCK = threading.Lock()


def _add_build_seconds(seconds: float) -> None:
    with _BUILD_LOCK:
        _BUILD_SECONDS[0] += seconds


def build_seconds() -> float:
    """Seconds this process has spent building (or finding cached) kernels: a one-time cost
    that the trainer keeps out of its run time (``train.json`` ``kernel_build_s``)."""
    return _BUILD_SECONDS[0]


def build_all() -> dict[str, str | None]:
    """Build (or find cached) every registered kernel; returns name -> None or the error.
    ``python -m splat_train.render.cpu.build`` runs it, so that no training run pays for the build."""
    import importlib

    for module in ("raster", "project", "ssim", "optim"):  # each registers its kernel on import
        importlib.import_module(f"splat_train.render.cpu.{module}")
    return {name: (None if k.load() is not None else k.error) for name, k in sorted(KERNEL_REGISTRY.items())}


def _cache_dir() -> Path:
    env = os.environ.get("SPLAT_TRAIN_KERNEL_DIR")
    return Path(env) if env else Path.home() / ".cache" / "splat_train" / "kernels"


def ptr(t: Tensor) -> int:
    return t.data_ptr()


_pool: ThreadPoolExecutor | None = None
_threads: int | None = None


def set_kernel_threads(n: int | None) -> None:
    """Threads for the C++ kernel (None: follow ``torch.get_num_threads()``)."""
    global _threads
    _threads = None if n is None else max(1, int(n))


def kernel_threads() -> int:
    """Threads of the C++ kernel: ``$SPLAT_TRAIN_KERNEL_THREADS`` if set, else the count given
    to :func:`set_kernel_threads`, else ``torch.get_num_threads()``. The kernel's threads block
    in C (no spinning OpenMP workers), so it can use more threads than torch's intra-op pool:
    with torch at 1 thread, 2 kernel threads made forward+backward of 50k Gaussians at 497x372
    1.85x faster (0.672 -> 0.364 s) here (with the scalar kernel "cpu_v1", since deleted)."""
    env = os.environ.get("SPLAT_TRAIN_KERNEL_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError as exc:
            raise ValueError(f"SPLAT_TRAIN_KERNEL_THREADS must be an integer, got {env!r}") from exc
    return _threads if _threads is not None else max(1, torch.get_num_threads())


def run_threaded(fn, *args, first=None):
    """Run a kernel entry on :func:`kernel_threads` threads sharing one work counter.

    ctypes drops the GIL during the call, so the threads run the C code concurrently.
    ``first``: a callable (independent of ``fn``'s work, dropping the GIL for its own) that
    the calling thread runs before it joins ``fn``: serial work overlapped with the parallel
    work of the other threads, which share the counter, so the work is split the same way
    whoever takes it. Returns ``first()``'s result (None without it).
    """
    global _pool
    nthreads = kernel_threads()
    counter = ctypes.c_int64(0)
    cptr = ctypes.addressof(counter)
    if nthreads == 1:
        res = first() if first is not None else None
        fn(*args, cptr)
        return res
    if _pool is None or _pool._max_workers < nthreads:
        _pool = ThreadPoolExecutor(max_workers=nthreads, thread_name_prefix="splat_cpu")
    futures = [_pool.submit(fn, *args, cptr) for _ in range(nthreads - 1)]
    try:
        res = first() if first is not None else None
    finally:
        fn(*args, cptr)
        for f in futures:
            f.result()
    return res


def suffix(dt: torch.dtype) -> str:
    suffix = {torch.float32: "f32", torch.float64: "f64"}.get(dt)
    if suffix is None:
        raise TypeError(f"CPU kernel supports float32 and float64, got {dt}")
    return suffix




KERNEL_REGISTRY: dict[str, Kernel] = {}


def main() -> int:
    """``python -m splat_train.render.cpu.build``: build every kernel once (scripts/install.sh runs it)."""
    from splat_train.render.cpu import build  # the imported module, whose registry the kernels join (not __main__)

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.perf_counter()
    done = build.build_all()
    failed = {name: err for name, err in done.items() if err}
    for name, err in failed.items():
        print(f"splat_train kernel {name!r} not built: {err} (training uses the slower torch path)")
    print(f"splat_train kernels: {len(done) - len(failed)}/{len(done)} ready in {_cache_dir()} "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
