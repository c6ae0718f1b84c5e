"""The one output rule of every stage command: a stage writes only what it owns.

Every stage CLI calls :func:`prepare_out` before it reads or writes anything:

* ``--out`` must not be, contain, or lie inside any input path of the command (compared
  after resolving symlinks). Where the output's place is inside an input by design (the
  results-tree readers' report folders, ``camio split``'s ``scene/split.json``) the command
  names that input in ``may_hold_out``: its ``--out`` may lie inside it, never be it or
  contain it. ``--out`` itself (a folder, or a file and its folder) may not be a symbolic
  link, nor have a name longer than its file system holds (less what a temporary's name adds,
  :data:`runtime.atomic.TEMP_NAME_EXTRA`) or a path of PATH_MAX bytes or more.
* A folder ``--out`` that exists must be empty (Snakemake creates output folders before a
  job), or hold the marker file :data:`MARKER` naming this same stage: a rerun of the stage
  into its own folder works, any other non-empty folder is refused.
* A folder holding only the workflow's ``logs/`` and ``benchmarks/`` (:data:`WORKFLOW_DIRS`)
  counts as empty, except for a stage that replaces its folder whole.
* The marker records every file the stage wrote with its stamp (size, ``mtime_ns``, inode;
  :func:`seal_out`), and while a run goes on, what was there before it (:data:`_KEPT`) and
  each file the run writes through :mod:`runtime.atomic`, before it is renamed into place
  (:data:`_WROTE`). A recorded file counts as the stage's only while its stamp still matches:
  a rerun refuses a folder where a file the stage wrote has changed (a user's file put where
  an output stood), and never writes over a file that was there before its run and is not
  its own (:func:`_before_rename`).
* A stage that replaces its whole folder (``replaces=True``: ``camio convert``, ``camio
  synth``, ``evaluation report``, ``evaluation study``, the workflow's ``views link``)
  refuses a folder that holds anything it did not write (a user's file in ``images/``, a
  ``sparse/1/`` model, or anything at all after a run of it that did not finish), so a
  file the stage did not write is never deleted.
* A rerun of any other stage refuses while a foreign entry lies inside a folder the stage
  wrote (it would replace that folder whole, e.g. ``sparse/0``), and keeps what lies beside
  its outputs.
* A stage that writes a folder of results beside whatever else is there (``fresh=True``:
  ``splat_train render``, ``splat_train testpose``, the COLMAP baseline) first removes,
  file by file, what its own earlier run wrote and still matches its record (after a run
  that did not finish: what that run recorded as it wrote), so the folder never mixes two
  runs; anything else stays, whenever it was put there.
* A file ``--out`` that exists is replaced only if this command (or, for the file names
  given in ``same_file_as``, another stage: ``split.json`` of ``camio convert``) wrote it
  and it has not changed since: the folder's ledger :data:`LEDGER` (or a replacing stage's
  marker) records who wrote which file, with its stamp. A photo, a camera file or a split
  the user made, or put where such a file stood, is refused, never overwritten.
* A marker or ledger this version cannot read (malformed, or of an older version without
  stamps) is refused with one line, never appended to; the marker, the ledger and the lock
  are opened without following a symbolic link, and a link where one of them would be is
  refused.
* One writer per output folder: :func:`prepare_out` takes an exclusive lock
  (:data:`LOCK`, ``flock``, holding the writer's pid) for the life of the command. A
  second command on the same folder is refused with one line naming the holder's pid; the
  lock of a killed process is released by the kernel, so it is taken over (with a log line).
* SIGTERM, SIGINT and SIGHUP end a command through :class:`Stopped` (:func:`run_stage`,
  :mod:`runtime.stops`, also after pycolmap installed its own handler), so every ``finally``
  runs: no temporary file or folder is left, the lock is given up, the marker says the run did
  not finish; one line, exit code 128 + the signal (SIGHUP 129, SIGINT 130, SIGTERM 143).
* A name read from a file (a split, an image list, a COLMAP model, a ``predictions.npz``) is
  a plain file name, listed once (:mod:`runtime.names`; :func:`check_name` and
  :func:`check_name_list` are handed on here).

Every refusal is an :class:`OutputFolderError` (a ``ValueError``), one line naming both
paths; the stage CLIs print it and exit with code 2 (:func:`run_stage`, the ending they share).
"""

from __future__ import annotations

