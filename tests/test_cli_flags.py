"""Every command line speaks the same language: one meaning per flag name across all the
project's CLIs (the same kind of value: a switch, a count, an integer, a number or a text /
path), ``-v``/``-q`` after the subcommand as before it, the old flag spellings working with a
deprecation line, and library modules beside the commands refusing to run as commands."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import inspect
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_PACKAGES = ("runtime", "camio", "imgmetrics", "vggt_init", "bridge", "splat_train", "evaluation", "benchmarks", "experiments", "scripts", "workflow")
# splat_train dispatches its subcommands by hand: each is its own parser
_SUBCOMMANDS = {"splat_train/__main__.py": ([], ["render"], ["testpose"], ["view"], ["export"])}


class _Parsed(Exception):
    def __init__(self, parser):
        self.parser = parser


def _cli_files() -> list[Path]:
    out = []
    for pkg in _PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            if "node_modules" not in f.parts and "ArgumentParser(" in f.read_text(errors="replace"):
                out.append(f.relative_to(ROOT))
    return out


def _load(rel: Path):
    if rel.parts[0] in ("scripts", "workflow", "benchmarks", "experiments") and rel.name != "__main__.py":
        spec = importlib.util.spec_from_file_location(f"_cli_{rel.stem}", ROOT / rel)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return importlib.import_module(".".join(rel.with_suffix("").parts))


def _parsers(monkeypatch) -> dict[str, argparse.ArgumentParser]:
    """{command: parser} of every CLI: its main() is called and stopped at its parse."""
    def stop(self, *args, **kwargs):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", stop)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", stop)
    found = {}
    for rel in _cli_files():
        mod = _load(rel)
        main = getattr(mod, "main", None)
        if main is None:
            continue
        for argv in _SUBCOMMANDS.get(str(rel), ([],)):
            monkeypatch.setattr(sys, "argv", [str(rel), *argv])
            try:
                main(list(argv)) if inspect.signature(main).parameters else main()
            except _Parsed as got:
                found[" ".join([str(rel), *argv])] = got.parser
    return found


def _kind(action: argparse.Action) -> str:
    if isinstance(action, argparse._CountAction):
        return "count"
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction,
                           argparse._StoreConstAction)):
        return "switch"
    rng = getattr(action.type, "range", None)  # a runtime.checks.flag: a number with a range
    if action.type in (int,) or (rng is not None and rng.integer):
        return "integer"
    if action.type in (float,) or rng is not None:
        return "number"
    return "text or path"


def _flags(parser: argparse.ArgumentParser, where: str, out: dict) -> None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                _flags(sub, f"{where} {name}", out)
            continue
        for opt in action.option_strings:
            if opt not in ("-h", "--help"):
                out.setdefault(opt, {}).setdefault(_kind(action), []).append(where)


def test_one_meaning_per_flag_name(monkeypatch):
    parsers = _parsers(monkeypatch)
    for cli in ("camio/__main__.py", "evaluation/__main__.py", "splat_train/__main__.py view",
                "bridge/__main__.py", "evaluation/initialisers/ba_init.py", "scripts/photos.py"):
        assert cli in parsers, sorted(parsers)
    flags: dict = {}
    for where, parser in parsers.items():
        _flags(parser, where, flags)
    clashes = {opt: kinds for opt, kinds in flags.items() if len(kinds) > 1}
    assert not clashes, "one flag name, several kinds of value:\n" + "\n".join(
        f"  {opt}: " + "; ".join(f"{k} in {', '.join(v[:3])}" for k, v in kinds.items()) for opt, kinds in clashes.items())
    assert set(flags["--seed"]) == {"integer"}  # a random seed everywhere, never the seed PLY
    assert set(flags["--seed-ply"]) == {"text or path"}


def test_every_stage_command_takes_v_and_q_after_its_subcommand(monkeypatch):
    parsers = _parsers(monkeypatch)
    stages = {k: p for k, p in parsers.items()
              if k.split()[0].startswith(("camio/", "vggt_init/", "bridge/", "splat_train/", "evaluation/"))}
    for where, parser in stages.items():
        flags: dict = {}
        _flags(parser, where, flags)
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        leaves = [f"{where} {n}" for a in subs for n in a.choices] or [where]
        for leaf in leaves:
            if leaf.endswith((" images", " floor")) and leaf.startswith("evaluation/__main__"):
                continue  # registered lazily (only when it is the command)
            for opt in ("-v", "-q"):
                assert leaf in flags.get(opt, {}).get("count" if opt == "-v" else "switch", []), (leaf, opt)


def test_one_error_prefix_style(monkeypatch):
    """argparse's errors read "python -m PACKAGE[ SUBCOMMAND]: error: ..." for every stage."""
    for where, parser in _parsers(monkeypatch).items():
        rel = where.split()[0]
        if rel.startswith(("camio/", "vggt_init/", "bridge/", "splat_train/", "evaluation/")):
            package = rel.split("/")[0]
            assert parser.prog.startswith(f"python -m {package}"), (where, parser.prog)
        for action in parser._actions:  # "required: command", the same word everywhere
            if isinstance(action, argparse._SubParsersAction):
                assert action.dest == "command", (where, action.dest)


