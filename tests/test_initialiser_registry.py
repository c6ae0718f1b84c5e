"""One list per concept: the initialisers (evaluation/initialisers/registry.py), the Bridge modes
(runtime/modes.py) and the training recipes (splat_train/recipes.py). The config schema names
these lists rather than copying them (``x-enum-from``, filled by the config check), the stages
and the study read them, and the workflow's rules have what the registry says each initialiser
runs and writes."""

from __future__ import annotations

import ast
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from bridge.core import MODES
from runtime.modes import BRIDGE_MODES
from evaluation.initialisers import registry
from evaluation.study import collect
from splat_train.recipes import RECIPE_NAMES
from vggt_init.defaults import POINT_SOURCES

REPO = Path(__file__).resolve().parents[1]
SCHEMA_FILE = REPO / "workflow" / "schemas" / "config.schema.yaml"
INIT_SMK = (REPO / "workflow" / "rules" / "init.smk").read_text()
sys.path.insert(0, str(REPO / "workflow" / "scripts"))

import check_config  # noqa: E402


def test_the_checked_schema_reads_the_lists():
    schema = check_config.load_schema()
    assert schema["$defs"]["initialisers"]["items"]["enum"] == list(registry.NAMES)
    assert schema["properties"]["bridge"]["properties"]["modes"]["items"]["enum"] == list(BRIDGE_MODES)
    recipe = schema["properties"]["train"]["properties"]["recipe"]
    assert recipe["enum"] == [*RECIPE_NAMES, None] and recipe["default"] is None  # null: DEFAULT_RECIPE
    assert schema["properties"]["study"]["properties"]["initialiser"]["enum"] == list(registry.studied())
    points_from = schema["properties"]["vggt"]["properties"]["points_from"]
    assert points_from["enum"] == [*POINT_SOURCES, None] and points_from["default"] is None  # null: vggt_init's


def test_the_schema_file_copies_no_list():
    """No enum of the schema file spells out one of the lists, in whole or in part (each is
    x-enum-from); a single name (study.references: colmap) is a choice, not a copy."""
    lists = {tuple(v) for v in check_config.enum_sources().values()}
    enums = []

    def walk(node):
        if isinstance(node, dict):
            if "enum" in node:
                enums.append(tuple(v for v in node["enum"] if v is not None))
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(yaml.safe_load(SCHEMA_FILE.read_text()))
    copies = {e for e in enums if any(len(set(e) & set(lst)) >= 2 for lst in lists)}
    assert enums and not copies, copies


def test_a_bad_list_name_in_the_schema_is_one_line(tmp_path):
    bad = tmp_path / "schema.yaml"
    bad.write_text(SCHEMA_FILE.read_text().replace("x-enum-from: bridge_modes", "x-enum-from: bridge_mode"))
    with pytest.raises(ValueError, match="x-enum-from 'bridge_mode' names no list; known: initialisers"):
        check_config.load_schema(bad)


def test_the_study_and_the_bridge_read_one_mode_list():
    assert collect.MODES is BRIDGE_MODES and MODES is BRIDGE_MODES
    assert collect.STUDY_INITS == registry.studied() == ("oracle", "posed")


def test_reading_the_lists_imports_no_heavy_module():
    """The config check reads the lists from light modules: no torch at workflow start."""
    code = ("import sys; sys.path.insert(0, 'workflow/scripts'); import check_config; "
            "check_config.load_schema(); print(sorted({'torch', 'pandas'} & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_no_module_spells_out_the_bridge_modes():
    """The tuple ("gated", "uniform", "filtered") is written once in the packages: runtime/modes.py."""
    found = []
    for pkg in ("runtime", "camio", "vggt_init", "bridge", "splat_train", "evaluation", "benchmarks", "experiments"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.Tuple, ast.List)) and len(node.elts) >= 2 and all(
                        isinstance(e, ast.Constant) and e.value in BRIDGE_MODES for e in node.elts):
                    found.append(str(path.relative_to(REPO)))
    assert found == ["runtime/modes.py"], found