import atexit
import errno
import json
import logging
import os
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping

from runtime import atomic
from runtime.names import check_name, check_name_list  # noqa: F401  (the name rule, handed on)
from runtime.stops import Stopped, stop_line, stopping, stops_caught, stops_held  # noqa: F401  (Stopped handed on)

__all__ = ["MARKER", "LOCK", "LEDGER", "OutputFolderError", "prepare_out", "seal_out", "check_out", "tidy_outs",
           "run_stage", "typed_line", "release_locks", "check_name", "check_name_list", "finish_outs",
           "Stopped"]

MARKER = ".stage"
"""Marker file in every folder a stage creates: line 1 the stage name; then, for a stage that
has finished, line 2 :data:`_FILES` and one record per line of what it wrote; while a run
goes on, :data:`_KEPT`, the records of what was there before it, :data:`_WROTE` and the
records of what the run has written so far. A record is a JSON list: ``[path, size,
mtime_ns, inode]`` for a file or link, ``[path]`` for a folder (its path ends in ``/``);
paths are relative, ``/``-separated. A replacing stage's run that has not finished leaves
line 1 alone."""

LOCK = ".stage.lock"
"""Lock file of the one writer of a folder (``flock``; holds the writer's pid)."""

LEDGER = ".stage.files"
"""Ledger of the file outputs written into a folder: one JSON list ``[name, stage, size,
mtime_ns, inode]`` per line, appended as each file is written (the last line of a name and
stage counts)."""

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

log = logging.getLogger(__name__)


_PREPARED: dict[Path, tuple[Path, ...]] = {}
"""Folders :func:`prepare_out` marked in this process -> the folders it created for them
(the folder and its new parents, deepest first; empty when the folder was there)."""


def tidy_outs() -> None:
    """Undo :func:`prepare_out` where the stage then wrote nothing (it failed early): remove
    the marker, and the folder and its parents where :func:`prepare_out` created them. A failed stage leaves
    nothing behind. Runs at interpreter exit; the CLIs also call it on their error paths."""
    release_locks()
    _STAGES.clear()  # a failed command records nothing more: its marker says the run did not finish
    _BEFORE.clear()
    for out, (_stage, created) in list(_PREPARED_FILES.items()):
        _PREPARED_FILES.pop(out, None)
        if out.exists() or out.is_symlink():
            continue
        for made in created:  # the folders prepare_out made for a file it then did not write
            try:
                made.rmdir()
            except OSError:
                break
    for folder, created in list(_PREPARED.items()):
        _PREPARED.pop(folder, None)
        try:
            if folder.is_dir() and MARKER in {e.name for e in folder.iterdir()} and not [
                    e for e in folder.iterdir() if e.name not in _OWN and not (e.name in WORKFLOW_DIRS and e.is_dir())]:
                (folder / MARKER).unlink()
                for made in created:  # the folder and the parents prepare_out made, while empty
                    made.rmdir()
        except OSError:
            pass


atexit.register(tidy_outs)


class OutputFolderError(ValueError):
    """An ``--out`` the stage must not write to (one line naming both paths)."""


def _check_name_lengths(out: PathLike, flag: str = "--out") -> None:
    """Refuse an ``--out`` with a name longer than its file system holds (NAME_MAX of its
    nearest existing folder in bytes, less :data:`runtime.atomic.TEMP_NAME_EXTRA` for the last
    name, whose temporary is written first) or a path of PATH_MAX bytes or more, before a call
    on it fails with ``ENAMETOOLONG`` (a bare OSError) or leaves a temporary behind."""
    path = Path(os.path.abspath(os.fspath(out)))
    name_max, path_max = 255, 4096
    for a in [path, *path.parents]:
        try:
            if a.is_dir():
                name_max, path_max = os.pathconf(a, "PC_NAME_MAX"), os.pathconf(a, "PC_PATH_MAX")
                break
        except (OSError, ValueError):  # too long to ask about, or no such limit: the next one up
            continue
    size = len(os.fsencode(path))
    if size >= path_max:
        raise OutputFolderError(f"{flag} {str(out)[:60]}...: the path is {size} bytes, longer than the file system "
                                f"allows ({path_max - 1}); choose a shorter path")
    parts = path.parts[1:]
    for i, part in enumerate(parts):
        limit = name_max - (atomic.TEMP_NAME_EXTRA if i == len(parts) - 1 else 0)
        if len(os.fsencode(part)) > limit:
            raise OutputFolderError(f"{flag} {str(out)[:60]}...: the name {part[:30]}... is {len(os.fsencode(part))} "
                                    f"bytes, over the {limit} this file system leaves for it; choose a shorter name")


