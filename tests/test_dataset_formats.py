"""The dataset formats, listed once (camio/datasets.py, ``DATASET_FORMATS``): ``python -m camio
convert --format`` offers them, the config check's ``scene.format`` enum is read from them, and
docs/contracts.md's table lists them, each in the registry's order (auto-detection's)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
import yaml

from _cli import run
from camio.datasets import DATASET_FORMATS, SceneError, dataset_format, detect_layout
from camio.scene import FORMATS, REFERENCE_FORMATS

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "workflow" / "scripts"))

import check_config  # noqa: E402


def test_the_cli_offers_every_format_with_its_description():
    out = run(["-m", "camio", "convert", "--help"])
    assert out.returncode == 0, out.stderr
    text = " ".join(out.stdout.split())
    assert "{" + ",".join(("auto", *DATASET_FORMATS)) + "}" in text
    for f in DATASET_FORMATS.values():
        assert f"{f.name}: {f.description} ({f.files})" in text, f.name


def test_the_checked_schema_reads_the_formats():
    schema = check_config.load_schema()
    fmt = schema["$defs"]["scene"]["properties"]["format"]
    assert fmt["enum"] == list(FORMATS) == ["auto", *DATASET_FORMATS] and fmt["default"] == "auto"
    assert "middlebury" in fmt["enum"]


def test_the_config_check_takes_each_format_and_refuses_a_typo(tmp_path):
    base = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg = {**base, "datasets": {"mine": {"scenes": {"a": {"path": "a", "format": "middlebury"}}}}}
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(cfg))
    assert run(["workflow/scripts/check_config.py", str(good)]).returncode == 0
    cfg["datasets"]["mine"]["scenes"]["a"]["format"] = "midlebury"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(cfg))
    proc = run(["workflow/scripts/check_config.py", str(bad)])
    assert proc.returncode == 2 and "'midlebury' is not a valid value; did you mean 'middlebury'?" in proc.stderr


def test_the_docs_table_lists_the_registry():
    text = (REPO / "docs" / "contracts.md").read_text()
    section = text.split("### Dataset formats", 1)[1].split("\n## ", 1)[0]
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in section.splitlines()
            if re.match(r"\| `", ln)]
    assert rows == [[f"`{f.name}`", f.description, f"`{f.files}`", "yes" if f.cameras else "no"]
                    for f in DATASET_FORMATS.values()]


def test_the_workflow_and_its_docs_copy_no_format_list():
    """No file of the workflow or docs spells out three format names in a row (the schema's
    copy lacked middlebury); the reference formats follow from the registry."""
    names = "|".join(DATASET_FORMATS)
    run_of_names = re.compile(rf"\b({names})\b,\s*\b({names})\b,\s*\b({names})\b")
    for path in [*(REPO / "workflow").rglob("*.smk"), *(REPO / "workflow").rglob("*.yaml"),
                 REPO / "workflow" / "README.md", REPO / "docs" / "contracts.md"]:
        assert not run_of_names.search(path.read_text()), path
    assert REFERENCE_FORMATS == tuple(n for n in DATASET_FORMATS if n != "folder")


def test_an_unknown_format_is_one_line(tmp_path):
    with pytest.raises(SceneError, match="unknown scene format 'nope'; choose one of auto, transforms, colmap"):
        dataset_format("nope")
    proc = run(["-m", "camio", "convert", "--src", str(tmp_path), "--out", str(tmp_path / "o"), "--format", "nope"])
    assert proc.returncode == 2 and "invalid choice: 'nope'" in proc.stderr and not (tmp_path / "o").exists()


def test_detection_asks_the_registry_in_order(tmp_path):
    """A folder with a Middlebury camera file is detected as middlebury; with cams/*_cam.txt as
    well, mvsnet (asked first); a folder of unknown camera files is refused, naming the formats."""
    (tmp_path / "x_par.txt").write_text("0\n")
    assert detect_layout(tmp_path) == "middlebury"
    (tmp_path / "cams").mkdir()
    (tmp_path / "cams" / "00000000_cam.txt").write_text("")
    assert detect_layout(tmp_path) == "mvsnet"
    other = tmp_path / "other"
    other.mkdir()
    (other / "bundle.out").write_text("")
    with pytest.raises(SceneError, match=r"known: transforms transforms.json, colmap sparse/0, .*middlebury \*_par.txt\)"):
        detect_layout(other)
