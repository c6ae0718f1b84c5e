"""Every option of every command-line interface has a help text."""
from __future__ import annotations

import argparse
import importlib

import pytest

# module whose main(argv) builds the parser, and the argv that selects every subcommand
CLIS = ["camio", "evaluation", "bridge", "vggt_init", "splat_train"] + [
    f"evaluation.initialisers.{name}" for name in ("colmap_baseline", "posed", "ba_init", "oracle", "random_init")]


class _Captured(Exception):
    def __init__(self, parser):
        self.parser = parser


def _parsers(module: str, monkeypatch) -> list[argparse.ArgumentParser]:
    """The parsers a CLI builds, caught at its parse_args (nothing runs)."""
    found = []

    def capture(self, *a, **k):
        raise _Captured(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", capture)
    mod = importlib.import_module(module + ".__main__" if module in
                                  ("camio", "evaluation", "bridge", "vggt_init", "splat_train") else module)
    argvs = [[]]
    if module == "evaluation":
        argvs = [["images"], ["floor"]]  # registers the lazily imported commands' real parsers
    if module == "splat_train":
        argvs = [[], ["render"], ["export"]]
    for argv in argvs:
        try:
            mod.main(argv)
        except _Captured as cap:
            found.append(cap.parser)
    return found


def _walk(parser: argparse.ArgumentParser, name: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _walk(sub, f"{name} {sub_name}")
        elif not isinstance(action, argparse._HelpAction):
            yield name, action


@pytest.mark.parametrize("module", CLIS)
def test_every_option_has_help(module, monkeypatch):
    parsers = _parsers(module, monkeypatch)
    assert parsers, f"{module} built no parser"
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}" for p in parsers for name, a in _walk(p, module)
               if not (a.help and a.help.strip()) and a.help != argparse.SUPPRESS and a.dest != "rest"]
    assert not missing, "options without help: " + ", ".join(missing)