def _resolved(p: PathLike) -> Path:
    return Path(os.path.abspath(os.fspath(p))).resolve()  # as the stage will open it (no ~ expansion)


def _inputs(inputs: Mapping[str, PathLike | Iterable[PathLike] | None]) -> list[tuple[str, Path]]:
    """(option name, resolved path) for every input given; lists (``nargs``) are flattened."""
    out: list[tuple[str, Path]] = []
    for name, val in inputs.items():
        if val is None:
            continue
        vals = [val] if isinstance(val, (str, os.PathLike)) else list(val)
        out.extend((name, _resolved(v)) for v in vals if v is not None and os.fspath(v) != "")
    return out


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


def _changed(folder: Path, recorded: Mapping[str, Stamp | None]) -> list[str]:
    """Files ``recorded`` as written whose entry in ``folder`` is there but differs from its
    record, and that no stage's ledger vouches for either (``camio split`` replacing the
    ``split.json`` of ``camio convert``)."""
    out = []
    for rel, st in recorded.items():
        if st is None:
            continue
        if os.path.lexists(folder / rel) and not _matches(folder / rel, st) and not _ledger_writers(folder / rel)[0]:
            out.append(rel)
    return sorted(out)


def _foreign(folder: Path, written: Iterable[str], skip_workflow: bool) -> list[str]:
    """Entries of ``folder`` (:func:`_tree`) that ``written`` does not list."""
    written = set(written)
    out = []
    for p in _tree(folder):
        top = p.split("/", 1)[0]
        if skip_workflow and top in WORKFLOW_DIRS and (folder / top).is_dir():
            continue
        if p not in written:
            out.append(p)
    return out


