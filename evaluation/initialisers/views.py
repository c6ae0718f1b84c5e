"""Which views an initialiser trains on: the command-line choice every initialiser offers.

``--split JSON --n N`` (the training list for n in a split.json, docs/contracts.md),
``--image-list FILE`` (one image name per line; blank lines and ``#`` comments skipped) or
``--names NAME ...``; :func:`training_names` reads whichever was given.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from runtime.checks import file_problem, flag

__all__ = ["add_view_args", "read_image_list", "training_names", "parse_training_args"]


def add_view_args(p: argparse.ArgumentParser, split: bool = True) -> None:
    """``--split``/``--n`` (when ``split``), ``--image-list`` and ``--names`` on ``p``."""
    if split:
        p.add_argument("--split", help="split.json (docs/contracts.md); use with --n")
        p.add_argument("--n", type=flag(int, 1), help="number of training views (key in split.json)")
    p.add_argument("--image-list", help="file with one training image name per line")
    p.add_argument("--names", nargs="+", help="training image names (instead of --image-list)")


def read_image_list(path: str | Path) -> list[str]:
    """The names in an image list (one per line; blank lines and ``#`` comments skipped).

    Raises:
        ValueError: the file does not exist, is a folder (:func:`runtime.checks.file_problem`'s line)
            or names no image.
    """
    lst = Path(path)
    problem = file_problem(lst, "image list")
    if problem:
        raise ValueError(problem)
    names = [ln.strip() for ln in lst.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not names:
        raise ValueError(f"image list {lst} is empty: one training image name per line")
    from runtime.names import check_name_list

    return check_name_list(names, lst)


def training_names(args: argparse.Namespace) -> list[str]:
    """The training names from the arguments of :func:`add_view_args`.

    Raises:
        ValueError: none given, ``--split`` without ``--n``, a split without that n, or a bad list.
    """
    if getattr(args, "split", None):
        if args.n is None:
            raise ValueError("--split needs --n (the number of training views)")
        from runtime.names import check_name_list

        try:
            data = json.loads(Path(args.split).read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{args.split}: not a split.json (JSON): {exc}") from None
        train = data.get("train") if isinstance(data, dict) else None
        if not isinstance(train, dict) or str(args.n) not in train:
            raise ValueError(f"{args.split} has no training list for n = {args.n}; "
                             f"it has {sorted(train) if isinstance(train, dict) else []}")
        if not isinstance(train[str(args.n)], list):
            raise ValueError(f"{args.split}: the training list for n = {args.n} must be a list of names")
        return check_name_list(train[str(args.n)], args.split)  # plain names, none twice
    if args.image_list:
        return read_image_list(args.image_list)
    if args.names:
        from runtime.names import check_name_list

        return check_name_list(args.names, "--names")
    if hasattr(args, "split"):
        raise ValueError("give the training images: --split JSON --n N, --image-list FILE or --names NAME ...")
    raise ValueError("give the training images: --image-list FILE or --names NAME ...")


def parse_training_args(p: argparse.ArgumentParser, argv: list[str] | None) -> tuple[argparse.Namespace, list[str]]:
    """Parse ``argv`` with ``p`` (which has :func:`add_view_args` and ``-v``), start logging and
    read the training names; a bad choice of views is argparse's usage line and exit code 2."""
    from runtime.logs import setup_logging

    args = p.parse_args(argv)
    setup_logging(args.verbose, getattr(args, "quiet", False))
    try:
        names = training_names(args)
    except ValueError as exc:
        p.error(str(exc))
    return args, names


if __name__ == "__main__":
    import sys

    from runtime.cliargs import not_a_command

    sys.exit(not_a_command("evaluation.initialisers.views", "one of the initialisers, e.g. python -m evaluation.initialisers.colmap_baseline --help"))
