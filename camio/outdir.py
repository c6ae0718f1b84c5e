"""The one output rule of every stage command: a stage writes only what it owns.

Every stage CLI calls :func:`prepare_out` before it reads or writes anything:

* ``--out`` must not be, contain, or lie inside any input path of the command (compared
  after resolving symlinks). Where the output's place is inside an input by design (the
  results-tree readers' report folders, ``camio split``'s ``scene/split.json``) the command
  names that input in ``may_hold_out``: its ``--out`` may lie inside it, never be it or
  contain it.
* A folder ``--out`` that exists must be empty (Snakemake creates output folders before a
  job), or hold the marker file :data:`MARKER` naming this same stage: a rerun of the stage
  into its own folder works, any other non-empty folder is refused.
* A folder holding only the workflow's ``logs/`` and ``benchmarks/`` (:data:`WORKFLOW_DIRS`)
  counts as empty, except for a stage that replaces its folder whole.
* A stage that replaces its whole folder (``replaces=True``: ``camio convert``, ``camio
  synth``, ``evaluation report``, ``evaluation study``, the workflow's ``views link``)
  records in the marker every file and folder it wrote, in every subfolder
  (:func:`seal_out`); a rerun refuses a folder that holds anything else (a user's file in
  ``images/``, a ``sparse/1/`` model), so a file the stage did not write is never deleted.
* Every stage records in the marker what it wrote when it succeeds (:func:`finish_outs`,
  called by :func:`run_stage`); a rerun refuses while a foreign entry lies inside a folder
  the stage wrote (it would replace that folder whole, e.g. ``sparse/0``), and keeps what
  lies beside its outputs.
* A stage that writes a folder of results beside whatever else is there (``fresh=True``:
  ``splat_train render``, ``splat_train testpose``, the COLMAP baseline) first removes,
  file by file, what its own earlier run wrote (recorded in the marker; after a run that did not finish, everything
  but what was there before it), so the folder never mixes two runs; anything else stays.
* A file ``--out`` that exists is replaced only if this command (or, for the file names
  given in ``same_file_as``, another stage: ``split.json`` of ``camio convert``) wrote it:
  the folder's ledger :data:`LEDGER` (or a replacing stage's marker) records who wrote
  which file. A photo, a camera file or a split the user made is refused, never overwritten.
* One writer per output folder: :func:`prepare_out` takes an exclusive lock
  (:data:`LOCK`, ``flock``, holding the writer's pid) for the life of the command. A
  second command on the same folder is refused with one line naming the holder's pid; the
  lock of a killed process is released by the kernel, so it is taken over (with a log line).
* SIGTERM and SIGHUP end a command through :class:`Stopped` (:func:`run_stage`), so every
  ``finally`` runs and no temporary file or folder is left; exit code 128 + the signal.
* A name read from a file (a split, an image list, a COLMAP model, a ``predictions.npz``) is
  a plain file name, listed once (:mod:`camio.names`; :func:`check_name` and
  :func:`check_name_list` are handed on here).

Every refusal is an :class:`OutputFolderError` (a ``ValueError``), one line naming both
paths; the stage CLIs print it and exit with code 2 (:func:`run_stage`, the ending they share).
"""

from __future__ import annotations

import atexit
import errno
import logging
import os
import signal
from pathlib import Path
from typing import Callable, Iterable, Mapping

from camio.names import check_name, check_name_list  # noqa: F401  (the name rule, handed on)

__all__ = ["MARKER", "LOCK", "LEDGER", "OutputFolderError", "prepare_out", "seal_out", "check_out", "tidy_outs",
           "run_stage", "typed_line", "release_locks", "check_name", "check_name_list", "finish_outs",
           "Stopped"]

MARKER = ".stage"
"""Marker file in every folder a stage creates: line 1 the stage name; then, for a stage that
records what it wrote, line 2 :data:`_FILES` and one relative path per line (folders end in
``/``), or :data:`_KEPT` and the paths that were there before a run that has not finished.
(Markers of older versions list top-level names after line 1, without a header line.)"""

LOCK = ".stage.lock"
"""Lock file of the one writer of a folder (``flock``; holds the writer's pid)."""

LEDGER = ".stage.files"
"""Ledger of the file outputs written into a folder: one ``name<TAB>stage`` per line."""

_FILES = "#files"
_KEPT = "#kept"
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