def check_out(out: PathLike, inputs: Mapping[str, PathLike | Iterable[PathLike] | None], stage: str, *,
              folder: bool = True, may_hold_out: Iterable[str] = (), replaces: bool = False,
              same_file_as: Mapping[str, Iterable[str]] | None = None,
              derived: Callable[[Path], bool] | None = None, fresh: bool = False, flag: str = "--out") -> Path:
    """Refuse an ``--out`` that breaks the output rule (module docstring); write nothing.

    Args:
        out: the command's ``--out`` (a folder, or a file when ``folder`` is False).
        inputs: option name (e.g. ``"--images"``) -> input path, list of paths, or None.
        stage: the stage's name as written in the marker (e.g. ``"camio convert"``).
        folder: ``out`` is a folder (the non-empty rule applies) or a file.
        may_hold_out: input names whose folder may hold ``out`` (results-tree readers).
        replaces: the stage replaces its folder whole (its writer is ``runtime.atomic.atomic_dir``
            on ``out``): only its own entries, in every subfolder, may be there.
        same_file_as: for a file ``out``: other stage -> the names of its files that this
            command may replace (``camio split`` replaces the ``split.json`` that ``camio
            convert`` wrote, and nothing else of it).
        derived: for a file ``out``: True for a file that counts as the command's own
            although no record says so (weights that load as such).
        flag: the option that named ``out``, as every refusal names it (``--video``, ``--doc``).

    Returns:
        ``out`` as a Path.

    Raises:
        OutputFolderError: one line naming ``out`` and the input or entry at fault.
    """
    out_p = Path(out)
    if not os.fspath(out).strip():
        raise OutputFolderError(f"{flag} is empty: name the {'folder' if folder else 'file'} {stage} writes")
    _check_name_lengths(out, flag)
    o = _resolved(out)
    if o == Path(o.anchor):
        raise OutputFolderError(f"{flag} {out} is the file system's root: choose a folder of its own")
    for up in Path(os.path.abspath(os.fspath(out))).parents:  # the nearest that exists must be a folder
        if up.exists() or up.is_symlink():
            if not up.is_dir():
                raise OutputFolderError(f"{flag} {out}: {up} is a file, not a folder; name a path in a folder")
            break
    hold_ok = set(may_hold_out)
    given = _inputs(inputs)
    for name, p in given:
        if o == p:
            raise OutputFolderError(f"{flag} {out} is the input {name} {p}: choose another output "
                                    "(a stage never writes over its inputs)")
    for name, p in given:
        if p in o.parents and name not in hold_ok:
            raise OutputFolderError(f"{flag} {out} lies inside the input {name} {p}: choose an output "
                                    "outside the inputs")
        if o in p.parents:
            raise OutputFolderError(f"{flag} {out} contains the input {name} {p}: choose an output "
                                    "folder that holds none of the inputs")
    parent = out_p.parent if str(out_p.parent) else Path(".")
    links = [(out_p, "folder" if folder else "file")] + ([] if folder else [(parent, "folder")])
    for p, kind in links:
        if p.is_symlink():
            raise OutputFolderError(f"{flag} {out}: {p} is a symbolic link; name the {kind} itself, {stage} never "
                                    "writes through a link (nothing was changed)")
    if not folder:
        if o.is_dir():
            raise OutputFolderError(f"{flag} {out} is a folder; {stage} writes a file there: name the file")
        if o.name in _OWN:
            raise OutputFolderError(f"{flag} {out}: {o.name} is the output rule's own file; name another file")
        if o.exists():
            writers, recorded = _file_writers(o.parent, o.name)
            kin = {other for other, names in (same_file_as or {}).items() if o.name in set(names)}
            if not writers & ({stage} | kin) and not (derived is not None and o.is_file() and derived(o)):
                who = (f"was written by `{sorted(writers)[0]}`" if writers
                       else f"has changed since `{sorted(recorded)[0]}` wrote it" if recorded
                       else f"was not written by `{stage}`")
                raise OutputFolderError(f"{flag} {out} exists and {who}: {stage} never replaces a file it did not "
                                        "write; move it away or name a new file (nothing was changed)")
        return out_p
    if o.exists() and not o.is_dir():
        raise OutputFolderError(f"{flag} {out} is a file, not a folder: choose a folder for {stage}")
    if o.is_dir():
        entries = sorted(e.name for e in o.iterdir() if e.name not in _OWN and e.name not in TOOL_FILES
                         and not (not replaces and e.name in WORKFLOW_DIRS and e.is_dir()))
        for own in _OWN:
            if (o / own).is_symlink():
                raise _link_refused(o / own)
        m = _marker(o)
        if entries and m.stage != stage:
            who = f"was written by `{m.stage}`" if m.stage else f"has no {MARKER} marker of `{stage}`"
            raise OutputFolderError(f"{flag} {out} is not empty ({len(entries)} entries, e.g. {entries[0]}) and "
                                    f"{who}: choose an empty or new folder (nothing was changed)")
        if m.stage == stage:
            changed = _changed(o, m.written)
            if changed:
                raise OutputFolderError(f"{flag} {out} holds {o / changed[0]}, which `{stage}` wrote but which has "
                                        "changed since (size, time or inode): a rerun would replace or remove it; "
                                        "move it away or choose a new folder (nothing was changed)")
        if replaces and m.stage == stage and m.kind != _KEPT:
            foreign = _foreign(o, m.entries, skip_workflow=False)  # a run that did not finish: all is foreign
            if foreign:
                raise OutputFolderError(f"{flag} {out} holds {o / foreign[0].rstrip('/')}, which `{stage}` did not "
                                        f"write and would replace: move it away or choose a new folder")
        if not replaces and not fresh and m.stage == stage and m.kind == _FILES:
            inside = _inside_own(o, m.entries)
            if inside:
                raise OutputFolderError(f"{flag} {out} holds {o / inside[0].rstrip('/')} inside a folder that `{stage}` "
                                        "wrote and replaces on a rerun: move it away or choose a new folder")
    return out_p


def _inside_own(folder: Path, written: Mapping[str, Stamp | None]) -> list[str]:
    """Entries of ``folder`` the stage did not write that lie inside a folder it did write (a
    rerun replaces such a folder whole, e.g. ``sparse/0``); entries beside its outputs at the
    top level are not among them."""
    out = []
    for p in _tree(folder):
        if p in written:
            continue
        parts = p.rstrip("/").split("/")
        if any("/".join(parts[:k]) + "/" in written for k in range(1, len(parts))):
            out.append(p)
    return out


