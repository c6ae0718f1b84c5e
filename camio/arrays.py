"""The size an ``.npy`` / ``.npz`` header claims, checked against the bytes that hold it.

numpy allocates an array from the shape its header states before it reads the data, so a
small file whose header claims 10^12 values asks for terabytes: a ``MemoryError`` traceback,
or worse, the memory of the machine. :func:`check_npy` and :func:`check_npz` read only the
headers and refuse, in one line naming the file (and the member), an array whose bytes are
more than the file (or the archive member) can hold. A stored member holds its compressed
bytes; a deflated one at most :data:`MAX_DEFLATE_RATIO` times them. Call them before
``np.load``; they allocate nothing in proportion to a claimed size.
"""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format

__all__ = ["MAX_DEFLATE_RATIO", "check_npy", "check_npz"]

MAX_DEFLATE_RATIO = 1032
"""The most bytes deflate can expand one compressed byte into (its longest match, 258 bytes,
coded in two bits)."""


def _header(f, path: str) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, header length in bytes) of the .npy stream ``f`` at its start."""
    try:
        version = npy_format.read_magic(f)
        read = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}.get(version)
        if read is None:
            raise ValueError(f"unsupported .npy version {version}")
        shape, _fortran, dtype = read(f)
    except (ValueError, EOFError, OSError) as exc:
        raise ValueError(f"{path}: not a readable .npy header ({exc})") from None
    return tuple(int(s) for s in shape), dtype, f.tell()


def _check(path: str, shape: tuple[int, ...], dtype: np.dtype, holds: int) -> None:
    if dtype.hasobject:
        raise ValueError(f"{path}: holds Python objects (a pickle), which are never loaded; write plain arrays")
    claims = math.prod(shape) * dtype.itemsize
    if claims > holds:
        raise ValueError(f"{path}: the header claims an array of shape {list(shape)} ({claims:,} bytes) but the "
                         f"file holds at most {holds:,} bytes of data: it is truncated or was not written by numpy; "
                         "write it again")


def check_npy(path: str | os.PathLike) -> None:
    """Refuse an ``.npy`` whose header claims more data than the file holds (ValueError, one
    line naming it)."""
    p = Path(path)
    with open(p, "rb") as f:
        shape, dtype, head = _header(f, str(p))
    _check(str(p), shape, dtype, p.stat().st_size - head)


def check_npz(path: str | os.PathLike) -> None:
    """Refuse an ``.npz`` one of whose ``.npy`` members claims more data than the member can
    hold (ValueError, one line naming the file and the member); a file that is no zip archive
    raises ``zipfile.BadZipFile`` as ``np.load`` would."""
    p = Path(path)
    with zipfile.ZipFile(p) as z:
        for info in z.infolist():
            if not info.filename.endswith(".npy"):
                continue
            ratio = 1 if info.compress_type == zipfile.ZIP_STORED else MAX_DEFLATE_RATIO
            holds = min(info.file_size, info.compress_size * ratio)
            with z.open(info) as f:
                shape, dtype, head = _header(f, f"{p} ({info.filename})")
            _check(f"{p} ({info.filename})", shape, dtype, holds - head)
