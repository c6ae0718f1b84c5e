"""One list per concept: the initialisers (evaluation/initialisers/registry.py), the Bridge modes
(bridge/core.py) and the training recipes (splat_train/recipes.py). Every copy a file must
spell out (the config schema's enums, the study's names) equals the list, and the workflow's
rules have what the registry says each initialiser runs and writes."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import yaml

from bridge.core import MODES
from evaluation.initialisers import registry
from evaluation.study import collect
from splat_train.recipes import DEFAULT_RECIPE, RECIPE_NAMES

REPO = Path(__file__).resolve().parents[1]
SCHEMA = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
INIT_SMK = (REPO / "workflow" / "rules" / "init.smk").read_text()


def test_schema_enums_equal_the_lists():
    assert SCHEMA["$defs"]["initialisers"]["items"]["enum"] == list(registry.NAMES)
    assert SCHEMA["properties"]["bridge"]["properties"]["modes"]["items"]["enum"] == list(MODES)
    recipe = SCHEMA["properties"]["train"]["properties"]["recipe"]
    assert recipe["enum"] == list(RECIPE_NAMES) and recipe["default"] == DEFAULT_RECIPE
    study_inits = SCHEMA["properties"]["study"]["properties"]["initialiser"]["enum"]
    assert study_inits == list(collect.STUDY_INITS) and set(study_inits) <= set(registry.NAMES)


def test_the_study_names_the_bridge_modes_as_the_bridge_does():
    assert collect.MODES == MODES  # evaluation may not import bridge: a copy, checked here


@pytest.mark.parametrize("name", registry.NAMES)
def test_each_initialiser_has_its_command_and_its_rule(name):
    init = registry.get(name)
    assert importlib.util.find_spec(init.command) is not None, init.command
    assert f"python -m {init.command} " in INIT_SMK, f"no rule of init.smk runs {init.command}"
    folder = "{{base}}_ba" if init.base else name
    assert f"/{folder}/{init.marker}\"" in INIT_SMK, f"no rule of init.smk writes {name}/{init.marker}"
    if init.base:
        base = registry.get(init.base)
        assert (init.confidence, init.needs) == (base.confidence, base.needs) and base.base is None
    if "predictions.npz" in init.writes:
        assert init.confidence and f"/{folder}/predictions.npz\"" in INIT_SMK


def test_the_bridge_reads_each_initialiser_by_its_output():
    assert set(registry.from_predictions()) | set(registry.from_colmap_model()) == set(registry.NAMES)
    assert not set(registry.from_predictions()) & set(registry.from_colmap_model())
    assert set(registry.from_predictions()) == {"vggt", "oracle", "vggt_ba", "oracle_ba"}
    bridge_smk = (REPO / "workflow" / "rules" / "bridge.smk").read_text()
    assert "init=INIT_FROM_PREDICTIONS" in bridge_smk and "init=INIT_FROM_COLMAP_MODEL" in bridge_smk
    # no rule file spells the list out again
    for smk in (REPO / "workflow" / "rules").glob("*.smk"):
        assert not re.search(r"vggt\|colmap|colmap\|posed", smk.read_text()), smk.name


def test_unknown_names_and_needs_are_refused():
    with pytest.raises(KeyError, match="known: vggt, colmap"):
        registry.get("nope")
    with pytest.raises(ValueError, match="unknown needs"):
        registry.Initialiser("x", "m", ("status.json",), "status.json", False, frozenset({"a GPU"}))
    with pytest.raises(ValueError, match="marker"):
        registry.Initialiser("x", "m", ("sparse/0",), "status.json", False)