def _file_writers(folder: Path, name: str) -> tuple[set[str], set[str]]:
    """(the stages recorded as writers of the file ``folder/name`` whose record matches it now,
    every stage recorded as its writer): the folder's :data:`LEDGER` and the marker of a stage
    that has finished and lists the file."""
    writers, recorded = _ledger_writers(folder / name)
    m = _marker(folder)
    if m.stage and m.kind == _FILES and name in m.entries:
        recorded.add(m.stage)
        if _matches(folder / name, m.entries[name]):
            writers.add(m.stage)
    return writers, recorded - writers


_PREPARED_FILES: dict[Path, tuple[str, tuple[Path, ...]]] = {}
"""File outputs :func:`prepare_out` prepared in this process -> (their stage, the folders it
created for them)."""


def _record_file(out: Path, stage: str) -> None:
    """Append ``out``'s record (its stamp as written by ``stage``) to its folder's :data:`LEDGER`,
    unless its last record of ``stage`` already matches."""
    writers, _ = _ledger_writers(out)
    st = _stamp(out) if stage not in writers else None
    if st is not None:
        _append_own(out.parent / LEDGER, [json.dumps([out.name, stage, *st], ensure_ascii=True)])


_BEFORE: dict[Path, tuple[str, frozenset[str]]] = {}
"""Folders prepared in this process whose marker is :data:`_KEPT` -> (their stage, the
entries that were there before the run and are not its own)."""


def _before_rename(tmp: Path, path: Path) -> None:
    """:mod:`runtime.atomic`'s hook, called when ``tmp`` is complete and before it is renamed onto
    ``path``: inside a folder prepared in this process, refuse to replace an entry that was
    there before the run and is not the stage's, then record what is about to be written in
    the folder's marker (a file ``--out``: in its folder's ledger), so that a rerun after a
    kill knows it.

    Raises:
        OutputFolderError: ``path`` (or an entry inside the folder it replaces) was there
            before the run and the stage did not write it.
    """
    target = Path(os.path.realpath(path.parent)) / path.name
    owners = [f for f in _BEFORE if f in target.parents]
    folder = max(owners, key=lambda f: len(f.parts)) if owners else None
    if folder is not None:
        stage, before = _BEFORE[folder]
        rel = target.relative_to(folder).as_posix()
        hit = [p for p in before if p.rstrip("/") == rel or p.startswith(rel + "/")]
        hit = [p for p in hit if os.path.lexists(folder / p.rstrip("/"))]
        if hit:
            raise OutputFolderError(f"`{stage}` would replace {folder / hit[0].rstrip('/')}, which was in {folder} "
                                    "before it ran and which it did not write: move it away and run it again")
    if target in _PREPARED_FILES and tmp.is_file() and not tmp.is_symlink():
        st = _stamp(tmp)
        if st is not None:
            _ledger(target.parent)  # a ledger this version does not read is never appended to
            _append_own(target.parent / LEDGER,
                        [json.dumps([target.name, _PREPARED_FILES[target][0], *st], ensure_ascii=True)])
    if folder is None:
        return
    if tmp.is_dir() and not tmp.is_symlink():
        rels = [rel + "/"] + [f"{rel}/{p}" for p in _tree_all(tmp)]
        lines = [_entry(r, None if r.endswith("/") else _stamp(tmp / r[len(rel) + 1:])) for r in rels]
    else:
        lines = [_entry(rel, _stamp(tmp))]
    _append_own(folder / MARKER, lines)


def _tree_all(folder: Path) -> list[str]:
    """Every entry under ``folder`` (:func:`_tree` without leaving anything out)."""
    out = []
    for root, dirs, files in os.walk(folder, followlinks=False):
        rel = Path(root).relative_to(folder)
        out += [(rel / d).as_posix() + ("" if (Path(root) / d).is_symlink() else "/") for d in dirs]
        out += [(rel / f).as_posix() for f in files]
    return sorted(out)


atomic.BEFORE_RENAME.append(_before_rename)


_LOCKS: dict[Path, int] = {}
"""Folders this process holds the writer's lock of -> the lock file's descriptor."""


def _lock(folder: Path, out: PathLike) -> None:
    """Take the writer's lock of ``folder`` for this process (module docstring); the lock file
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
    and when :func:`run_stage` ends."""
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


def _matching(folder: Path, recorded: Mapping[str, Stamp | None]) -> list[str]:
    """Entries ``recorded`` that are in ``folder`` as recorded (folders: present as folders)."""
    out = []
    for rel, st in recorded.items():
        p = folder / rel.rstrip("/")
        if (rel.endswith("/") and p.is_dir() and not p.is_symlink()) or _matches(p, st):
            out.append(rel)
    return out


