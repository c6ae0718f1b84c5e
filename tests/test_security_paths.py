"""Security: names from the config cannot make the workflow write outside its results folder.

Output paths are ``R/{dataset}/{scene}/n{n}/{init}/{mode}/...`` (workflow/rules/common.smk).
Dataset and scene names come from the config (keys of ``datasets`` and ``scenes``); ``n``,
``init`` and ``mode`` are integers or enums. Two guards must hold:

* the config schema rejects names that are not one plain path component ("../x", "..",
  "/abs", "a/b", ".hidden", empty), so a config cannot name them;
* the wildcard constraints reject the same strings, so a target path given on the command
  line cannot make a wildcard span ``..`` or ``/`` either.

Every name the schema accepts, joined under R, stays under R (a Hypothesis property).
"""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
COMMON = ROOT / "workflow" / "rules" / "config.smk"  # SCENE/RUN/MODE (included by common.smk)

BAD_NAMES = ["../x", "..", ".", "/abs", "/etc/passwd", "a/b", "a/../../b", ".hidden", "", "x\\..\\y",
             "~", "~root", "a b", "-rf", "x\n/.."]
GOOD_NAMES = ["fern", "garden_2", "mip360", "a.b-c", "Scene01", "x..y"]


@functools.lru_cache(maxsize=1)
def _schema() -> dict:
    return yaml.safe_load(SCHEMA.read_text())


@functools.lru_cache(maxsize=1)
def _validator() -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(_schema())


def _config(dataset: str = "synthetic", scene: str = "bundled") -> dict:
    return {"datasets": {dataset: {"scenes": {scene: {"synth": {"views": 8, "width": 64}}}}},
            "views": [3], "initialisers": ["vggt"]}


def _validate(cfg: dict) -> None:
    _validator().validate(cfg)


def test_schema_accepts_plain_names():
    for name in GOOD_NAMES:
        _validate(_config(dataset=name, scene=name))


@pytest.mark.parametrize("name", BAD_NAMES, ids=[repr(n) for n in BAD_NAMES])
@pytest.mark.parametrize("where", ["dataset", "scene"])
def test_schema_rejects_escaping_names(name, where):
    with pytest.raises(jsonschema.ValidationError):
        _validate(_config(**{where: name}))


@pytest.mark.parametrize("where", ["dataset", "scene"])
def test_schema_rejects_trailing_newline_in_names(where):
    """Python's ``$`` also matches before a final newline, so the schema excludes it explicitly."""
    with pytest.raises(jsonschema.ValidationError):
        _validate(_config(**{where: "x\n"}))


def _wildcard_constraints() -> dict[str, str]:
    text = COMMON.read_text()
    block = text[text.index("wildcard_constraints:"):]
    cons = {m.group(1): m.group(2) for m in re.finditer(r'^\s+(\w+)=r"([^"]+)",', block, re.M)}
    # init and mode are the lists of names, joined (the initialiser registry, the Bridge's modes)
    from bridge.core import MODES
    from evaluation.initialisers import registry

    assert 'init="|".join(initialisers.NAMES)' in block and 'mode="|".join(BRIDGE_MODES)' in block
    return {**cons, "init": "|".join(registry.NAMES), "mode": "|".join(MODES)}


def test_wildcard_constraints_reject_escaping_values():
    cons = _wildcard_constraints()
    assert {"dataset", "scene", "n", "init", "mode"} <= set(cons), cons
    for key in ("dataset", "scene"):
        for name in BAD_NAMES:
            assert not re.fullmatch(cons[key], name), f"{key} wildcard accepts {name!r}"
        for name in GOOD_NAMES:
            assert re.fullmatch(cons[key], name)
    for key in ("n", "init", "mode"):
        for name in ("..", "../3", "/3", "3/.."):
            assert not re.fullmatch(cons[key], name)


def test_schema_and_wildcards_agree_on_names():
    """One rule for names: the schema's propertyNames pattern is the wildcards' pattern."""
    schema = _schema()
    pats = {schema["properties"]["datasets"]["propertyNames"]["pattern"],
            schema["$defs"]["dataset"]["properties"]["scenes"]["propertyNames"]["pattern"]}
    cons = _wildcard_constraints()
    for pat in pats:
        core = pat.removeprefix("^").removesuffix("$")
        assert core == cons["dataset"] == cons["scene"], (pat, cons)


_name = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,12}\Z")


@settings(max_examples=60, deadline=None)
@given(ds=_name, sc=_name, n=st.integers(1, 99))
def test_accepted_names_stay_under_results(ds, sc, n):
    """Any names the schema accepts, formatted into the workflow's path patterns, resolve
    inside R (patterns copied from common.smk's SCENE/RUN/MODE)."""
    _validate(_config(dataset=ds, scene=sc))
    R = "/data/results"
    for init in ("vggt", "colmap", "oracle"):
        for path in (f"{R}/{ds}/{sc}/split.json", f"{R}/{ds}/{sc}/n{n}/{init}/gated/train/model.ply"):
            assert os.path.normpath(path).startswith(R + "/"), path
            assert os.path.normpath(path).count("/") == path.count("/"), path  # no '.' or '..' component


def test_patterns_in_common_smk_are_those_checked():
    text = COMMON.read_text()
    assert 'SCENE = f"{R}/{{dataset}}/{{scene}}"' in text
    assert 'RUN = f"{SCENE}/n{{n}}/{{init}}"' in text
    assert 'MODE = f"{RUN}/{{mode}}"' in text


@pytest.mark.slow
def test_workflow_refuses_escaping_scene_name(tmp_path):
    """The real workflow: a dry run with scene '../escape' stops at config validation."""
    cfg = _config(scene="../escape")
    cfg["results"] = str(tmp_path / "results")
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--snakefile", str(ROOT / "workflow" / "Snakefile"),
                           "--configfile", str(tmp_path / "bad.yaml"), "--directory", str(tmp_path), "--cores", "1"],
                          capture_output=True, text=True, timeout=180)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0, text
    assert "../escape" in text and ("does not match" in text or "ValidationError" in text), text[-3000:]
    assert not (tmp_path / "escape").exists() and not (tmp_path / "results").exists()