@pytest.mark.parametrize("name", registry.NAMES)
def test_each_initialiser_has_its_command_and_its_rule(name):
    init = registry.get(name)
    assert importlib.util.find_spec(init.command) is not None, init.command
    if not init.own_rule:  # the common rule runs it (tests/test_add_initialiser.py)
        assert "init=INIT_COMMON_RULE" in INIT_SMK and "python -m {params.command} " in INIT_SMK
        return
    assert f"python -m {init.command} " in INIT_SMK, f"no rule of init.smk runs {init.command}"
    folder = "{{base}}_ba" if init.base else "{{base}}_mvs" if init.cameras_from else name
    assert f"/{folder}/{init.marker}\"" in INIT_SMK, f"no rule of init.smk writes {name}/{init.marker}"
    if init.base:
        base = registry.get(init.base)
        assert (init.confidence, init.needs) == (base.confidence, base.needs) and base.base is None
    if "predictions.npz" in init.writes:
        assert init.confidence and f"/{folder}/predictions.npz\"" in INIT_SMK


@pytest.mark.parametrize("name", registry.studied())
def test_a_studied_initialiser_takes_the_noise_flags(name):
    """Its command offers the study's noise flags (its --help, as the study's jobs call it)."""
    out = subprocess.run([sys.executable, "-m", registry.get(name).command, "--help"], capture_output=True,
                         text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    for flag in ("--rot-deg", "--trans-frac", "--depth-rel", "--outlier-frac"):
        assert flag in out.stdout, (name, flag)


def test_the_bridge_reads_each_initialiser_by_its_output():
    assert set(registry.from_predictions()) | set(registry.from_colmap_model()) == set(registry.NAMES)
    assert not set(registry.from_predictions()) & set(registry.from_colmap_model())
    assert set(registry.from_predictions()) == {"vggt", "oracle", "mvs", "vggt_ba", "oracle_ba", "vggt_mvs",
                                                "colmap_mvs"}
    bridge_smk = (REPO / "workflow" / "rules" / "bridge.smk").read_text()
    assert "init=INIT_FROM_PREDICTIONS" in bridge_smk and "init=INIT_FROM_COLMAP_MODEL" in bridge_smk
    assert "base=BA_FROM_PREDICTIONS" in INIT_SMK and "base=BA_FROM_COLMAP_MODEL" in INIT_SMK
    assert "base=DENSE_FROM" in INIT_SMK


def test_a_dense_step_starts_from_its_bases_cameras():
    """``<base>_mvs``: multi-view stereo on ``base``'s COLMAP model, needing what ``base`` needs."""
    dense = {n: i for n, i in registry.INITIALISERS.items() if i.cameras_from}
    assert set(dense) == {"vggt_mvs", "colmap_mvs"} and registry.dense_bases() == ("vggt", "colmap")
    for name, init in dense.items():
        base = registry.get(init.cameras_from)
        assert name == f"{base.name}_mvs" and init.needs == base.needs and init.confidence
        assert init.command == registry.get("mvs").command
    # no rule file spells a list out again
    for smk in (REPO / "workflow" / "rules").glob("*.smk"):
        text = smk.read_text()
        assert not re.search(r"vggt\|colmap|colmap\|posed|vggt\|oracle|gated\|uniform", text), smk.name
        assert not re.search(r"\(\s*\"vggt\",\s*\"vggt_ba\"", text), smk.name


def test_unknown_names_and_needs_are_refused():
    with pytest.raises(KeyError, match="known: vggt, colmap"):
        registry.get("nope")
    with pytest.raises(ValueError, match="unknown needs"):
        registry.Initialiser("x", "m", ("status.json",), "status.json", False, frozenset({"a GPU"}))
    with pytest.raises(ValueError, match="marker"):
        registry.Initialiser("x", "m", ("sparse/0",), "status.json", False)
    with pytest.raises(ValueError, match="the common rule runs a CPU command that writes sparse/0 and status.json"):
        registry.Initialiser("x", "m", ("predictions.npz", "sparse/0", "status.json"), "status.json", True)
    assert not registry.with_common_rule()  # every shipped initialiser has its rule


def test_reports_and_planning_name_no_initialiser():
    """Reports, the study, planning and the workflow's scripts read order, labels, roles and
    what follows a run from the registry: no initialiser's name as a string literal there (a
    config block's key, ``config["vggt"]`` or ``cfg["vggt"]``, is that initialiser's own block)."""
    names = "|".join(sorted(registry.NAMES, key=len, reverse=True))
    literal = re.compile(rf"(?<!config\[)(?<!cfg\[)[\"']({names})[\"']")
    files = [*(REPO / "evaluation" / "reports").glob("*.py"), *(REPO / "evaluation" / "study").glob("*.py"),
             *(REPO / "workflow" / "scripts").glob("*.py"), *(REPO / "scripts").glob("*.py"),
             *(REPO / "workflow" / "rules" / f"{n}.smk" for n in ("planning", "study_plan", "targets", "scenes",
                                                                  "params", "evaluate", "bridge", "train"))]
    found = [f"{f.relative_to(REPO)}:{i}: {ln.strip()}" for f in files
             for i, ln in enumerate(f.read_text().splitlines(), 1) if literal.search(ln)]
    assert len(files) > 20 and not found, found


def test_roles_order_and_labels_come_from_the_registry():
    assert (registry.with_role("ours"), registry.with_role("baseline")) == ("vggt", "colmap")
    assert registry.checkpointed() == ("colmap",)
    assert [registry.rank(n) for n in registry.NAMES] == list(range(len(registry.NAMES)))
    assert registry.rank("not_an_initialiser") == len(registry.NAMES)
    assert registry.label("vggt") == "vggt" and registry.label("elsewhere") == "elsewhere"
    with pytest.raises(ValueError, match="role 'best' is not one of ours, baseline"):
        registry.Initialiser("x", "m", ("sparse/0", "status.json"), "status.json", False, role="best")


def test_a_bad_option_is_refused_when_the_registry_is_read():
    """An entry's options are checked where they are written: key, type, default, range, and
    that an initialiser with a rule of its own takes none (its params function does)."""
    opt = registry.Option("max_points", "integer", 100, "keep at most this many points", minimum=1)
    assert (opt.flag, opt.args(7), opt.args(None), registry.Option("fast", "boolean", False, "h").args(True)) == (
        "--max-points", ["--max-points", "7"], [], ["--fast"])
    assert opt.schema() == {"type": "integer", "default": 100, "description": "keep at most this many points",
                            "minimum": 1}
    for kwargs, message in (({"key": "Max-Points"}, "lower case"), ({"type": "int"}, "not one of integer"),
                            ({"default": "100"}, "is not of type integer"), ({"default": True}, "is not of type"),
                            ({"type": "string", "default": "a"}, "a range needs a number")):
        with pytest.raises(ValueError, match=message):
            registry.Option(**{"key": "max_points", "type": "integer", "default": 100, "help": "h",
                               "minimum": 1, **kwargs})
    model = ("sparse/0", "status.json")
    with pytest.raises(ValueError, match="options are for the common rule"):
        registry.Initialiser("x", "m", model, "status.json", False, own_rule=True, options=(opt,))
    with pytest.raises(ValueError, match="an option key is given twice"):
        registry.Initialiser("x", "m", model, "status.json", False, options=(opt, opt))
    assert registry.option_blocks() == {}  # no shipped initialiser runs on the common rule


def test_an_option_block_beside_a_block_of_the_schema_is_refused(monkeypatch):
    monkeypatch.setattr(registry, "option_blocks", lambda: {"random": {"type": "object"}})
    with pytest.raises(ValueError, match="the initialiser random has options in the registry and a block of its own"):
        check_config.load_schema()