def _start_run(folder: Path, stage: str, remove: bool) -> None:
    """Begin a run of ``stage`` in ``folder``: with ``remove`` (a ``fresh`` stage) first remove,
    file by file, what its earlier run recorded and still matches (module docstring); then
    record what is there that is not the stage's as kept (:data:`_KEPT`), until
    :func:`seal_out`, and remember it for :func:`_before_rename`."""
    m = _marker(folder)
    own = set(_matching(folder, m.written)) if m.stage == stage else set()
    if remove and own:
        made = set()  # after a run that did not finish: the folders it made around its files
        if m.kind == _KEPT:
            made = {"/".join(p.rstrip("/").split("/")[:k]) + "/" for p in own
                    for k in range(1, p.rstrip("/").count("/") + 1)} - set(m.entries)
        gone = 0
        # deepest first, a folder after the files beside it (set order is random: one rule)
        for p in sorted(own | made, key=lambda q: (-q.rstrip("/").count("/"), q.endswith("/"), q)):
            target = folder / p.rstrip("/")
            try:
                if p.endswith("/"):
                    target.rmdir()  # only when empty: a user's file below keeps it
                else:
                    target.unlink()
                    gone += 1
            except OSError:
                pass
        if gone:
            log.info("removed %d files of the earlier `%s` run from %s", gone, stage, folder)
        own = set()
    present = _tree(folder)
    kept = [p for p in present if p not in own]
    _write_own(folder / MARKER, "\n".join([stage, _KEPT, *(_entry(p, None) for p in kept), _WROTE]) + "\n")
    _BEFORE[_resolved(folder)] = (stage, frozenset(kept))


_STAGES: dict[Path, str] = {}
"""Folders :func:`prepare_out` prepared in this process -> their stage (sealed by
:func:`finish_outs` when the command succeeds, unless :func:`seal_out` already did)."""

_SEALED: set[Path] = set()


def finish_outs() -> None:
    """Record what each folder prepared in this process received (:func:`seal_out`), for the
    folders the command did not seal itself, and the stamp of each file output it wrote
    without :mod:`runtime.atomic`. :func:`run_stage` calls it when the command succeeds; a
    command that failed leaves its marker saying its run did not finish."""
    for folder, stage in list(_STAGES.items()):
        _STAGES.pop(folder, None)
        if folder in _SEALED or not folder.is_dir():
            continue
        try:
            seal_out(folder, stage)
        except (OSError, OutputFolderError):
            pass
    for out, (stage, _created) in list(_PREPARED_FILES.items()):
        _PREPARED_FILES.pop(out, None)
        try:
            if out.is_file() and not out.is_symlink():
                _record_file(out, stage)
        except (OSError, OutputFolderError):
            pass
    _SEALED.clear()
    _BEFORE.clear()
    _PREPARED.clear()  # finished: a folder it wrote nothing into (no plot to draw) is still its output


