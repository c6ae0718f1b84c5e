"""Build the pinned gsplat's CUDA extension here, without a GPU, against a given CUDA and torch.

gsplat (the GPU rasterizer, ``.[gpu]``) ships as source and compiles its CUDA kernels on first
use (torch's JIT: nvcc + ninja). Whether that build works with a machine's CUDA toolkit and
torch is the first thing a GPU run can fail on, and it can be checked on any x86-64 Linux box:
this script fetches NVIDIA's compiler wheels (nvcc, cicc, CCCL, the runtime headers) for
``--cuda`` and the CUDA build of ``--torch`` from PyPI, then runs gsplat's own JIT build
(its sources, include paths and flags, as ``gsplat/cuda/_backend.py`` passes them) for
``--arch`` with torch's ``cpp_extension``, links the library against that torch's CUDA
libraries and checks that every symbol it needs, outside the Python C API, is defined by them.
Loading it needs a GPU driver, which this does not check.

    python scripts/gsplat_build_check.py                      # the lent device's versions
    python scripts/gsplat_build_check.py --cuda 12.8 --torch 2.8.0 --arch 8.6

Downloads ~640 MB once into ``--work`` (kept for later runs). Measured (2026-11-26, 2-core
box): gsplat 1.5.3, CUDA 13.0.88, torch 2.11.0+cu130, sm_90: 29 of 29 objects, no error or
warning, linked, 0 unresolved symbols; 403 s (326 s for the compile alone on an idle box).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CUDA_WHEELS = ("nvidia-cuda-nvcc", "nvidia-cuda-cccl", "nvidia-cuda-runtime", "nvidia-cuda-crt", "nvidia-nvvm")
TORCH_LIBS = ("libc10.so", "libc10_cuda.so", "libtorch.so", "libtorch_cpu.so", "libtorch_cuda.so",
              "libtorch_python.so")
PLATFORMS = ("manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_27_x86_64", "manylinux_2_28_x86_64",
             "manylinux1_x86_64", "manylinux2010_x86_64", "manylinux_2_12_x86_64")
# symbols the dynamic loader or libgcc provides, not torch / CUDA
LOADER_SYMBOLS = {"_ITM_deregisterTMCloneTable", "_ITM_registerTMCloneTable", "__gmon_start__", "__tls_get_addr"}


def log(msg: str) -> None:
    print(f"gsplat_build_check: {msg}", flush=True)


def download(spec: str, dest: Path) -> Path:
    """The wheel for ``spec`` (cp312, manylinux x86-64) in ``dest``, fetched unless present."""
    name = spec.split("=")[0].replace("-", "_").lower()
    ver = spec.split("==")[1].rstrip("*").rstrip(".")
    have = [p for p in dest.glob("*.whl") if p.name.lower().startswith(f"{name}-{ver}")]
    if not have:
        log(f"downloading {spec}")
        cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
               "--python-version", "3.12", "--implementation", "cp", "-d", str(dest), spec]
        for p in PLATFORMS:
            cmd += ["--platform", p]
        subprocess.run(cmd, check=True)
        have = [p for p in dest.glob("*.whl") if p.name.lower().startswith(f"{name}-{ver}")]
    if len(have) != 1:
        raise SystemExit(f"gsplat_build_check: expected one wheel for {spec} in {dest}, found {have}")
    return have[0]


def extract(wheel: Path, dest: Path, members: tuple[str, ...] | None = None) -> None:
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist() if members is None else [n for n in z.namelist() if n.startswith(members)]
        z.extractall(dest, names)


def undefined_symbols(lib: Path, providers: list[Path]) -> list[str]:
    """Dynamic symbols ``lib`` needs that no file in ``providers`` defines (Python's C API and
    the loader's own excluded)."""
    def syms(path: Path, flag: str) -> set[str]:
        out = subprocess.run(["nm", "-D", flag, str(path)], capture_output=True, text=True).stdout
        return {line.split()[-1].split("@")[0] for line in out.splitlines() if line.strip()}

    need = syms(lib, "--undefined-only")
    have: set[str] = set()
    for p in providers:
        have |= syms(p, "--defined-only")
    return sorted(s for s in need - have - LOADER_SYMBOLS if not s.lstrip("_").startswith("Py"))


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(ROOT))
    from splat_train.render._gsplat_backend import GSPLAT_VERSION

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gsplat", default=GSPLAT_VERSION, help="gsplat version (default: the pinned one)")
    ap.add_argument("--cuda", default="13.0", help="CUDA toolkit minor version of the wheels (default %(default)s)")
    ap.add_argument("--torch", default="2.11.0", help="torch version, its PyPI (CUDA) build (default %(default)s)")
    ap.add_argument("--arch", default="9.0", help="TORCH_CUDA_ARCH_LIST (default %(default)s: Hopper)")
    ap.add_argument("--work", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "gsplat_build_check")
    ap.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("-v", "--verbose", action="count", default=0, help="print ninja's compile lines ([k/30] progress)")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    wheels = args.work / "wheels"
    wheels.mkdir(parents=True, exist_ok=True)
    tag = f"gsplat{args.gsplat}-cuda{args.cuda}-torch{args.torch}-sm{args.arch.replace('.', '')}"
    tree = args.work / tag
    cuda, tdir, gdir, build = tree / "cuda", tree / "torch", tree / "gsplat", tree / "build"
    if not (cuda / "bin" / "nvcc").exists():
        for w in CUDA_WHEELS:
            extract(download(f"{w}=={args.cuda}.*", wheels), tree / "cuda_wheels")
        found = glob.glob(str(tree / "cuda_wheels" / "nvidia" / "*" / "bin" / "nvcc"))
        if len(found) != 1:
            raise SystemExit(f"gsplat_build_check: no single nvcc in the CUDA {args.cuda} wheels: {found}")
        if cuda.exists() or cuda.is_symlink():
            cuda.unlink()
        cuda.symlink_to(Path(found[0]).parents[1])
    for exe in [*(cuda / "bin").iterdir(), *(cuda / "nvvm" / "bin").iterdir()]:
        exe.chmod(0o755)
    nvcc_v = subprocess.run([str(cuda / "bin" / "nvcc"), "--version"], capture_output=True, text=True).stdout
    release = next((x for x in nvcc_v.splitlines() if "release" in x), nvcc_v.strip()).split("release")[-1].strip()
    (cuda / "version.json").write_text(json.dumps({"cuda": {"version": args.cuda}}))
    cudart = sorted((cuda / "lib").glob("libcudart.so.*"))
    if cudart and not (cuda / "lib" / "libcudart.so").exists():
        (cuda / "lib" / "libcudart.so").symlink_to(cudart[0].name)
    if not (tdir / "torch" / "include").exists():
        extract(download(f"torch=={args.torch}", wheels), tdir,
                ("torch/include/", "torch/version.py", *(f"torch/lib/{lib}" for lib in TORCH_LIBS)))
    torch_ver = (tdir / "torch" / "version.py").read_text().split("__version__ = ")[1].split("\n")[0].strip("'\"")
    if not (gdir / "gsplat").exists():
        extract(download(f"gsplat=={args.gsplat}", wheels), gdir)
    log(f"gsplat {args.gsplat}, nvcc {release}, torch {torch_ver} headers and libraries, arch {args.arch}")

    # gsplat/cuda/_backend.py's JIT build: its sources, include paths and flags
    os.environ.update(CUDA_HOME=str(cuda), TORCH_CUDA_ARCH_LIST=args.arch, MAX_JOBS=str(args.jobs),
                      PATH=f"{cuda / 'bin'}:{os.environ['PATH']}")
    from torch.utils import cpp_extension as ce

    inc = tdir / "torch" / "include"
    ce.CUDA_HOME = str(cuda)  # a CPU torch leaves it unset
    ce.include_paths = lambda *a, **k: [str(inc), str(inc / "torch/csrc/api/include"), str(cuda / "include")]
    ce.TORCH_LIB_PATH = str(tdir / "torch" / "lib")  # link against the CUDA torch, not this one
    src = gdir / "gsplat" / "cuda"
    sources = sorted(glob.glob(str(src / "csrc/*.cu"))) + sorted(glob.glob(str(src / "csrc/*.cpp"))) + [
        str(src / "ext.cpp")]
    if build.exists():
        for f in build.iterdir():
            f.unlink()
    build.mkdir(parents=True, exist_ok=True)
    log(f"compiling {len(sources)} sources on {args.jobs} jobs (~6 min on 2 cores; --verbose shows each)")
    t1 = time.perf_counter()
    try:
        ce.load(name="gsplat_cuda", sources=sources, extra_cflags=["-O3", "-Wno-attributes"],
                extra_cuda_cflags=["-O3", "-use_fast_math"],
                extra_include_paths=[str(src / "include"), str(src / "csrc/third_party/glm")],
                build_directory=str(build), verbose=bool(args.verbose), with_cuda=True)
        loaded = True
    except ImportError as e:  # built, but not loadable here (no GPU driver; another torch)
        loaded, why = False, str(e).splitlines()[0]
    except Exception as e:
        log(f"FAILED after {time.perf_counter() - t1:.0f} s: {type(e).__name__}: {str(e)[-2000:]}")
        return 1
    lib = build / "gsplat_cuda.so"
    objs = sorted(build.glob("*.o"))
    log(f"built {lib.name} ({lib.stat().st_size / 1e6:.1f} MB) from {len(objs)} objects in "
        f"{time.perf_counter() - t1:.0f} s" + ("" if loaded else f"; not loadable here, as expected ({why})"))
    providers = [tdir / "torch" / "lib" / x for x in TORCH_LIBS] + cudart + [
        Path(p) for p in ("/lib/x86_64-linux-gnu/libstdc++.so.6", "/lib/x86_64-linux-gnu/libc.so.6",
                          "/lib/x86_64-linux-gnu/libm.so.6", "/lib/x86_64-linux-gnu/libgcc_s.so.1")
        if Path(p).exists()]
    missing = undefined_symbols(lib, providers)
    if missing:
        log(f"FAILED: {len(missing)} symbols undefined in torch {torch_ver} / CUDA {args.cuda}: {missing[:20]}")
        return 1
    log(f"OK: every non-Python symbol resolves against torch {torch_ver} and cudart "
        f"({time.perf_counter() - t0:.0f} s in all)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