def test_help_texts_are_plain_words(monkeypatch):
    """No reStructuredText markup (a :mod: role, double back-ticks) in any --help."""
    import re

    def walk(parser, where):
        yield where, parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, f"{where} {name}")

    for where, parser in _parsers(monkeypatch).items():
        for leaf, p in walk(parser, where):
            markup = re.findall(r":[a-z]+:`[^`]*`|``[^`]*``", p.format_help())
            assert not markup, (leaf, markup[:3])


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120, cwd=ROOT)


def test_camio_takes_q_after_the_subcommand(tmp_path):
    proc = _run("-m", "camio", "synth", "-q", "--out", str(tmp_path / "s"), "--views", "4", "--width", "32")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_old_spellings_work_with_a_deprecation_line(tmp_path):
    from runtime.cliargs import deprecated_flags
    from splat_train.__main__ import _OLD_TRAIN_FLAGS

    argv = deprecated_flags(["--seed", "a/seed.ply", "--seed-rng", "3", "--out", "o"], "python -m splat_train",
                            _OLD_TRAIN_FLAGS)
    assert argv == ["--seed-ply", "a/seed.ply", "--seed", "3", "--out", "o"]
    assert deprecated_flags(["--seed", "3"], "x", _OLD_TRAIN_FLAGS) == ["--seed", "3"]  # the new meaning
    proc = _run("-m", "splat_train", "view", "--model", str(tmp_path / "m.ply"), "--seed", str(tmp_path / "s.ply"))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2
    assert lines[0] == (f"python -m splat_train view: warning: --seed {tmp_path / 's.ply'} is deprecated and will be "
                        "removed in the next release; use --seed-ply")
    assert lines[1].startswith("python -m splat_train view: error:")


@pytest.mark.parametrize("module", ["colmap_repeats", "colmap_run", "views"])
@pytest.mark.parametrize("args", [[], ["--help"], ["--bogus"]])
def test_library_modules_are_not_commands(module, args):
    proc = _run("-m", f"evaluation.initialisers.{module}", *args)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith(f"python -m evaluation.initialisers.{module}: error: this module is a library")
    assert len(proc.stderr.strip().splitlines()) == 1


def test_a_failing_step_never_logs_done(tmp_path):
    (tmp_path / "src").mkdir()
    proc = _run("-m", "camio", "convert", "--src", str(tmp_path / "src"), "--out", str(tmp_path / "out"))
    assert proc.returncode == 2
    assert "convert failed after" in proc.stderr and " done" not in proc.stderr, proc.stderr


def test_viewer_on_a_busy_port_names_it_and_suggests_port_0(tmp_path):
    import socket

    from splat_train.view.server import ViewerNotInstalled, check_installed

    try:
        check_installed()
    except ViewerNotInstalled:
        pytest.skip("the viewer's browser files are not installed (make install)")
    import numpy as np

    from camio.ply import GaussianCloud, write_gaussian_ply

    n = 4
    write_gaussian_ply(tmp_path / "model.ply", GaussianCloud(
        means=np.zeros((n, 3), np.float32), sh_dc=np.zeros((n, 3), np.float32),
        sh_rest=np.zeros((n, 0, 3), np.float32), opacity_logit=np.zeros(n, np.float32),
        log_scales=np.zeros((n, 3), np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1))))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        proc = _run("-m", "splat_train", "view", "--model", str(tmp_path / "model.ply"), "--port", str(port),
                    "--no-browser")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        f"python -m splat_train view: error: port {port} on 127.0.0.1 is already in use (another viewer?); "
        "pass --port 0 to pick a free one"]