log = logging.getLogger(__name__)


_PREPARED: dict[Path, tuple[Path, ...]] = {}
"""Folders :func:`prepare_out` marked in this process -> the folders it created for them
(the folder and its new parents, deepest first; empty when the folder was there)."""


def tidy_outs() -> None:
    """Undo :func:`prepare_out` where the stage then wrote nothing (it failed early): remove
    the marker, and the folder and its parents where :func:`prepare_out` created them. A failed stage leaves
    nothing behind. Runs at interpreter exit; the CLIs also call it on their error paths."""
    release_locks()
    _STAGES.clear()  # a failed command records nothing: its marker says the run did not finish
    for out, (entry, created) in list(_PREPARED_FILES.items()):
        _PREPARED_FILES.pop(out, None)
        try:
            _untidy_file(out, entry, created)
        except OSError:
            pass
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


def _read_marker(folder: Path) -> tuple[str | None, set[str] | None]:
    """(stage name, paths written or None) of ``folder``'s marker; (None, None) without one.

    Paths are relative (folders end in ``/``); a marker of an older version lists top-level
    names only. A marker whose run has not finished (:data:`_KEPT`) gives None."""
    stage, kind, paths = _marker(folder)
    if kind == _KEPT:
        return stage, None
    return stage, paths


def _marker(folder: Path) -> tuple[str | None, str | None, set[str] | None]:
    """(stage, kind: :data:`_FILES`, :data:`_KEPT` or None for the older top-level form,
    paths or None) of ``folder``'s marker."""
    f = folder / MARKER
    if not f.is_file():
        return None, None, None
    lines = f.read_text(errors="replace").splitlines()
    if not lines:
        return None, None, None
    if len(lines) > 1 and lines[1] in (_FILES, _KEPT):
        return lines[0].strip(), lines[1], set(lines[2:])
    return lines[0].strip(), None, (set(lines[1:]) if len(lines) > 1 else None)


def _tree(folder: Path) -> list[str]:
    """Every entry under ``folder`` as a relative posix path (folders end in ``/``; links are
    entries, never followed), the rule's own files and the tools' files at the top excluded;
    sorted, parents before children."""
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


