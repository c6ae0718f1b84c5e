"""Defaults defined once in code: the CLI flags read the constants, and the copies that a YAML
file must spell out (config.yaml, the workflow schema) agree with them."""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from evaluation.metrics.pose import MAX_ATE_REL_RADIUS, MAX_REL_ROT_DEG, GateConfig, add_gate_args, gate_from_args
from vggt_init import defaults as vggt_defaults

REPO = Path(__file__).resolve().parents[1]


def _schema() -> dict:
    return yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())


def test_gate_defaults_in_yaml_equal_the_code_constants():
    props = _schema()["properties"]["evaluation"]["properties"]
    assert props["max_ate_rel_radius"]["default"] == MAX_ATE_REL_RADIUS
    assert props["max_rel_rot_deg"]["default"] == MAX_REL_ROT_DEG
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())["evaluation"]
    assert cfg["max_ate_rel_radius"] == MAX_ATE_REL_RADIUS and cfg["max_rel_rot_deg"] == MAX_REL_ROT_DEG
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
    points_from = _schema()["properties"]["vggt"]["properties"]["points_from"]
    assert points_from["default"] == vggt_defaults.POINTS_FROM
    assert tuple(points_from["enum"]) == vggt_defaults.POINT_SOURCES


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


def test_testpose_defaults_live_in_code():
    """evaluation.testpose_steps: null means splat_train.testpose.DEFAULT_STEPS; the patience
    default is DEFAULT_PATIENCE in the schema, the CLI and the functions."""
    import inspect

    from splat_train.__main__ import _testpose_parser
    from splat_train.testpose import DEFAULT_PATIENCE, DEFAULT_STEPS, refine_test_pose, run_testpose

    props = _schema()["properties"]["evaluation"]["properties"]
    assert props["testpose_steps"]["default"] is None
    assert f"DEFAULT_STEPS, {DEFAULT_STEPS}" in " ".join(props["testpose_steps"]["description"].split())
    assert props["testpose_patience"]["default"] == DEFAULT_PATIENCE
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
    import ast
    import inspect

    from vggt_init import preprocess

    for fn in (preprocess.resized_size, preprocess.preprocess_rgb, preprocess.load_and_preprocess):
        assert inspect.signature(fn).parameters["target"].default == vggt_defaults.IMAGE_SIZE, fn.__name__
    for path in (REPO / "vggt_init" / "preprocess.py", REPO / "vggt_init" / "run.py",
                 REPO / "vggt_init" / "__main__.py", REPO / "bridge" / "__main__.py"):
        consts = [n.value for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Constant)]
        assert vggt_defaults.IMAGE_SIZE not in consts, path
    smk = (REPO / "workflow" / "rules" / "resources.smk").read_text()
    assert str(vggt_defaults.IMAGE_SIZE) not in smk and "IMAGE_SIZE" in smk
