"""One writer per output folder: the lock of a folder (:data:`runtime.ledger.LOCK`).

:func:`runtime.outdir.prepare_out` takes an exclusive ``flock`` on the folder's lock file for the
life of the command and writes the holder's pid into it. A second command on the same folder
is refused with one line naming that pid; the lock of a killed process is released by the
kernel, so it is taken over (with a log line). The lock file is opened without following a
symbolic link; :func:`release_locks` gives every lock up, at exit and when a stage command
ends.
"""

from __future__ import annotations

import atexit
import errno
import logging
import os
import stat
from pathlib import Path

from runtime.ledger import LOCK, OutputFolderError, PathLike, _link_refused, _resolved

__all__ = ["release_locks"]

log = logging.getLogger("runtime.outdir")  # the output rule's logger: its lines name runtime.outdir


_LOCKS: dict[Path, int] = {}
"""Folders this process holds the writer's lock of -> the lock file's descriptor."""


def _lock(folder: Path, out: PathLike) -> None:
    """Take the writer's lock of ``folder`` for this process (this module's docstring); the lock file
    is opened without following a link.

    Raises:
        OutputFolderError: another live process holds it (one line naming its pid), or a link
            or another non-plain file stands where the lock file goes.
    """
    import fcntl

    key = _resolved(folder)
    if key in _LOCKS:
        return
    path = folder / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
        except OSError as exc:
            if exc.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
                raise _link_refused(path) from None
            raise
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise _link_refused(path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise OutputFolderError(f"--out {out} is being written by another process (pid {holder}, lock "
                                    f"{path}): wait for it to finish or choose another folder") from None
        try:
            same = os.fstat(fd).st_ino == os.lstat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed the file as we opened it: lock the new one
    old = os.read(fd, 64).decode(errors="replace").strip()
    if old and old != str(os.getpid()):
        log.info("taking over the lock of %s: process %s has ended", folder, old)
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _LOCKS[key] = fd


def release_locks() -> None:
    """Give up every writer's lock this process holds (removing the lock files). Runs at exit
    and when :func:`runtime.outdir.run_stage` ends."""
    for key in list(_LOCKS):
        _unlock(key)


def _unlock(key: Path) -> None:
    """Give up the lock of the folder ``key`` (resolved), removing its lock file if it is ours."""
    fd = _LOCKS.pop(key, None)
    if fd is None:
        return
    try:
        if os.fstat(fd).st_ino == os.lstat(key / LOCK).st_ino:
            os.unlink(key / LOCK)
    except OSError:
        pass
    try:
        os.close(fd)
    except OSError:
        pass


atexit.register(release_locks)
