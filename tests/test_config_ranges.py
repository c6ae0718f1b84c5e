"""One range per number: every numeric flag of a stage's command line has one (runtime.checks.flag),
and the workflow schema never accepts a value that the flag or config field it feeds refuses
(workflow/schemas/config.schema.yaml; its x-maximum-from limits are read from the code)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "workflow" / "scripts"))

import check_config  # noqa: E402
from test_cli_flags import _parsers  # noqa: E402  (every CLI's parser, stopped at its parse)

from bridge.core import BridgeConfig  # noqa: E402
from evaluation.initialisers.mvs.run import MvsConfig  # noqa: E402
from runtime.checks import Range, field_ranges  # noqa: E402
from splat_train.config import field_of  # noqa: E402

# The stages' commands; benchmarks/, experiments/ and scripts/ are tools, splat_train view the viewer's own.
_STAGE_ROOTS = ("camio/", "bridge/", "splat_train/", "evaluation/", "vggt_init/", "runtime/", "imgmetrics/",
                "workflow/")
_NOT_STAGES = ("splat_train/__main__.py view", "splat_train/view/")


def _actions(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                for a in _actions(sub):
                    yield a
        else:
            yield action


def _numeric(action) -> bool:
    return action.type in (int, float) or hasattr(action.type, "range")


def test_every_numeric_flag_of_a_stage_command_has_a_range(monkeypatch):
    parsers = {k: p for k, p in _parsers(monkeypatch).items()
               if k.startswith(_STAGE_ROOTS) and not k.startswith(_NOT_STAGES)}
    assert len(parsers) >= 12, sorted(parsers)
    bare = [f"{cmd} {a.option_strings[0]}" for cmd, p in parsers.items() for a in _actions(p)
            if _numeric(a) and not hasattr(a.type, "range")]
    assert not bare, "numeric flags without a range (give them type=runtime.checks.flag(...)): " + ", ".join(bare)


def _flag_range(parsers, command: str, flag: str) -> Range:
    for a in _actions(parsers[command]):
        if flag in a.option_strings:
            return a.type.range
    raise AssertionError(f"{command} has no {flag}")


def _field_range(cls, name: str) -> Range:
    allowed, rng = field_ranges(cls)[name]
    return rng or Range(integer=float not in allowed)


# schema path -> where its value goes: (command, flag) or (config class, field)
_FEEDS = {
    "$defs.synth.views": ("camio/__main__.py", "--views"),
    "$defs.synth.width": ("camio/__main__.py", "--width"),
    "$defs.synth.seed": ("camio/__main__.py", "--seed"),
    "$defs.scene.downsample": ("camio/__main__.py", "--downsample"),
    "$defs.scene.max_size": ("camio/__main__.py", "--max-size"),
    "$defs.views.items": ("camio/__main__.py", "--n"),
    "$defs.study_noise.rot_deg": ("evaluation/initialisers/oracle.py", "--rot-deg"),
    "$defs.study_noise.trans_frac": ("evaluation/initialisers/oracle.py", "--trans-frac"),
    "$defs.study_noise.depth_rel": ("evaluation/initialisers/oracle.py", "--depth-rel"),
    "$defs.study_noise.outlier_frac": ("evaluation/initialisers/oracle.py", "--outlier-frac"),
    "$defs.study_noise.conf_noise": ("evaluation/initialisers/oracle.py", "--conf-noise"),
    "vggt.image_size": ("vggt_init/__main__.py", "--image-size"),
    "vggt.threads": ("vggt_init/__main__.py", "--threads"),
    "colmap.seed": ("evaluation/initialisers/colmap_baseline.py", "--seed"),
    "colmap.repeats": ("evaluation/initialisers/colmap_baseline.py", "--repeats"),
    "colmap.max_image_size": ("evaluation/initialisers/colmap_baseline.py", "--max-image-size"),
    "colmap.max_num_features": ("evaluation/initialisers/colmap_baseline.py", "--max-num-features"),
    "colmap.threads": ("evaluation/initialisers/colmap_baseline.py", "--threads"),
    **{f"oracle.{k}": ("evaluation/initialisers/oracle.py", "--" + k.replace("_", "-"))
       for k in ("seed", "rot_deg", "trans_frac", "depth_rel", "outlier_frac", "conf_scale", "conf_noise",
                 "downsample")},
    **{f"posed.{k}": ("evaluation/initialisers/posed.py", "--" + k.replace("_", "-"))
       for k in ("seed", "rot_deg", "trans_frac", "depth_rel", "outlier_frac")},
    "study.seeds.items": ("evaluation/initialisers/oracle.py", "--seed"),
    "random.points": ("evaluation/initialisers/random_init.py", "--points"),
    "random.seed": ("evaluation/initialisers/random_init.py", "--seed"),
    "random.fallback_min_points": ("evaluation/initialisers/posed.py", "--fallback-min-points"),
    "ba.min_points": ("evaluation/initialisers/ba_init.py", "--min-points"),
    "ba.seed": ("evaluation/initialisers/ba_init.py", "--seed"),
    "mvs.max_size": (MvsConfig, "max_size"),
    "mvs.max_sources": (MvsConfig, "max_sources"),
    "mvs.threads": (MvsConfig, "threads"),
    "bridge.stride": (BridgeConfig, "stride"),
    "bridge.max_points": (BridgeConfig, "max_points"),
    **{f"train.{k}": field_of(k) for k in ("iterations", "dropout_rate", "depth_weight", "binocular_weight",
                                                  "opacity_decay", "gaussians_per_pixel", "seed", "eval_every",
                                                  "checkpoint_every")},
    "train.threads": field_of("num_threads"),
    "evaluation.max_ate_rel_radius": ("evaluation/__main__.py", "--max-ate-rel-radius"),
    "evaluation.max_rel_rot_deg": ("evaluation/__main__.py", "--max-rel-rot-deg"),
    "evaluation.testpose_steps": ("splat_train/__main__.py testpose", "--steps"),
    "evaluation.testpose_patience": ("splat_train/__main__.py testpose", "--patience"),
}


def _schema_node(schema: dict, path: str) -> dict:
    node = schema
    for part in path.split("."):
        if part == "$defs":
            node = node["$defs"]
        elif part == "items":
            node = node["items"]
        else:
            node = node.get("properties", node)[part]
        while "$ref" in node:
            node = schema["$defs"][node["$ref"].rsplit("/", 1)[-1]]
    return node


def _schema_bounds(node: dict) -> tuple[float, bool, float, bool]:
    """(lo, lo_open, hi, hi_open) of a schema number (-inf / inf when unbounded)."""
    lo, lo_open = ((node["exclusiveMinimum"], True) if "exclusiveMinimum" in node
                   else (node.get("minimum", -math.inf), False))
    hi, hi_open = ((node["exclusiveMaximum"], True) if "exclusiveMaximum" in node
                   else (node.get("maximum", math.inf), False))
    return lo, lo_open, hi, hi_open


@pytest.fixture(scope="module")
def feeds(request):
    mp = pytest.MonkeyPatch()
    try:
        parsers = _parsers(mp)
    finally:
        mp.undo()
    out = {}
    for path, (where, name) in _FEEDS.items():
        out[path] = _flag_range(parsers, where, name) if isinstance(where, str) else _field_range(where, name)
    return out


@pytest.mark.parametrize("path", sorted(_FEEDS))
def test_the_schema_range_lies_within_the_code_range(feeds, path):
    """A workflow value the schema accepts is one the stage accepts: the schema's bounds are the
    flag's or field's, or narrower (e.g. threads >= 1 where a flag's 0 means "every core")."""
    node = _schema_node(check_config.load_schema(), path)
    rng = feeds[path]
    types = node.get("type", [])
    types = [types] if isinstance(types, str) else types
    assert ("integer" in types) == rng.integer or not rng.integer, (path, types, rng)
    lo, lo_open, hi, hi_open = _schema_bounds(node)
    if rng.lo is not None:
        assert lo > rng.lo or (lo == rng.lo and (lo_open or not rng.lo_open)), (path, node, rng)
    if rng.hi is not None:
        assert hi < rng.hi or (hi == rng.hi and (hi_open or not rng.hi_open)), (path, node, rng)


@pytest.mark.parametrize("path", ["$defs.synth.width", "$defs.scene.max_size", "vggt.image_size", "train.seed"])
def test_a_limit_the_code_defines_is_read_from_it_not_copied(path):
    raw = _schema_node(check_config.yaml.safe_load(check_config.SCHEMA.read_text()), path)
    assert "maximum" not in raw and "x-maximum-from" in raw
    assert _schema_node(check_config.load_schema(), path)["maximum"] == \
        check_config.maximum_sources()[raw["x-maximum-from"]]