def _foreign(folder: Path, written: set[str], skip_workflow: bool) -> list[str]:
    """Entries of ``folder`` (:func:`_tree`) that ``written`` does not list."""
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
              derived: Callable[[Path], bool] | None = None, fresh: bool = False) -> Path:
    """Refuse an ``--out`` that breaks the output rule (module docstring); write nothing.

    Args:
        out: the command's ``--out`` (a folder, or a file when ``folder`` is False).
        inputs: option name (e.g. ``"--images"``) -> input path, list of paths, or None.
        stage: the stage's name as written in the marker (e.g. ``"camio convert"``).
        folder: ``out`` is a folder (the non-empty rule applies) or a file.
        may_hold_out: input names whose folder may hold ``out`` (results-tree readers).
        replaces: the stage replaces its folder whole (its writer is ``camio.atomic.atomic_dir``
            on ``out``): only its own entries, in every subfolder, may be there.
        same_file_as: for a file ``out``: other stage -> the names of its files that this
            command may replace (``camio split`` replaces the ``split.json`` that ``camio
            convert`` wrote, and nothing else of it).

    Returns:
        ``out`` as a Path.

    Raises:
        OutputFolderError: one line naming ``out`` and the input or entry at fault.
    """
    out_p = Path(out)
    if not os.fspath(out).strip():
        raise OutputFolderError(f"--out is empty: name the {'folder' if folder else 'file'} {stage} writes")
    o = _resolved(out)
    if o == Path(o.anchor):
        raise OutputFolderError(f"--out {out} is the file system's root: choose a folder of its own")
    hold_ok = set(may_hold_out)
    given = _inputs(inputs)
    for name, p in given:
        if o == p:
            raise OutputFolderError(f"--out {out} is the input {name} {p}: choose another output "
                                    "(a stage never writes over its inputs)")
    for name, p in given:
        if p in o.parents and name not in hold_ok:
            raise OutputFolderError(f"--out {out} lies inside the input {name} {p}: choose an output "
                                    "outside the inputs")
        if o in p.parents:
            raise OutputFolderError(f"--out {out} contains the input {name} {p}: choose an output "
                                    "folder that holds none of the inputs")
    if not folder:
        if o.is_dir():
            raise OutputFolderError(f"--out {out} is a folder; {stage} writes a file there: name the file")
        if o.name in _OWN or o.name == MARKER:
            raise OutputFolderError(f"--out {out}: {o.name} is the output rule's own file; name another file")
        if o.exists() or out_p.is_symlink():
            writers = _file_writers(o.parent, o.name)
            kin = {other for other, names in (same_file_as or {}).items() if o.name in set(names)}
            if not writers & ({stage} | kin) and not (derived is not None and o.is_file() and derived(o)):
                who = f"was written by `{sorted(writers)[0]}`" if writers else f"was not written by `{stage}`"
                raise OutputFolderError(f"--out {out} exists and {who}: {stage} never replaces a file it did not "
                                        "write; move it away or name a new file (nothing was changed)")
        return out_p
    if o.exists() and not o.is_dir():
        raise OutputFolderError(f"--out {out} is a file, not a folder: choose a folder for {stage}")
    if o.is_dir():
        entries = sorted(e.name for e in o.iterdir() if e.name not in _OWN and e.name not in TOOL_FILES
                         and not (not replaces and e.name in WORKFLOW_DIRS and e.is_dir()))
        owner, kind, paths = _marker(o)
        if entries and owner != stage:
            who = f"was written by `{owner}`" if owner else f"has no {MARKER} marker of `{stage}`"
            raise OutputFolderError(f"--out {out} is not empty ({len(entries)} entries, e.g. {entries[0]}) and "
                                    f"{who}: choose an empty or new folder (nothing was changed)")
        if replaces and owner == stage and paths is not None and kind != _KEPT:
            if kind == _FILES:
                foreign = _foreign(o, paths, skip_workflow=False)
            else:  # an older marker: top-level names
                foreign = [e for e in entries if e not in paths]
            if foreign:
                raise OutputFolderError(f"--out {out} holds {o / foreign[0].rstrip('/')}, which `{stage}` did not "
                                        f"write and would replace: move it away or choose a new folder")
        if not replaces and not fresh and owner == stage and kind == _FILES:
            inside = _inside_own(o, paths)
            if inside:
                raise OutputFolderError(f"--out {out} holds {o / inside[0].rstrip('/')} inside a folder that `{stage}` "
                                        "wrote and replaces on a rerun: move it away or choose a new folder")
    return out_p


def _inside_own(folder: Path, written: set[str]) -> list[str]:
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


def _file_writers(folder: Path, name: str) -> set[str]:
    """The stages recorded as writers of the file ``folder/name``: the folder's :data:`LEDGER`
    and the marker of a stage that replaced the folder whole and lists the file."""
    writers = set()
    ledger = folder / LEDGER
    if ledger.is_file():
        for line in ledger.read_text(errors="replace").splitlines():
            fname, _, who = line.partition("\t")
            if fname == name and who:
                writers.add(who)
    owner, kind, paths = _marker(folder)
    if owner and kind != _KEPT and paths and name in paths:
        writers.add(owner)
    return writers


def _record_file(out: Path, stage: str, created: tuple[Path, ...]) -> None:
    """Add ``out`` (a file) to its folder's :data:`LEDGER` as written by ``stage`` (before it
    is written; :func:`tidy_outs` takes the entry back if the stage then wrote nothing)."""
    folder = out.parent if str(out.parent) else Path(".")
    ledger = folder / LEDGER
    lines = ledger.read_text(errors="replace").splitlines() if ledger.is_file() else []
    entry = f"{out.name}\t{stage}"
    if entry not in lines:
        with open(ledger, "a") as f:
            f.write(entry + "\n")
        _PREPARED_FILES[_resolved(out)] = (entry, created)


_PREPARED_FILES: dict[Path, tuple[str, tuple[Path, ...]]] = {}
"""File outputs :func:`prepare_out` entered in a ledger in this process -> (the ledger line,
the folders it created for them)."""


def _untidy_file(out: Path, entry: str, created: tuple[Path, ...]) -> None:
    """Take back the ledger line of a file output that was never written (see :func:`tidy_outs`)."""
    if out.exists() or out.is_symlink():
        return
    ledger = out.parent / LEDGER
    if ledger.is_file():
        lines = [ln for ln in ledger.read_text(errors="replace").splitlines() if ln != entry]
        if lines:
            ledger.write_text("\n".join(lines) + "\n")
        else:
            ledger.unlink()
    for made in created:
        if made.is_dir() and not any(made.iterdir()):
            made.rmdir()


