"""Defaults defined once in code: the CLI flags read the constants, the copies that a YAML
file must spell out (config.yaml, the workflow schema) agree with them, and no number that a
config dataclass, a registry or a defaults module defines appears as a literal elsewhere in the
package code, the CLIs or the workflow (the AST walk of tests/_default_literals.py)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

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
    ("splat_train/__main__.py", "checkpoint_every"):
        "splat_train's: --checkpoint-every's help writes TrainConfig's 500 by hand (%(default)s removes it)",
    ("splat_train/__main__.py", "eval_every"):
        "splat_train's: --eval-every's help writes TrainConfig's 200 by hand (%(default)s removes it)",
    ("evaluation/initialisers/colmap_baseline.py", "max_image_size"):
        "--max-image-size's default= writes ColmapSettings' 3200 (default=ColmapSettings().max_image_size)",
    ("evaluation/initialisers/colmap_baseline.py", "max_num_features"):
        "--max-num-features's default= writes ColmapSettings' 16384 (default=ColmapSettings().max_num_features)",
    ("evaluation/initialisers/triangulate.py", "max_image_size"):
        "triangulate_known_poses' parameter writes ColmapSettings' 3200 (take a ColmapSettings)",
    ("evaluation/initialisers/triangulate.py", "max_num_features"):
        "triangulate_known_poses' parameter writes ColmapSettings' 16384 (take a ColmapSettings)",
    ("workflow/schemas/config.schema.yaml", "conf_scale"):
        "workflow/rules/study_plan.smk gives every study cell --conf-scale from config oracle, so the schema "
        "fills it (null once that rule passes it only when set); test_schema_defaults_are_null_or_the_stages "
        "compares it with the oracle's",
}


def test_no_default_number_repeats_as_a_literal():
    """Every number a config dataclass, registry or defaults module defines (SOURCES of
    tests/_default_literals.py) is written there only: elsewhere the code imports the constant
    (argparse defaults read the dataclass, their help says %(default)s), the YAML leaves it out
    or null."""
    found = literals.repeats(REPO, shared={**SHARED, **UNRESOLVED})
    assert not found, "defaults written again as literals (import the constant):\n" + "\n".join(found)


def test_unresolved_repeats_are_still_there():
    """Each UNRESOLVED entry still names a repeat (a resolved one leaves the list)."""
    found = literals.repeats(REPO, shared=SHARED)
    for rel, name in UNRESOLVED:
        assert any(line.startswith(f"{rel}:") and f"({name})" in line for line in found), (rel, name)


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
