"""Flag spellings shared by every command line: old spellings kept for one release.

One meaning per flag name across the project's CLIs (tests/test_cli_flags.py checks it):
``--seed`` is always an integer random seed, ``--seed-ply`` a seed point cloud (PLY file), ``-v``/``-q``
more / less log output after the subcommand. :func:`deprecated_flags` rewrites an old spelling
to the new one with a one-line deprecation message, before argparse sees the arguments.
"""

from __future__ import annotations

import sys
from typing import Callable

__all__ = ["deprecated_flags", "is_int", "add_log_flags", "not_a_command", "plain", "device_name", "is_device"]


def is_device(text: object) -> bool:
    """Does ``text`` name a device: auto, cpu, cuda or cuda:N (N >= 0, the GPU's index)?"""
    import re

    return isinstance(text, str) and re.fullmatch(r"auto|cpu|cuda(:[0-9]+)?", text) is not None


def device_name(text: str) -> str:
    """An argparse ``type``: ``text`` when it names a device (:func:`is_device`), else one line
    saying which names are taken (argparse prints it and exits 2)."""
    import argparse

    if is_device(text):
        return text
    raise argparse.ArgumentTypeError(f"{text!r} is not a device: use auto, cpu, cuda or cuda:N (N = the GPU's "
                                     "index, 0, 1, ...)")


def is_int(text: str) -> bool:
    """Does ``text`` read as an integer (a random seed rather than a file)?"""
    try:
        int(text)
    except ValueError:
        return False
    return True


def deprecated_flags(argv: list[str], prog: str,
                     renames: dict[str, tuple[str, Callable[[str], bool] | None]]) -> list[str]:
    """``argv`` with each deprecated flag replaced by its new name.

    Args:
        argv: the arguments after the program (and subcommand) name.
        prog: the command, for the message (e.g. "python -m splat_train").
        renames: old flag -> (new flag, test of the value or None). With a test, the flag is
            renamed only when its value passes it (``--seed seed.ply`` is the old PLY flag,
            ``--seed 3`` the new random seed); without one, always.

    Each renamed flag prints one line to stderr: "<prog>: warning: <old> is deprecated, use <new>".
    """
    out: list[str] = []
    i = 0
    told: set[str] = set()
    while i < len(argv):
        arg = argv[i]
        flag, eq, value = arg.partition("=")
        if flag in renames and argv[i:i + 1] and (eq or i + 1 < len(argv)):
            new, test = renames[flag]
            if not eq:
                value = argv[i + 1]
            if test is None or test(value):
                if flag not in told:
                    told.add(flag)
                    print(f"{prog}: warning: {flag} {value} is deprecated and will be "
                          f"removed in the next release; use {new}", file=sys.stderr)
                out += [new, value]
                i += 1 if eq else 2
                continue
        out.append(arg)
        i += 1
    return out


def add_log_flags(p, subcommand: bool = False) -> None:
    """``-v``/``--verbose`` (repeatable) and ``-q``/``--quiet`` on a parser. On a subcommand's
    parser (``subcommand=True``) they default to nothing, so that the flags work before the
    subcommand (the main parser's) and after it alike."""
    import argparse

    kw = {"default": argparse.SUPPRESS} if subcommand else {}
    p.add_argument("-v", "--verbose", action="count", help="more log output (repeatable)",
                   **(kw or {"default": 0}))
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only", **kw)


def not_a_command(module: str, instead: str) -> int:
    """What a library module beside the commands does when run as one: one line naming the
    command to use instead, exit code 2 (``python -m MODULE`` used to print nothing and exit 0)."""
    print(f"python -m {module}: error: this module is a library, not a command; use {instead}", file=sys.stderr)
    return 2


def plain(text: str | None) -> str | None:
    """``text`` (a docstring used as a --help description) without reStructuredText markup:
    ``:mod:`x``` and double back-ticks become the bare name."""
    import re

    if text is None:
        return None
    text = re.sub(r":[a-z]+:`~?([^`]*)`", r"\1", text)
    return re.sub(r"``([^`]*)``", r"\1", text)
