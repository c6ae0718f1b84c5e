"""Numbers checked where they enter: one range type for config fields and command-line flags.

A :class:`Range` says what a number may be (integer or real, bounds, open or closed ends);
a real number is always finite, an integer is never a bool (JSON ``true`` is not 1 iteration).
:meth:`Range.check` checks a value already parsed (a config file's), :func:`flag` makes the
argparse ``type=`` of a numeric flag, so a bad flag is argparse's one-line usage error
(exit 2) before the command does anything::

    p.add_argument("--threads", type=flag(int, lo=0), ...)      # error: argument --threads:
                                                                # must be an integer >= 0, got '-4'
    p.add_argument("--lr", type=flag(float, lo=0, lo_open=True))

Config dataclasses put a field's range next to the field, ``x: Annotated[float, Range(0, 1)] = 0.2``;
:func:`check_fields` checks every field against its annotation (type, None where the type
allows it, range).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import numbers
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["Range", "flag", "flag_of", "check_fields", "field_ranges", "RGB", "folder_problem", "NotAFolderError", "check_folder", "file_problem"]


@dataclass(frozen=True)
class Range:
    """The values a number may take.

    Args:
        lo, hi: bounds (None: unbounded on that side).
        lo_open, hi_open: the bound itself is excluded.
        integer: an integer (not a bool, not 2.0 from a flag); otherwise a finite real number
            (an int is accepted as a real, a bool is not).
        length: a list of exactly this many such numbers instead of one (an RGB colour: 3).
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    length: int | None = None

    def describe(self) -> str:
        """What the range allows, for an error line: "an integer >= 1", "a finite number in [0, 1)"."""
        if self.lo is not None and self.hi is not None:
            bounds = f"in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            bounds = f"{'>' if self.lo_open else '>='} {_num(self.lo)}"
        elif self.hi is not None:
            bounds = f"{'<' if self.hi_open else '<='} {_num(self.hi)}"
        else:
            bounds = ""
        if self.length is not None:
            return f"{self.length} numbers, each finite{' and ' + bounds if bounds else ''}"
        return f"{'an integer' if self.integer else 'a finite number'}{' ' + bounds if bounds else ''}"

    def _ok(self, x: Any) -> bool:
        if isinstance(x, bool) or not isinstance(x, numbers.Real):  # numpy's numbers too, never a bool
            return False
        if self.integer and not isinstance(x, numbers.Integral):
            return False
        if not self.integer and not math.isfinite(x):
            return False
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return False
        return not (self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi))

    def ok(self, value: Any) -> bool:
        """Whether ``value`` (a parsed number, or a list of them with ``length``) is in range."""
        if self.length is None:
            return self._ok(value)
        return isinstance(value, (list, tuple)) and len(value) == self.length and all(self._ok(x) for x in value)

    def check(self, value: Any, name: str) -> Any:
        """``value`` when it is in range; else ValueError "NAME must be ..., got VALUE"."""
        if not self.ok(value):
            raise ValueError(f"{name} must be {self.describe()}, got {value!r}")
        return value


def _num(x: float) -> str:
    """A bound as written: an integer in full, a real number short (``0.5``, ``1e-06``)."""
    return str(x) if isinstance(x, int) else f"{x:g}"


# A colour: red, green, blue in [0, 1] (backgrounds).
RGB = Range(0.0, 1.0, length=3)


def flag(kind: type = float, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         hi_open: bool = False) -> Callable[[str], Any]:
    """The argparse ``type=`` of a numeric flag: the text read as ``kind`` (int or float) and
    checked against :class:`Range` ``(lo, hi, lo_open, hi_open)``; argparse.ArgumentTypeError
    ("must be an integer >= 0, got '-4'") otherwise, which argparse reports as one usage
    error line naming the flag, exit 2. The range is the returned function's ``range``."""
    rng = Range(lo, hi, lo_open, hi_open, integer=kind is int)

    def parse(text: str):
        try:
            value = kind(text)
        except (TypeError, ValueError):
            value = None
        if value is None or not rng.ok(value):
            raise argparse.ArgumentTypeError(f"must be {rng.describe()}, got {text!r}")
        return value

    parse.range = rng  # type: ignore[attr-defined]
    parse.__name__ = kind.__name__  # argparse names the type in some messages
    return parse


