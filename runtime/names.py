"""The one rule for names read from files: a name becomes a path only inside its own folder.

Image names come from files a user may not have written: a split or an image list, a COLMAP
model (``images.txt``, ``images.bin``), the ``image_names`` of a ``predictions.npz``, the
frame paths of a ``transforms.json``. Each is checked here before it is joined to a folder, so
that no command reads or writes outside its folders (``../x.png`` in a model made ``splat_train
render`` write over a file outside ``--out``):

* :func:`check_name`: a plain file name (no folders, ``..``, separators, NUL, line breaks,
  bytes that are not UTF-8); :func:`check_name_list` also refuses a name listed twice.
* :func:`check_stems`: no two names differing only by their extension where outputs are named
  by stem (renders ``<stem>.png``: ``v0.png`` and ``v0.jpg`` would write one file).
* :func:`check_inside`: a relative path that may hold sub-folders (a ``transforms.json``
  frame's ``images/x.jpg``) stays inside its folder once ``.`` and ``..`` are resolved.

Every refusal is a ``ValueError`` of one line naming the file the name came from and what to
do; the stage CLIs print it and exit with code 2 (``runtime.outdir.run_stage``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

__all__ = ["check_name", "check_name_list", "check_stems", "check_inside"]

PathLike = str | os.PathLike


def check_name(name: str, what: str, source: PathLike) -> str:
    """Refuse a file name read from a file that is not a plain name in one folder: not text,
    empty, absolute, with a ``/`` or ``\\`` separator, ``.`` or ``..``, a NUL, a line break,
    or characters that are not UTF-8. Such a name would make a command read or write outside
    its folders (or fail in a writer that needs text).

    Returns:
        ``name`` unchanged.

    Raises:
        ValueError: one line naming ``source`` and the name.
    """
    bad = (not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name
           or any(c in name for c in "\0\n\r") or not _utf8(name))
    if bad:
        raise ValueError(f"{source}: the {what} {name!r} is not a plain file name (no folders, '..', "
                         "separators or non-UTF-8 bytes): fix the file")
    return name


def _utf8(name: str) -> bool:
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # lone surrogates: bytes that were not UTF-8
        return False
    return True


def check_name_list(names: Iterable[str], source: PathLike, what: str = "image name") -> list[str]:
    """Every name plain (:func:`check_name`) and none twice (a view listed twice would be
    trained, or counted, twice).

    Returns:
        the names as a list.

    Raises:
        ValueError: one line naming ``source``, the name and its two places in the list.
    """
    names = list(names)
    seen: dict[str, int] = {}
    for i, name in enumerate(names, 1):
        check_name(name, what, source)
        if name in seen:
            raise ValueError(f"{source}: the {what} {name!r} is listed twice (entries {seen[name]} and {i}): "
                             "each image may appear once")
        seen[name] = i
    return names


def check_stems(names: Iterable[str], source: PathLike, suffix: str = ".png") -> list[str]:
    """No two names whose outputs, named ``<stem><suffix>``, would be one file (``v0.png`` and
    ``v0.jpg`` both render to ``v0.png``; the second would replace the first).

    Returns:
        the names as a list.

    Raises:
        ValueError: one line naming ``source``, both names and the output they share.
    """
    names = list(names)
    first: dict[str, str] = {}
    for name in names:
        out = Path(name).stem + suffix
        if out in first and first[out] != name:
            raise ValueError(f"{source}: the images {first[out]!r} and {name!r} differ only by their extension, "
                             f"and outputs are named by stem (both would be written as {out!r}): rename one")
        first.setdefault(out, name)
    return names


def check_inside(rel: str, folder: PathLike, what: str, source: PathLike) -> Path:
    """``folder / rel`` for a path read from a file that may hold sub-folders (``images/x.jpg``,
    ``./train/r_0``), refused unless it stays inside ``folder`` once ``.`` and ``..`` are
    resolved (an absolute path counts where it lies inside ``folder``). Compared as written:
    a symbolic link the folder itself holds is followed as its owner made it.

    Returns:
        the joined path (normalised).

    Raises:
        ValueError: one line naming ``source`` and the path.
    """
    if not isinstance(rel, str) or not rel or "\0" in rel or not _utf8(rel):
        raise ValueError(f"{source}: the {what} {rel!r} is not a path: fix the file")
    base = os.path.normpath(os.path.abspath(os.fspath(folder)))
    full = os.path.normpath(os.path.join(base, rel))
    if full == base or not full.startswith(base.rstrip(os.sep) + os.sep):
        raise ValueError(f"{source}: the {what} {rel!r} lies outside {base}: every image a scene file names "
                         "must be inside the scene's folder; fix the file")
    return Path(full)