_LOCKS: dict[Path, int] = {}
"""Folders this process holds the writer's lock of -> the lock file's descriptor."""


def _lock(folder: Path, out: PathLike) -> None:
    """Take the writer's lock of ``folder`` for this process (module docstring).

    Raises:
        OutputFolderError: another live process holds it (one line naming its pid).
    """
    import fcntl

    key = _resolved(folder)
    if key in _LOCKS:
        return
    path = folder / LOCK
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise OutputFolderError(f"--out {out} is being written by another process (pid {holder}, lock "
                                    f"{path}): wait for it to finish or choose another folder") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
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
        if os.fstat(fd).st_ino == os.stat(key / LOCK).st_ino:
            os.unlink(key / LOCK)
    except OSError:
        pass
    try:
        os.close(fd)
    except OSError:
        pass


atexit.register(release_locks)


def _clear_own(folder: Path, stage: str) -> None:
    """Remove, file by file, what ``stage``'s earlier run wrote into ``folder`` (module
    docstring), then record what is there now as kept (:data:`_KEPT`) until :func:`seal_out`."""
    owner, kind, paths = _marker(folder)
    if owner == stage and kind in (_FILES, _KEPT):
        present = _tree(folder)
        if kind == _FILES:
            gone = [p for p in present if p in paths]
        else:  # the earlier run did not finish: everything it did not find there is its own
            gone = [p for p in present if p not in paths and p.split("/", 1)[0] not in WORKFLOW_DIRS]
        for p in sorted(gone, key=lambda q: -q.count("/")):
            target = folder / p.rstrip("/")
            try:
                if p.endswith("/"):
                    target.rmdir()  # only when empty: a user's file below keeps it
                else:
                    target.unlink()
            except OSError:
                pass
        if gone:
            log.info("removed %d entries of the earlier `%s` run from %s", len(gone), stage, folder)
    kept = _tree(folder)
    (folder / MARKER).write_text("\n".join([stage, _KEPT, *kept]) + "\n")


def _keep_others(folder: Path, stage: str) -> None:
    """Record as kept (:data:`_KEPT`) what is in ``folder`` that ``stage``'s earlier run did
    not write, so that :func:`seal_out` records what this run writes, file by file."""
    owner, kind, paths = _marker(folder)
    present = _tree(folder)
    if owner == stage and kind == _FILES:
        kept = [p for p in present if p not in paths]
    elif owner == stage and kind == _KEPT:
        kept = [p for p in present if p in paths]
    elif owner == stage:
        kept = []  # an older marker: everything there counts as the stage's
    else:
        kept = present  # the workflow's logs/ and benchmarks/
    (folder / MARKER).write_text("\n".join([stage, _KEPT, *kept]) + "\n")


_STAGES: dict[Path, str] = {}
"""Folders :func:`prepare_out` prepared in this process -> their stage (sealed by
:func:`finish_outs` when the command succeeds, unless :func:`seal_out` already did)."""

_SEALED: set[Path] = set()


def finish_outs() -> None:
    """Record what each folder prepared in this process received (:func:`seal_out`), for the
    folders the command did not seal itself. :func:`run_stage` calls it when the command
    succeeds; a command that failed leaves its marker saying its run did not finish."""
    for folder, stage in list(_STAGES.items()):
        _STAGES.pop(folder, None)
        if folder in _SEALED or not folder.is_dir():
            continue
        try:
            seal_out(folder, stage)
        except OSError:
            pass
    _SEALED.clear()
    _PREPARED.clear()  # finished: a folder it wrote nothing into (no plot to draw) is still its output


