"""The output rule's own files and the records in them (:mod:`runtime.outdir` gives the rule).

A stage vouches for a file only by a record of it: its :data:`Stamp` as the stage wrote it.
The records live in three files of each output folder, each opened without following a
symbolic link and refused with one line (:class:`OutputFolderError`) where this version does not
read it:

* ``<out>/.stage`` (:data:`MARKER`): line 1 the stage's name; then ``#files`` and one record
  per line of what the stage wrote, or, while a run has not finished, ``#kept``, the records of
  the paths that were there before it, ``#wrote`` and the records of what the run has written
  so far (each appended before the file is renamed into place). A replacing stage's run that
  has not finished leaves line 1 alone.
* A record is a JSON list: ``[path, size, mtime_ns, inode, ctime_ns, blake2b]`` for a file or
  link, ``[path]`` for a folder (ending in ``/``) or a kept entry; paths are relative,
  ``/``-separated.
* ``<folder>/.stage.files`` (:data:`LEDGER`): one JSON list ``[name, stage, size, mtime_ns,
  inode, ctime_ns, blake2b]`` per file output written into the folder, appended as it is
  written; the last line of a name and stage counts.
* ``<out>/.stage.lock`` (:data:`LOCK`): the writer's pid (:mod:`runtime.outlock`).

It holds the names of these files, reading, replacing and appending them, the stamps and the
records, the entries of a folder that count when it is compared with its records
(:func:`_tree`), and :class:`OutputFolderError`, the one error of the whole rule: it lives here,
in the rule's lowest module, because reading these files already refuses. docs/contracts.md
gives the same formats.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

from runtime import atomic
from runtime.stops import stops_held

__all__ = ["MARKER", "LOCK", "LEDGER", "TOOL_FILES", "WORKFLOW_DIRS", "OutputFolderError", "Stamp", "PathLike"]

MARKER = ".stage"
"""Marker file in every folder a stage creates (its format: the module docstring)."""

LOCK = ".stage.lock"
"""Lock file of the one writer of a folder (``flock``; holds the writer's pid)."""

LEDGER = ".stage.files"
"""Ledger of the file outputs written into a folder (its format: the module docstring)."""

_FILES = "#files"
_KEPT = "#kept"
_WROTE = "#wrote"
_OWN = frozenset({MARKER, LOCK, LEDGER})

TOOL_FILES = frozenset({".snakemake_timestamp"})
"""Entries a workflow tool adds to a stage's folder (Snakemake touches this one in every
``directory()`` output it has completed); they are not the user's files."""

WORKFLOW_DIRS = frozenset({"logs", "benchmarks"})
"""Folders the workflow's ``log:`` and ``benchmark:`` paths put inside a job's output folder
before the job starts (workflow/rules/*.smk, e.g. ``n3/oracle/logs/``). A folder holding only
these counts as empty for a stage that writes beside them; a stage that replaces its folder
whole (which would delete them) still refuses it."""

PathLike = str | os.PathLike
Stamp = tuple[int, int, int, int, str]
"""What identifies a file as written: (size, ``mtime_ns``, inode, ``ctime_ns``, BLAKE2b-128 of
its bytes), of the entry itself (a link is not followed: its target's name is hashed). A file
matches its record when its size and hash are the record's (:func:`_matches`); equal size,
times and inode spare the hashing, a copy of the folder (new inodes) is hashed."""


class OutputFolderError(ValueError):
    """An ``--out`` the stage must not write to (one line naming both paths)."""


def _resolved(p: PathLike) -> Path:
    """``p`` absolute, links resolved: how the rule compares paths and keys its folders."""
    return Path(os.path.abspath(os.fspath(p))).resolve()  # as the stage will open it (no ~ expansion)


# --- the rule's own files: opened without following a link ------------------------------------

def _link_refused(path: Path) -> OutputFolderError:
    return OutputFolderError(f"{path} is a symbolic link or not a plain file where the output rule keeps its own "
                             "file: remove it and run the command again (nothing was changed)")


def _read_own(path: Path) -> str | None:
    """The text of the rule's file ``path`` (marker, ledger), opened without following a link;
    None when there is none.

    Raises:
        OutputFolderError: a link, a folder or another non-plain file stands there.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
            raise _link_refused(path) from None
        raise
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise _link_refused(path)
        return f.read().decode("utf-8", errors="surrogateescape")


def _write_own(path: Path, text: str) -> None:
    """Replace the rule's file ``path`` whole: a temporary beside it (created anew, never
    through a link), renamed over it (a link standing there is replaced, not followed). A stop
    signal that comes meanwhile waits until it is whole (:func:`runtime.stops.stops_held`)."""
    with stops_held():
        _replace_own(path, text)


def _replace_own(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f"{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", errors="surrogateescape") as f:
            f.write(text)
        os.chmod(tmp, 0o666 & ~atomic._umask())  # as a file the stage writes
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _append_own(path: Path, lines: list[str]) -> None:
    """Append ``lines`` to the rule's file ``path`` (created if absent), never through a link."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.EISDIR, errno.ENXIO):
            raise _link_refused(path) from None
        raise
    with stops_held(), os.fdopen(fd, "a", encoding="utf-8", errors="surrogateescape") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise _link_refused(path)
        f.write("".join(ln + "\n" for ln in lines))


