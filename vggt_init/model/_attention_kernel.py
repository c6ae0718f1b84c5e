"""Fused bf16 attention for CPUs with AVX512-BF16: the C++ kernel in ``_attention_kernel.cpp``.

Flash-style: per (batch, head, block of 48 query rows) the scores q k^T are accumulated in float32
from bf16 q, k with ``vdpbf16ps``, scaled by 1/sqrt(D) and fed to an online softmax (running row
max and sum in float32); P is rounded to bf16 and P V accumulated in float32, then divided by the
row sum and rounded to bf16. No [N, N] score matrix is ever stored. The precision is that of
``fastpath._attention_onednn`` in bf16 (float32 scores and softmax, bf16 P and V).

Build: on first use with the system compiler (``$CXX``, else c++ / g++ / clang++) and
``-mavx512f -mavx512bw -mavx512vl -mavx512bf16 -mfma`` into ``$VGGT_INIT_KERNEL_DIR`` (else
``~/.cache/vggt_init/kernels``), via :mod:`runtime.cbuild`; loaded with ctypes. :func:`available`
is False (and callers use the oneDNN path) without a compiler, on a CPU without avx512_bf16, after
a failed build (logged once), or with ``VGGT_INIT_NO_KERNEL=1``.

Threads: ``torch.get_num_threads()`` Python threads share an atomic task counter inside the C call
(ctypes drops the GIL). Each task's arithmetic is fixed, so results are bitwise independent of the
thread count.
"""

from __future__ import annotations

import ctypes
import logging
import os
import subprocess
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from torch import Tensor

from runtime.cbuild import build_shared, find_compiler

__all__ = ["available", "build_error", "supports", "attention_bf16", "HEAD_DIMS"]

log = logging.getLogger(__name__)

_SOURCE = Path(__file__).with_name("_attention_kernel.cpp")
_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-mavx512f", "-mavx512bw", "-mavx512vl",
          "-mavx512bf16", "-mfma"]
HEAD_DIMS = (32, 64, 96, 128)  # head dims the kernel is compiled for
_ABI = 1

_lock = threading.Lock()
_state: dict = {"tried": False, "lib": None, "error": None, "key_block": 64}
_pool: ThreadPoolExecutor | None = None


def _cache_dir() -> Path:
    env = os.environ.get("VGGT_INIT_KERNEL_DIR")
    return Path(env) if env else Path.home() / ".cache" / "vggt_init" / "kernels"


def _cpu_has_bf16() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return {"avx512f", "avx512bw", "avx512vl", "avx512_bf16"} <= flags
    except OSError:
        pass
    return False  # no /proc/cpuinfo (not Linux): do not risk illegal instructions


def _load() -> ctypes.CDLL | None:
    with _lock:
        if _state["tried"]:
            return _state["lib"]
        _state["tried"] = True
        if os.environ.get("VGGT_INIT_NO_KERNEL", "") not in ("", "0"):
            _state["error"] = "disabled by VGGT_INIT_NO_KERNEL"
            return None
        if not _cpu_has_bf16():
            _state["error"] = "CPU lacks avx512_bf16 (or /proc/cpuinfo unreadable)"
            return None
        cxx = find_compiler()
        if cxx is None:
            _state["error"] = "no C++ compiler found (set $CXX or install g++)"
            log.warning("bf16 attention kernel unavailable: %s; using oneDNN attention", _state["error"])
            return None
        try:
            lib = ctypes.CDLL(str(build_shared(_SOURCE, _FLAGS, _cache_dir(), "vggt_attn", cxx)))
            if lib.vggt_attn_abi_version() != _ABI:
                raise RuntimeError("kernel ABI version mismatch")
            if not lib.vggt_attn_cpu_ok():
                raise RuntimeError("CPU lacks avx512_bf16 (__builtin_cpu_supports)")
        except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
            _state["error"] = str(exc)
            log.warning("bf16 attention kernel unavailable (%s); using oneDNN attention", exc)
            return None
        i64, vp = ctypes.c_int64, ctypes.c_void_p
        lib.vggt_attn_bf16.argtypes = [i64, i64, i64, i64, vp, vp, vp, vp, vp]
        lib.vggt_attn_bf16.restype = ctypes.c_int
        lib.vggt_attn_exp.argtypes = [vp, vp, i64]
        lib.vggt_attn_exp.restype = None
        _state["key_block"] = int(lib.vggt_attn_key_block())
        _state["lib"] = lib
        return lib