def prepare_out(out: PathLike, inputs: Mapping[str, PathLike | Iterable[PathLike] | None], stage: str, *,
                folder: bool = True, may_hold_out: Iterable[str] = (), replaces: bool = False,
                fresh: bool = False, same_file_as: Mapping[str, Iterable[str]] | None = None,
                derived: Callable[[Path], bool] | None = None) -> Path:
    """:func:`check_out`, then create a folder ``out``, take its writer's lock and mark it as
    ``stage``'s (a file ``out`` gets its parent folder created and is entered in the folder's
    :data:`LEDGER`). A folder that cannot be written (read-only, no permission) is refused as
    one line too.

    Args:
        fresh: the stage writes a folder of results: remove its earlier run's files first
            (module docstring); call :func:`seal_out` with what it wrote when it has finished.

    Returns:
        ``out`` as a Path.
    """
    out_p = check_out(out, inputs, stage, folder=folder, may_hold_out=may_hold_out, replaces=replaces,
                      same_file_as=same_file_as, derived=derived, fresh=fresh)
    target = out_p if folder else (out_p.parent if str(out_p.parent) else Path("."))
    try:
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
            marker = target / MARKER
            owner, written = _read_marker(target)
            if fresh:
                _clear_own(target, stage)
            elif not replaces:
                _keep_others(target, stage)
            elif owner != stage:
                marker.write_text(stage + "\n")
            if owner != stage:
                _PREPARED[_resolved(target)] = tuple(created)
            _STAGES[_resolved(target)] = stage
        else:
            if not os.access(target, os.W_OK | os.X_OK):
                raise PermissionError(errno.EACCES, "Permission denied", str(target))
            _record_file(out_p, stage, tuple(created))
    except OSError as exc:
        raise OutputFolderError(f"cannot write --out {out}: {exc.strerror or exc} ({exc.filename or target}); "
                                "choose a writable folder") from exc
    return out_p


def seal_out(out: PathLike, stage: str) -> Path:
    """Record in ``out``'s marker what ``stage`` wrote (call when the stage has finished): for
    a stage that replaced its folder whole, every file and folder in it, in every subfolder;
    after ``prepare_out(..., fresh=True)``, everything but what was there before the run."""
    out_p = Path(out)
    owner, kind, paths = _marker(out_p)
    kept = paths if (owner == stage and kind == _KEPT) else set()
    names = [p for p in _tree(out_p) if p not in kept]
    (out_p / MARKER).write_text("\n".join([stage, _FILES, *names]) + "\n")
    _SEALED.add(_resolved(out_p))
    return out_p


def typed_line(exc: BaseException) -> str:
    """An error as one line after its type's name: ``FileNotFoundError: ...``."""
    return f"{type(exc).__name__}: {exc}"


def run_stage(log: logging.Logger, work: Callable[[], int | None], *,
              errors: tuple[type[BaseException], ...] = (ValueError, OSError),
              line: Callable[[BaseException], str] = str, traceback: bool = False) -> int:
    """What every stage CLI ends with: run ``work`` (it calls :func:`prepare_out` first, then
    the stage) and turn a bad input into one error line and exit code 2.

    Args:
        log: the stage's logger.
        work: the stage after its argument parsing; returns its exit code (None: 0).
        errors: what counts as a bad input when ``work`` raises it.
        line: the error line of such an error (:func:`typed_line` puts its type's name first).
        traceback: also log the traceback at debug level (shown with -v).

    Returns:
        ``work``'s exit code; 2 for a refusal of the output rule (:class:`OutputFolderError`,
        its own line) or an error of ``errors``, after :func:`tidy_outs` (a failed stage leaves
        nothing behind).
    """
    previous = _catch_signals()
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
    except Stopped as exc:
        tidy_outs()
        log.error("stopped by %s: nothing half-written was kept (outputs are written atomically); run the "
                  "same command again", exc.name)
        return 128 + exc.signum
    finally:
        release_locks()
        for signum, handler in previous.items():
            signal.signal(signum, handler)


class Stopped(BaseException):
    """The process was asked to stop (SIGTERM, SIGHUP): raised in the main thread so that every
    ``finally`` runs (temporary files and folders of :mod:`camio.atomic` are removed)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum
        self.name = signal.Signals(signum).name


def _stop(signum, frame) -> None:
    raise Stopped(signum)


def _catch_signals() -> dict:
    """Turn SIGTERM and SIGHUP into :class:`Stopped` (main thread only; SIGINT stays Python's
    KeyboardInterrupt). Returns the handlers to put back."""
    import threading

    previous = {}
    if threading.current_thread() is not threading.main_thread():
        return previous
    for signum in (signal.SIGTERM, signal.SIGHUP):
        try:
            previous[signum] = signal.signal(signum, _stop)
        except (ValueError, OSError):
            pass
    return previous