# --- records: what a stage wrote, with its stamp ---------------------------------------------

def _digest(p: Path) -> str | None:
    """BLAKE2b-128 (hex) of the bytes of the file ``p``, or of a link's target name; None when
    it cannot be read."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    try:
        if os.path.islink(p):
            h.update(os.fsencode(os.readlink(p)))
            return h.hexdigest()
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            return None
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _stamp(p: Path) -> Stamp | None:
    """The :data:`Stamp` of the entry ``p`` itself (a link is not followed); None when there is
    none or it cannot be read."""
    try:
        st = os.lstat(p)
    except OSError:
        return None
    digest = _digest(p)
    return None if digest is None else (st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns, digest)


def _matches(p: Path, rec: Stamp | None) -> bool:
    """The file (or link) ``p`` is there and is what ``rec`` recorded: same size and bytes
    (same size, times and inode: no need to read it)."""
    if rec is None:
        return False
    try:
        st = os.lstat(p)
    except OSError:
        return False
    if stat.S_ISDIR(st.st_mode) or st.st_size != rec[0]:
        return False
    if (st.st_mtime_ns, st.st_ino, st.st_ctime_ns) == rec[1:4]:
        return True
    return _digest(p) == rec[4]


def _entry(rel: str, stamp: Stamp | None) -> str:
    """One record line: ``[path]`` for a folder (``rel`` ends in ``/``) or an entry kept as it
    was, else ``[path, *stamp]``."""
    return json.dumps([rel] if stamp is None else [rel, *stamp], ensure_ascii=True)


def _stamps(folder: Path, rels: Iterable[str]) -> list[str]:
    """Record lines of the entries ``rels`` of ``folder`` as they are now (gone ones left out)."""
    out = []
    for rel in rels:
        st = None if rel.endswith("/") else _stamp(folder / rel)
        if rel.endswith("/") or st is not None:
            out.append(_entry(rel, st))
    return out


class _Unreadable(ValueError):
    """A line of a marker or ledger that this version does not read (the reason)."""


def _relative(rel: object) -> str:
    if not isinstance(rel, str) or not rel or rel.startswith("/") or "\0" in rel or any(
            part in ("", ".", "..") for part in rel.rstrip("/").split("/")):
        raise _Unreadable(f"{rel!r} is not a relative path inside the folder")
    return rel


def _record(line: str) -> tuple[str, Stamp | None]:
    """(path, stamp or None for a folder or a kept entry) of a marker's record line."""
    try:
        rec = json.loads(line)
    except ValueError:
        raise _Unreadable("not a record (markers of older versions list bare paths, without stamps)") from None
    if not isinstance(rec, list) or not rec:
        raise _Unreadable("not a record")
    rel = _relative(rec[0])
    if len(rec) == 1:
        return rel, None
    if _is_stamp(rec[1:]) and not rel.endswith("/"):
        return rel, tuple(rec[1:])
    raise _Unreadable("not a record [path, size, mtime_ns, inode, ctime_ns, blake2b] or [path]")


def _is_stamp(v: list) -> bool:
    return (len(v) == 5 and all(type(x) is int and x >= 0 for x in v[:4]) and isinstance(v[4], str)
            and len(v[4]) == 32 and all(c in "0123456789abcdef" for c in v[4]))