def available() -> bool:
    """True when the kernel is built (first call builds it) and usable on this CPU."""
    return _load() is not None


def build_error() -> str | None:
    """Why the kernel is unavailable (None when it loaded or was not tried)."""
    return _state["error"]


def supports(head_dim: int) -> bool:
    """True when the kernel is available and compiled for this head dim."""
    return head_dim in HEAD_DIMS and available()


def exp_f32(x: Tensor) -> Tensor:
    """The kernel's vectorised float32 exp applied to ``x`` (any shape; for tests)."""
    lib = _load()
    if lib is None:
        raise RuntimeError(f"bf16 attention kernel unavailable: {_state['error']}")
    xc = x.detach().to(torch.float32).contiguous()
    y = torch.empty_like(xc)
    lib.vggt_attn_exp(xc.data_ptr(), y.data_ptr(), xc.numel())
    return y


def _pack(k: Tensor, v: Tensor, kb: int) -> tuple[Tensor, Tensor]:
    """Pair-interleaved K and V for vdpbf16ps (layouts in the .cpp header).

    k, v: [BH, N, D] bf16. Returns kp [BH, Np/16, D/2, 16, 2] and vp [BH, Np/2, D/16, 16, 2],
    Np = N rounded up to a multiple of ``kb``, zero past N.
    """
    BH, N, D = k.shape
    np_ = -(-N // kb) * kb
    if np_ != N:
        k = torch.nn.functional.pad(k, (0, 0, 0, np_ - N))
        v = torch.nn.functional.pad(v, (0, 0, 0, np_ - N))
    kp = k.reshape(BH, np_ // 16, 16, D // 2, 2).permute(0, 1, 3, 2, 4).contiguous()
    vp = v.reshape(BH, np_ // 2, 2, D // 16, 16).permute(0, 1, 3, 4, 2).contiguous()
    return kp, vp


def attention_bf16(q: Tensor, k: Tensor, v: Tensor) -> Tensor:
    """softmax(q k^T / sqrt(D)) v in bf16 through the kernel (no autograd).

    Args:
        q, k, v: [B, nh, N, D] CPU tensors, any float dtype and strides (cast to bf16).
            D must be in ``HEAD_DIMS``.

    Returns:
        [B, N, nh, D] bf16, contiguous (token-major).

    Raises:
        RuntimeError when the kernel is unavailable; ValueError for an unsupported D or shape.
    """
    lib = _load()
    if lib is None:
        raise RuntimeError(f"bf16 attention kernel unavailable: {_state['error']}")
    if q.dim() != 4 or q.shape != k.shape or q.shape != v.shape:
        raise ValueError(f"q, k, v must share one [B, nh, N, D] shape, got {tuple(q.shape)}, "
                         f"{tuple(k.shape)}, {tuple(v.shape)}")
    B, H, N, D = q.shape
    if D not in HEAD_DIMS:
        raise ValueError(f"head dim {D} not supported by the kernel (supported: {HEAD_DIMS})")
    out = torch.empty(B, N, H, D, dtype=torch.bfloat16)
    if B * H * N == 0:
        return out
    with torch.no_grad():
        qc = q.detach().to(torch.bfloat16).contiguous()
        kp, vp = _pack(k.detach().to(torch.bfloat16).reshape(B * H, N, D),
                       v.detach().to(torch.bfloat16).reshape(B * H, N, D), _state["key_block"])
    counter = ctypes.c_int64(0)
    args = (B, H, N, D, qc.data_ptr(), kp.data_ptr(), vp.data_ptr(), out.data_ptr(), ctypes.addressof(counter))
    nthreads = max(1, torch.get_num_threads())
    global _pool
    if nthreads == 1:
        rc = [lib.vggt_attn_bf16(*args)]
    else:
        with _lock:
            if _pool is None or _pool._max_workers < nthreads - 1:
                _pool = ThreadPoolExecutor(max_workers=nthreads - 1, thread_name_prefix="vggt_attn")
            pool = _pool
        futures = [pool.submit(lib.vggt_attn_bf16, *args) for _ in range(nthreads - 1)]
        rc = [lib.vggt_attn_bf16(*args)] + [f.result() for f in futures]
    if any(rc):
        raise ValueError(f"kernel refused head dim {D}")
    return out
