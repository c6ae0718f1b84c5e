"""The one output rule of every stage command: a stage writes only what it owns.

Every stage CLI calls :func:`prepare_out` before it reads or writes anything:

* ``--out`` must not be, contain, or lie inside any input path of the command (compared after
  resolving symlinks). Where the output's place is inside an input by design (the results-tree
  readers' report folders, ``camio split``'s ``scene/split.json``) the command names that input
  in ``may_hold_out``: its ``--out`` may lie inside it, never be it or contain it. ``--out``
  itself (a folder, or a file and its folder) may not be a symbolic link, nor have a name longer
  than its file system holds (less what a temporary's name adds,
  :data:`runtime.atomic.TEMP_NAME_EXTRA`) or a path of PATH_MAX bytes or more.
* A folder ``--out`` that exists must be empty (Snakemake creates output folders before a job),
  or hold the marker file :data:`runtime.ledger.MARKER` naming this same stage: a rerun of the
  stage into its own folder works, any other non-empty folder is refused.
* A folder holding only the workflow's ``logs/`` and ``benchmarks/``
  (:data:`runtime.ledger.WORKFLOW_DIRS`) counts as empty, except for a stage that replaces its
  folder whole.
* The marker records every file the stage wrote with its stamp (:data:`runtime.ledger.Stamp`:
  size, times, inode, a hash of its bytes; :func:`seal_out`), and while a run goes on, what was
  there before it (``#kept``) and each file the run writes through :mod:`runtime.atomic`, before
  it is renamed into place (``#wrote``). A recorded file counts as the stage's only while its
  stamp still matches: a rerun refuses a folder where a file the stage wrote has changed (a
  user's file put where an output stood), and never writes over a file that was there before its
  run and is not its own (:func:`runtime.outrun._before_rename`).
* A stage that replaces its whole folder (``replaces=True``: ``camio convert``, ``camio synth``,
  ``evaluation report``, ``evaluation study``, the workflow's ``views link``) refuses a folder
  that holds anything it did not write (a user's file in ``images/``, a ``sparse/1/`` model, or
  anything at all after a run of it that did not finish), so a file the stage did not write is
  never deleted.
* A rerun of any other stage refuses while a foreign entry lies inside a folder the stage wrote
  (it would replace that folder whole, e.g. ``sparse/0``), and keeps what lies beside its
  outputs.
* A stage that writes a folder of results beside whatever else is there (``fresh=True``:
  ``splat_train render``, ``splat_train testpose``, the COLMAP baseline) first removes, file by
  file, what its own earlier run wrote and still matches its record (after a run that did not
  finish: what that run recorded as it wrote), so the folder never mixes two runs; anything else
  stays, whenever it was put there.
* A file ``--out`` that exists is replaced only if this command (or, for the file names given in
  ``same_file_as``, another stage: ``split.json`` of ``camio convert``) wrote it and it has not
  changed since: the folder's ledger :data:`runtime.ledger.LEDGER` (or a replacing stage's
  marker) records who wrote which file, with its stamp. A photo, a camera file or a split the
  user made, or put where such a file stood, is refused, never overwritten.
* A marker or ledger this version cannot read (malformed, or of an older version without stamps)
  is refused with one line, never appended to; the marker, the ledger and the lock are opened
  without following a symbolic link, and a link where one of them would be is refused.
* One writer per output folder: :func:`prepare_out` takes an exclusive lock
  (:data:`runtime.ledger.LOCK`, ``flock``, holding the writer's pid; :mod:`runtime.outlock`) for
  the life of the command. A second command on the same folder is refused with one line naming
  the holder's pid; the lock of a killed process is released by the kernel, so it is taken over
  (with a log line).
* SIGTERM, SIGINT and SIGHUP end a command through :class:`runtime.stops.Stopped`
  (:func:`run_stage`, :mod:`runtime.stops`, also after pycolmap installed its own handler), so
  every ``finally`` runs: no temporary file or folder is left, the lock is given up, the marker
  says the run did not finish; one line, exit code 128 + the signal (SIGHUP 129, SIGINT 130,
  SIGTERM 143).
* A name read from a file (a split, an image list, a COLMAP model, a ``predictions.npz``) is a
  plain file name, listed once (:mod:`runtime.names`: :func:`runtime.names.check_name` and
  :func:`runtime.names.check_name_list`).

Every refusal is a :class:`runtime.ledger.OutputFolderError` (a ``ValueError``), one line naming
both paths; the stage CLIs print it and exit with code 2 (:func:`run_stage`, the ending they
share).

This module holds the run of a stage: :func:`prepare_out`, :func:`seal_out`, :func:`run_stage`
and what it calls at the end (:func:`finish_outs` when the command succeeds, :func:`tidy_outs`
when it fails). The rule's other parts, each imported by those above it:

* :mod:`runtime.ledger`: the rule's own files (marker, ledger, lock file names and formats),
  stamps and records, and :class:`~runtime.ledger.OutputFolderError`;
* :mod:`runtime.outlock`: the lock of an output folder;
* :mod:`runtime.outcheck`: :func:`~runtime.outcheck.check_out`, the refusals (writes nothing);
* :mod:`runtime.outrun`: what this process prepared, and the records a run appends as it writes
  (:mod:`runtime.atomic`'s hook before each rename).
"""

from __future__ import annotations

import atexit
import errno
import logging
import os
from pathlib import Path
from typing import Callable, Iterable, Mapping

from runtime.ledger import (_FILES, _KEPT, _OWN, MARKER, WORKFLOW_DIRS, OutputFolderError, PathLike, _ledger,
                            _marker, _resolved, _stamps, _tree, _write_own)
from runtime.outcheck import check_out
from runtime.outlock import _lock, _unlock, release_locks
from runtime.outrun import _BEFORE, _PREPARED, _PREPARED_FILES, _SEALED, _STAGES, _record_file, _start_run
from runtime.stops import Stopped, stop_line, stopping, stops_caught, stops_held

__all__ = ["prepare_out", "seal_out", "run_stage", "typed_line", "finish_outs", "tidy_outs"]


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
    """:func:`runtime.outcheck.check_out`, then create a folder ``out``, take its writer's lock
    and mark it as ``stage``'s (a file ``out`` gets its parent folder created; its record goes
    into the folder's :data:`runtime.ledger.LEDGER` as it is written). A folder that cannot be
    written (read-only, no permission) is refused as one line too.

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
        ``work``'s exit code; 2 for a refusal of the output rule
        (:class:`~runtime.ledger.OutputFolderError`, its own line) or an error of ``errors``; 128 + the signal for SIGTERM, SIGINT or SIGHUP
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