def prepare_out(out: PathLike, inputs: Mapping[str, PathLike | Iterable[PathLike] | None], stage: str, *,
                folder: bool = True, may_hold_out: Iterable[str] = (), replaces: bool = False,
                fresh: bool = False, same_file_as: Mapping[str, Iterable[str]] | None = None,
                derived: Callable[[Path], bool] | None = None, flag: str = "--out") -> Path:
    """:func:`check_out`, then create a folder ``out``, take its writer's lock and mark it as
    ``stage``'s (a file ``out`` gets its parent folder created; its record goes into the
    folder's :data:`LEDGER` as it is written). A folder that cannot be written (read-only, no
    permission) is refused as one line too.

    Args:
        fresh: the stage writes a folder of results: remove its earlier run's files first
            (module docstring); call :func:`seal_out` with what it wrote when it has finished.

    Returns:
        ``out`` as a Path.
    """
    out_p = check_out(out, inputs, stage, folder=folder, may_hold_out=may_hold_out, replaces=replaces,
                      same_file_as=same_file_as, derived=derived, fresh=fresh, flag=flag)
    target = out_p if folder else (out_p.parent if str(out_p.parent) else Path("."))
    try:
        # held against stop signals: the folders, lock, marker and the records of them come together
        with stops_held():
            created = []  # the folders this call creates, deepest first (the parents too)
            probe = _resolved(target)
            while not probe.exists():
                created.append(probe)
                probe = probe.parent
            target.mkdir(parents=True, exist_ok=True)
            if folder:
                try:
                    _lock(target, out)
                    # again under the lock: another writer may have filled the folder meanwhile
                    check_out(out, inputs, stage, folder=folder, may_hold_out=may_hold_out, replaces=replaces,
                              fresh=fresh)
                except OutputFolderError:
                    _unlock(_resolved(target))
                    for made in created:  # leave no folder this call made
                        try:
                            made.rmdir()
                        except OSError:
                            break
                    raise
                owner = _marker(target).stage
                if not replaces:
                    _start_run(target, stage, remove=fresh)
                elif owner != stage:
                    _write_own(target / MARKER, stage + "\n")
                if owner != stage:
                    _PREPARED[_resolved(target)] = tuple(created)
                _STAGES[_resolved(target)] = stage
            else:
                if not os.access(target, os.W_OK | os.X_OK):
                    raise PermissionError(errno.EACCES, "Permission denied", str(target))
                _ledger(target)  # a ledger this version does not read is refused before anything is written
                _PREPARED_FILES[Path(os.path.realpath(target)) / out_p.name] = (stage, tuple(created))
    except OSError as exc:
        raise OutputFolderError(f"cannot write {flag} {out}: {exc.strerror or exc} ({exc.filename or target}); "
                                "choose a writable folder") from exc
    return out_p


def seal_out(out: PathLike, stage: str) -> Path:
    """Record in ``out``'s marker what ``stage`` wrote, with each file's stamp (call when the
    stage has finished): for a stage that replaced its folder whole, every file and folder in
    it, in every subfolder; otherwise everything but what was there before the run."""
    out_p = Path(out)
    m = _marker(out_p)
    kept = set(m.entries) if (m.stage == stage and m.kind == _KEPT) else set()
    names = [p for p in _tree(out_p) if p not in kept]
    _write_own(out_p / MARKER, "\n".join([stage, _FILES, *_stamps(out_p, names)]) + "\n")
    _SEALED.add(_resolved(out_p))
    _BEFORE.pop(_resolved(out_p), None)
    return out_p


def typed_line(exc: BaseException) -> str:
    """An error as one line after its type's name: ``FileNotFoundError: ...``."""
    return f"{type(exc).__name__}: {exc}"


def run_stage(log: logging.Logger, work: Callable[[], int | None], *,
              errors: tuple[type[BaseException], ...] = (ValueError, OSError),
              line: Callable[[BaseException], str] = str, traceback: bool = False) -> int:
    """What every stage CLI ends with: run ``work`` (it calls :func:`prepare_out` first, then
    the stage) and turn a bad input into one error line and exit code 2, a stop signal into one
    line and exit code 128 + the signal.

    Args:
        log: the stage's logger.
        work: the stage after its argument parsing; returns its exit code (None: 0).
        errors: what counts as a bad input when ``work`` raises it.
        line: the error line of such an error (:func:`typed_line` puts its type's name first).
        traceback: also log the traceback at debug level (shown with -v).

    Returns:
        ``work``'s exit code; 2 for a refusal of the output rule (:class:`OutputFolderError`,
        its own line) or an error of ``errors``; 128 + the signal for SIGTERM, SIGINT or SIGHUP
        (:mod:`runtime.stops`: 143, 130, 129); each after :func:`tidy_outs` (a failed or stopped
        stage leaves nothing behind).
    """
    with stops_caught():
        try:
            rc = int(work() or 0)
            if rc == 0:
                finish_outs()
            return rc
        except OutputFolderError as exc:
            tidy_outs()
            log.error("%s", exc)
            return 2
        except errors as exc:
            tidy_outs()
            if traceback:
                log.debug("traceback", exc_info=True)
            log.error("%s", line(exc))
            return 2
        except BaseException as exc:  # a stop, also one inside an import (an ImportError caused by it)
            if not isinstance(exc, (Stopped, KeyboardInterrupt)) and stopping() is None:
                raise
            tidy_outs()
            text, rc = stop_line(exc if isinstance(exc, (Stopped, KeyboardInterrupt)) else Stopped(stopping()))
            log.error("%s", text)
            return rc
        finally:
            release_locks()
