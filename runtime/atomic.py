"""Atomic outputs: write under a temporary name in the same folder, then rename.

A crash never leaves a file or folder that looks complete: readers see either the old
version or the whole new one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from runtime.stops import stops_held

__all__ = ["atomic_path", "atomic_dir", "scratch_dir", "write_json", "save_npz"]


BEFORE_RENAME: list[Callable[[Path, Path], None]] = []
"""Called as ``hook(tmp, path)`` when a temporary is complete, before it is renamed onto
``path`` (:mod:`runtime.outrun` records there what a stage writes, so that a rerun knows it even
after a kill, and refuses to replace what is not the stage's). A hook that raises stops the
write; the temporary is removed."""


def _before_rename(tmp: Path, path: Path) -> None:
    for hook in BEFORE_RENAME:
        hook(tmp, path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def _temporary(make: Callable[[], Path], remove: Callable[[Path], None]) -> Iterator[Path]:
    """Yield the temporary ``make()`` creates, made with the stop signals held
    (:func:`runtime.stops.stops_held`) so that none lands between its creation and the ``try``
    that removes it: a stop that came while it was made, or at any point after, ends in
    ``remove(tmp)`` unless the block moved it away."""
    tmp = None
    try:
        with stops_held():
            tmp = make()
        yield tmp
    finally:
        if tmp is not None and tmp.exists():
            remove(tmp)


#: bytes a temporary's name adds to the name of the file or folder it stands for
#: (``.`` + stem + ``.`` + 8 random characters + ``.tmp`` + suffix): an output's own name must
#: leave room for them under the file system's name limit (runtime.outcheck checks ``--out``)
TEMP_NAME_EXTRA = 14


def _temp_file(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs follow the umask
    except BaseException:
        os.unlink(tmp)
        raise
    return Path(tmp)


def _temp_dir(path: Path) -> Path:
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())
    except BaseException:
        tmp.rmdir()
        raise
    return tmp


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the suffix so that writers that dispatch on it still work. A stop
    signal at any point, its creation included, leaves no temporary file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _temporary(lambda: _temp_file(path), Path.unlink) as tmp:
        yield tmp
        _before_rename(tmp, path)
        os.replace(tmp, path)


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``path``; on success it replaces ``path``. A stop
    signal at any point, the folder's creation included, leaves no temporary folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with _temporary(lambda: _temp_dir(path), lambda t: shutil.rmtree(t, ignore_errors=True)) as tmp:
        yield tmp
        _before_rename(tmp, path)
        if path.exists():
            with stops_held():  # the swap is whole: no stop leaves the old version aside
                old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
                os.replace(path, old / "x")
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)


@contextlib.contextmanager
def scratch_dir(prefix: str, parent: str | Path | None = None) -> Iterator[Path]:
    """A scratch folder (``tempfile.mkdtemp`` in ``parent``, default the system's) removed when
    the block ends, however it ends, a stop signal at its creation included; a folder the
    block moved away stays where it went."""
    with _temporary(lambda: Path(tempfile.mkdtemp(prefix=prefix, dir=parent)),
                    lambda t: shutil.rmtree(t, ignore_errors=True)) as tmp:
        yield tmp


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None  # JSON has no NaN/Inf: a missing value is null
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically. NaN/Inf become null; numpy is converted."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n")
    return Path(path)


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return Path(path)