def flag_of(cls: type, name: str) -> Callable[[str], Any]:
    """The argparse ``type=`` of the flag that sets field ``name`` of the config dataclass
    ``cls``: :func:`flag` with the field's own :class:`Range`, so that the flag and the config
    key accept the same values (one range, beside the field)."""
    allowed, rng = _ranges_cached(cls)[name]
    if rng is None:
        rng = Range(integer=float not in allowed)
    return flag(int if rng.integer else float, rng.lo, rng.hi, lo_open=rng.lo_open, hi_open=rng.hi_open)


def field_ranges(cls: type) -> dict[str, tuple[tuple[type, ...], Range | None]]:
    """{field: (the types its annotation allows, its Range or None)} of a dataclass whose fields
    are annotated ``Annotated[T, Range(...)]`` (or plain ``T``)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = {}
    for f in dataclasses.fields(cls):
        hint, rng = hints[f.name], None
        if typing.get_origin(hint) is typing.Annotated:
            rng = next((m for m in hint.__metadata__ if isinstance(m, Range)), None)
            hint = hint.__origin__
        args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
        out[f.name] = (tuple(typing.get_origin(a) or a for a in args), rng)
    return out


def check_fields(obj: Any) -> None:
    """Check every field of the dataclass ``obj`` against its annotation: None only where the
    type allows it, a bool field a bool, a str field a str, a number in its :class:`Range`
    (ints and floats never bools, floats finite). ValueError naming the first bad field."""
    for name, (allowed, rng) in _ranges_cached(type(obj)).items():
        value = getattr(obj, name)
        if value is None and type(None) in allowed:
            continue
        if isinstance(value, str) and str in allowed:
            continue  # the field's own check reads the word (a recipe, a device, "mean")
        if bool in allowed:
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be true or false, got {value!r}")
            continue
        if rng is None and (int in allowed or float in allowed):
            rng = Range(integer=float not in allowed)
        if rng is None:
            if str in allowed and not isinstance(value, str):
                raise ValueError(f"{name} must be a string, got {value!r}")
            continue
        rng.check(value, name)


_CACHE: dict[type, dict] = {}


def _ranges_cached(cls: type) -> dict:
    if cls not in _CACHE:
        _CACHE[cls] = field_ranges(cls)
    return _CACHE[cls]


def folder_problem(path: str | os.PathLike, what: str) -> str | None:
    """Why ``path`` cannot be read as the folder ``what`` names (``"image folder"``), else None:
    ``"<what> <path> does not exist"`` or ``"<what> <path> is a file, not a folder"``, the
    one wording of every command that takes a folder (a file given for it is named as such)."""
    if os.path.isdir(path):
        return None
    if os.path.lexists(path):
        return f"{what} {path} is a file, not a folder: name the folder"
    return f"{what} {path} does not exist"


class NotAFolderError(FileNotFoundError, NotADirectoryError):
    """A folder argument that does not exist or is a file (:func:`check_folder`); caught by
    whoever catches either ``FileNotFoundError`` or ``NotADirectoryError``."""


def check_folder(path: str | os.PathLike, what: str) -> None:
    """Raise :class:`NotAFolderError` with :func:`folder_problem`'s line unless ``path`` is a folder."""
    problem = folder_problem(path, what)
    if problem:
        raise NotAFolderError(problem)


def file_problem(path: str | os.PathLike, what: str, suffix: str | None = None) -> str | None:
    """Why ``path`` cannot be read as the file ``what`` names (``"predictions file"``), else
    None: ``"<what> <path> does not exist"`` or ``"<what> <path> is a folder, not a file"``,
    naming a file of ``suffix`` (``".ply"``) the folder holds, the likely meant one."""
    if os.path.isfile(path):
        return None
    if os.path.isdir(path):
        held = sorted(e for e in os.listdir(path) if suffix and e.lower().endswith(suffix)) if suffix else []
        hint = f" (it holds {held[0]}{', ...' if len(held) > 1 else ''})" if held else ""
        return f"{what} {path} is a folder, not a file: name the file{hint}"
    return f"{what} {path} does not exist"