@dataclass
class _Marker:
    """A folder's marker as read: its stage (None: no marker), its kind (:data:`_FILES`,
    :data:`_KEPT`, or None for a replacing stage's unfinished run), its records, and, under
    :data:`_KEPT`, the records of what the unfinished run wrote."""

    stage: str | None = None
    kind: str | None = None
    entries: dict[str, Stamp | None] = field(default_factory=dict)
    wrote: dict[str, Stamp | None] = field(default_factory=dict)

    @property
    def written(self) -> dict[str, Stamp | None]:
        """What the stage is recorded to have written (all of it, or the unfinished run's)."""
        return self.entries if self.kind == _FILES else self.wrote if self.kind == _KEPT else {}


def _marker(folder: Path) -> _Marker:
    """``folder``'s marker, read without following a link.

    Raises:
        OutputFolderError: a marker this version does not read (one line, naming it and its line).
    """
    path = folder / MARKER
    text = _read_own(path)
    if text is None:
        return _Marker()
    lines = text.splitlines()
    try:
        if not lines or not lines[0].strip() or lines[0].startswith(("#", "[")):
            raise _Unreadable("line 1 is not a stage name")
        m = _Marker(stage=lines[0].strip())
        if len(lines) == 1:
            return m
        if lines[1] not in (_FILES, _KEPT):
            raise _Unreadable(f"line 2 is not {_FILES} or {_KEPT} (markers of older versions list bare names)")
        m.kind = lines[1]
        into = m.entries
        for i, line in enumerate(lines[2:], 3):
            if line == _WROTE and m.kind == _KEPT and into is m.entries:
                into = m.wrote
                continue
            try:
                rel, st = _record(line)
            except _Unreadable as exc:
                raise _Unreadable(f"line {i}: {exc}") from None
            into[rel] = st
        return m
    except _Unreadable as exc:
        raise OutputFolderError(f"{path} is not a marker this version reads ({exc}): move the folder's files away "
                                "(they count as the user's) or choose a new folder; nothing was changed") from None


def _ledger(folder: Path) -> list[tuple[str, str, Stamp]]:
    """The records (name, stage, stamp) of ``folder``'s :data:`LEDGER`, in order.

    Raises:
        OutputFolderError: a ledger this version does not read (one line; it is never appended to).
    """
    path = folder / LEDGER
    text = _read_own(path)
    out = []
    for i, line in enumerate((text or "").splitlines(), 1):
        try:
            rec = json.loads(line)
        except ValueError:
            rec = None
        ok = (isinstance(rec, list) and len(rec) == 7 and isinstance(rec[0], str) and isinstance(rec[1], str)
              and rec[0] and "/" not in rec[0] and rec[0] not in (".", "..") and rec[1] and _is_stamp(rec[2:]))
        if not ok:
            why = ("a ledger of an older version, without stamps" if "\t" in line and not line.startswith("[")
                   else "not a record [name, stage, size, mtime_ns, inode, ctime_ns, blake2b]")
            raise OutputFolderError(f"{path} line {i} is {why}: delete the ledger (the files it lists then count "
                                    "as the user's and are never replaced) or choose another folder; nothing "
                                    "was changed")
        out.append((rec[0], rec[1], tuple(rec[2:])))
    return out


def _ledger_writers(path: Path) -> tuple[set[str], set[str]]:
    """(stages whose ledger record of the file ``path`` matches it now, stages recorded as its
    writers at all)."""
    last: dict[str, Stamp] = {}
    for name, stage, st in _ledger(path.parent):
        if name == path.name:
            last[stage] = st
    return {s for s, st in last.items() if _matches(path, st)}, set(last)


def _tree(folder: Path) -> list[str]:
    """Every entry under ``folder`` as a relative posix path (folders end in ``/``; links are
    entries, never followed), the rule's own files (and their temporaries) and the tools' files
    at the top excluded; sorted, parents before children."""
    out: list[str] = []
    for root, dirs, files in os.walk(folder, followlinks=False):
        rel = Path(root).relative_to(folder)
        top = rel == Path(".")
        for d in list(dirs):
            p = (rel / d).as_posix()
            if (Path(root) / d).is_symlink():
                dirs.remove(d)
                out.append(p)
            else:
                out.append(p + "/")
        for f in files:
            if top and (f in _OWN or f in TOOL_FILES):
                continue
            out.append((rel / f).as_posix())
    return sorted(out)
