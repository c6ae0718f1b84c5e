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
  synth``, ``evaluation report``, ``evaluation study``) records in the marker what it wrote
  (:func:`seal_out`); a rerun refuses a folder that holds anything else, so a file the
  stage did not write is never deleted.

Every refusal is an :class:`OutputFolderError` (a ``ValueError``), one line naming both
paths; the stage CLIs print it and exit with code 2 (:func:`run_stage`, the ending they share).
"""

from __future__ import annotations

import atexit
import errno
import logging
import os
from pathlib import Path
from typing import Callable, Iterable, Mapping

__all__ = ["MARKER", "OutputFolderError", "prepare_out", "seal_out", "keep_out", "check_out", "tidy_outs", "run_stage",
           "typed_line"]

MARKER = ".stage"
"""Marker file in every folder a stage creates: line 1 the stage name, then (for stages that
replace their folder whole) one top-level entry name per line that the stage wrote."""

TOOL_FILES = frozenset({".snakemake_timestamp"})
"""Entries a workflow tool adds to a stage's folder (Snakemake touches this one in every
``directory()`` output it has completed); they are not the user's files."""

WORKFLOW_DIRS = frozenset({"logs", "benchmarks"})
"""Folders the workflow's ``log:`` and ``benchmark:`` paths put inside a job's output folder
before the job starts (workflow/rules/*.smk, e.g. ``n3/oracle/logs/``). A folder holding only
these counts as empty for a stage that writes beside them; a stage that replaces its folder
whole (which would delete them) still refuses it."""

PathLike = str | os.PathLike


_FILE_PARENTS: list[tuple[Path, ...]] = []
"""The folders :func:`prepare_out` created for a file ``out`` (deepest first)."""

_PREPARED: dict[Path, tuple[Path, ...]] = {}
"""Folders :func:`prepare_out` marked in this process -> the folders it created for them
(the folder and its new parents, deepest first; empty when the folder was there)."""


def tidy_outs() -> None:
    """Undo :func:`prepare_out` where the stage then wrote nothing (it failed early): remove
    the marker, and the folder and its parents where :func:`prepare_out` created them. A failed stage leaves
    nothing behind. Runs at interpreter exit; the CLIs also call it on their error paths."""
    for folder, created in list(_PREPARED.items()):
        _PREPARED.pop(folder, None)
        try:
            if folder.is_dir() and MARKER in {e.name for e in folder.iterdir()} and not [
                    e for e in folder.iterdir() if e.name != MARKER and not (e.name in WORKFLOW_DIRS and e.is_dir())]:
                (folder / MARKER).unlink()
                for made in created:  # the folder and the parents prepare_out made, while empty
                    made.rmdir()
        except OSError:
            pass
    for made in _FILE_PARENTS:  # parents made for a file --out: removed while still empty
        for folder in made:
            try:
                folder.rmdir()
            except OSError:
                break
    _FILE_PARENTS.clear()


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
    """(stage name, entries written or None) of ``folder``'s marker; (None, None) without one."""
    f = folder / MARKER
    if not f.is_file():
        return None, None
    lines = f.read_text(errors="replace").splitlines()
    if not lines:
        return None, None
    entries = set(lines[1:]) if len(lines) > 1 else None
    return lines[0].strip(), entries


def check_out(out: PathLike, inputs: Mapping[str, PathLike | Iterable[PathLike] | None], stage: str, *,
              folder: bool = True, may_hold_out: Iterable[str] = (), replaces: bool = False) -> Path:
    """Refuse an ``--out`` that breaks the output rule (module docstring); write nothing.

    Args:
        out: the command's ``--out`` (a folder, or a file when ``folder`` is False).
        inputs: option name (e.g. ``"--images"``) -> input path, list of paths, or None.
        stage: the stage's name as written in the marker (e.g. ``"camio convert"``).
        folder: ``out`` is a folder (the non-empty rule applies) or a file.
        may_hold_out: input names whose folder may hold ``out`` (results-tree readers).
        replaces: the stage replaces its folder whole (its writer is ``camio.atomic.atomic_dir``
            on ``out``): only its own entries may be there.

    Returns:
        ``out`` as a Path.

    Raises:
        OutputFolderError: one line naming ``out`` and the input or entry at fault.
    """
    out_p = Path(out)
    o = _resolved(out)
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
        return out_p
    if o.exists() and not o.is_dir():
        raise OutputFolderError(f"--out {out} is a file, not a folder: choose a folder for {stage}")
    if o.is_dir():
        entries = sorted(e.name for e in o.iterdir() if e.name != MARKER and e.name not in TOOL_FILES
                         and not (not replaces and e.name in WORKFLOW_DIRS and e.is_dir()))
        owner, written = _read_marker(o)
        if entries and owner != stage:
            who = f"was written by `{owner}`" if owner else f"has no {MARKER} marker of `{stage}`"
            raise OutputFolderError(f"--out {out} is not empty ({len(entries)} entries, e.g. {entries[0]}) and "
                                    f"{who}: choose an empty or new folder (nothing was changed)")
        if written is not None:
            foreign = [e for e in entries if e not in written]
            if foreign:
                raise OutputFolderError(f"--out {out} holds {o / foreign[0]}, which `{stage}` did not write "
                                        f"and would replace: move it away or choose a new folder")
    return out_p


def prepare_out(out: PathLike, inputs: Mapping[str, PathLike | Iterable[PathLike] | None], stage: str, *,
                folder: bool = True, may_hold_out: Iterable[str] = (), replaces: bool = False) -> Path:
    """:func:`check_out`, then create a folder ``out`` and mark it as ``stage``'s (a file
    ``out`` gets its parent folder created). A folder that cannot be written (read-only,
    no permission) is refused as one line too.

    Returns:
        ``out`` as a Path.
    """
    out_p = check_out(out, inputs, stage, folder=folder, may_hold_out=may_hold_out, replaces=replaces)
    target = out_p if folder else (out_p.parent if str(out_p.parent) else Path("."))
    try:
        created = []  # the folders this call creates, deepest first (the parents too)
        probe = _resolved(target)
        while not probe.exists():
            created.append(probe)
            probe = probe.parent
        target.mkdir(parents=True, exist_ok=True)
        if folder:
            marker = target / MARKER
            owner, written = _read_marker(target)
            if owner != stage:
                marker.write_text(stage + "\n")
                _PREPARED[_resolved(target)] = tuple(created)
        else:
            if created:
                _FILE_PARENTS.append(tuple(created))
            if not os.access(target, os.W_OK | os.X_OK):
                raise PermissionError(errno.EACCES, "Permission denied", str(target))
    except OSError as exc:
        raise OutputFolderError(f"cannot write --out {out}: {exc.strerror or exc} ({exc.filename or target}); "
                                "choose a writable folder") from exc
    return out_p


def seal_out(out: PathLike, stage: str) -> Path:
    """Record in ``out``'s marker every top-level entry now in it, as written by ``stage``
    (call after a stage that replaced its folder whole has finished)."""
    out_p = Path(out)
    names = sorted(e.name for e in out_p.iterdir() if e.name != MARKER)
    (out_p / MARKER).write_text("\n".join([stage, *names]) + "\n")
    keep_out(out_p)
    return out_p


def keep_out(out: PathLike) -> None:
    """The stage that prepared ``out`` has finished: its folder stays, even when it wrote
    nothing into it (e.g. no plot to draw), rather than being tidied away at exit."""
    _PREPARED.pop(_resolved(Path(out)), None)


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
    try:
        return int(work() or 0)
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
