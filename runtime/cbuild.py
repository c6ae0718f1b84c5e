"""Build a single-file C++ shared library with the system compiler, cached, for ctypes loading.

Used by the CPU kernels (``splat_train/render/cpu/raster.py``, ``vggt_init/model/_attention_kernel.py``):
plain C ABI sources with no torch headers, compiled on first use into a cache folder and named by a
hash of the source bytes, the compiler, the flags and the machine, so an edited source or new
flags give a new library and stale ones are never loaded.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["find_compiler", "build_shared"]

log = logging.getLogger(__name__)


def find_compiler() -> str | None:
    """``$CXX`` if set and on PATH, else the first of c++, g++, clang++ found; None if none is."""
    for cand in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if cand and shutil.which(cand):
            return cand
    return None


def build_shared(source: Path, flags: list[str], cache_dir: Path, prefix: str, cxx: str,
                 timeout: float = 300, headers: tuple[Path, ...] = ()) -> Path:
    """Compile ``source`` to ``cache_dir/{prefix}_{hash}.so`` unless that file exists; return its path.

    ``flags`` must include ``-shared -fPIC``. ``headers``: local headers the source includes;
    their bytes join the hash, so editing one rebuilds every source that names it. The compile
    writes a temporary file and renames it into place, so concurrent builders race harmlessly.
    Raises RuntimeError (with the compiler's stderr tail) when the compile fails,
    subprocess.TimeoutExpired after ``timeout`` seconds.
    """
    src = Path(source).read_bytes() + b"".join(Path(h).read_bytes() for h in headers)
    key = hashlib.sha256(src + " ".join([cxx, *flags]).encode() + os.uname().machine.encode()).hexdigest()[:16]
    target = Path(cache_dir) / f"{prefix}_{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        cmd = [cxx, *flags, str(source), "-o", tmp]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    log.info("built %s", target)
    return target
