"""What this process's run of a stage has prepared, and the records it keeps as it writes.

:func:`runtime.outdir.prepare_out` notes here the folders and files it prepared; a run that
writes beside what is there begins with :func:`_start_run` (a ``fresh`` stage first removes its
earlier run's files; the marker then lists what was there as ``#kept``). Every write through
:mod:`runtime.atomic` passes :func:`_before_rename` before its rename: it refuses to replace
what was there before the run and is not the stage's, and appends the record of what is about
to be written to the folder's marker (a file ``--out``: its folder's ledger), so that a rerun
after a kill knows it. :mod:`runtime.outdir` seals the folders when the command succeeds and
tidies them when it fails. The file formats are :mod:`runtime.ledger`'s.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Mapping

from runtime import atomic
from runtime.ledger import (_KEPT, _WROTE, LEDGER, MARKER, OutputFolderError, Stamp, _append_own, _entry, _ledger,
                            _ledger_writers, _marker, _matches, _resolved, _stamp, _tree, _write_own)

__all__: list[str] = []

log = logging.getLogger("runtime.outdir")  # the output rule's logger: its lines name runtime.outdir


_PREPARED: dict[Path, tuple[Path, ...]] = {}
"""Folders :func:`runtime.outdir.prepare_out` marked in this process -> the folders it created
for them (the folder and its new parents, deepest first; empty when the folder was there)."""


_PREPARED_FILES: dict[Path, tuple[str, tuple[Path, ...]]] = {}
"""File outputs :func:`runtime.outdir.prepare_out` prepared in this process -> (their stage, the
folders it created for them)."""

_STAGES: dict[Path, str] = {}
"""Folders :func:`runtime.outdir.prepare_out` prepared in this process -> their stage (sealed
by :func:`runtime.outdir.finish_outs` when the command succeeds, unless
:func:`runtime.outdir.seal_out` already did)."""

_SEALED: set[Path] = set()


def _record_file(out: Path, stage: str) -> None:
    """Append ``out``'s record (its stamp as written by ``stage``) to its folder's :data:`runtime.ledger.LEDGER`,
    unless its last record of ``stage`` already matches."""
    writers, _ = _ledger_writers(out)
    st = _stamp(out) if stage not in writers else None
    if st is not None:
        _append_own(out.parent / LEDGER, [json.dumps([out.name, stage, *st], ensure_ascii=True)])


_BEFORE: dict[Path, tuple[str, frozenset[str]]] = {}
"""Folders prepared in this process whose marker is ``#kept`` -> (their stage, the
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
    """Every entry under ``folder`` (:func:`runtime.ledger._tree` without leaving anything out)."""
    out = []
    for root, dirs, files in os.walk(folder, followlinks=False):
        rel = Path(root).relative_to(folder)
        out += [(rel / d).as_posix() + ("" if (Path(root) / d).is_symlink() else "/") for d in dirs]
        out += [(rel / f).as_posix() for f in files]
    return sorted(out)


atomic.BEFORE_RENAME.append(_before_rename)


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
    file by file, what its earlier run recorded and still matches (:mod:`runtime.outdir`'s
    docstring); then record what is there that is not the stage's as kept (``#kept``), until
    :func:`runtime.outdir.seal_out`, and remember it for :func:`_before_rename`."""
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
