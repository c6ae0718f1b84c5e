"""The refusals of the output rule: :func:`check_out` writes nothing and raises one line.

The account of the rule is :mod:`runtime.outdir`'s docstring; :func:`runtime.outdir.prepare_out`
calls :func:`check_out` before anything is written, and again under the folder's lock. The
helpers here compare an existing ``--out`` with the records of :mod:`runtime.ledger`: what
changed since the stage wrote it, what it did not write, who wrote a file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable, Mapping

from runtime import atomic
from runtime.ledger import (_FILES, _KEPT, _OWN, MARKER, TOOL_FILES, WORKFLOW_DIRS, OutputFolderError, PathLike,
                            Stamp, _ledger_writers, _link_refused, _marker, _matches, _resolved, _tree)

__all__ = ["check_out"]


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


def _inputs(inputs: Mapping[str, PathLike | Iterable[PathLike] | None]) -> list[tuple[str, Path]]:
    """(option name, resolved path) for every input given; lists (``nargs``) are flattened."""
    out: list[tuple[str, Path]] = []
    for name, val in inputs.items():
        if val is None:
            continue
        vals = [val] if isinstance(val, (str, os.PathLike)) else list(val)
        out.extend((name, _resolved(v)) for v in vals if v is not None and os.fspath(v) != "")
    return out


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
    """Entries of ``folder`` (:func:`runtime.ledger._tree`) that ``written`` does not list."""
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
    """Refuse an ``--out`` that breaks the output rule (:mod:`runtime.outdir`'s docstring); write nothing.

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
    every stage recorded as its writer): the folder's :data:`runtime.ledger.LEDGER` and the marker of a stage
    that has finished and lists the file."""
    writers, recorded = _ledger_writers(folder / name)
    m = _marker(folder)
    if m.stage and m.kind == _FILES and name in m.entries:
        recorded.add(m.stage)
        if _matches(folder / name, m.entries[name]):
            writers.add(m.stage)
    return writers, recorded - writers
