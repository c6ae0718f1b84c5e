"""The workflow quotes every path in its shell lines: a results folder and a scene folder whose
names hold a space and a single quote run through the real DAG (snakemake's CLI) and nothing
is written outside the results folder.

Files named like the first word of each folder stand beside them: an unquoted redirect or
argument would write to, or read, them instead.
"""

from __future__ import annotations

import pytest
import yaml

from _workflow_run import REPO, SNAKEMAKE_MISSING, posed_source, snakemake

pytestmark = [pytest.mark.slow, pytest.mark.skipif(SNAKEMAKE_MISSING, reason="snakemake is not installed")]

RESULTS = "my res'ults"
SCENE = "my scene's folder"


def _snapshot(root, skip):
    """Every file under ``root`` (bytes) and folder, ``skip`` (top-level names) left out."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if rel.parts[0] in skip:
            continue
        out[rel.as_posix()] = p.read_bytes() if p.is_file() else b"<dir>"
    return out


def test_paths_with_a_space_and_a_quote_run_through_the_workflow(tmp_path):
    src = posed_source(tmp_path)
    scene = src.rename(tmp_path / SCENE)
    for decoy in ("my", "my res", "'ults", "scene's", "folder"):
        (tmp_path / decoy).write_text(f"the user's {decoy}\n")
    (scene / "my").write_text("the user's file in the scene folder\n")
    cfg = yaml.safe_load((REPO / ".test" / "config.yaml").read_text())
    cfg["results"] = RESULTS
    cfg["views"] = [3]
    cfg["initialisers"] = ["posed"]
    cfg["datasets"] = {"real": {"scenes": {"posedscene": {"path": str(scene), "views": [3],
                                                          "initialisers": ["posed"]}}}}
    cfg["vggt"]["checkpoint"] = str(REPO / cfg["vggt"]["checkpoint"])
    cfg["vggt"]["model_config"] = str(REPO / cfg["vggt"]["model_config"])
    cfg_file = tmp_path / "config.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg))
    before = _snapshot(tmp_path, skip={RESULTS, ".snakemake"})

    proc = snakemake(tmp_path, cfg_file, "--cores", "2", timeout=1200)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    results = tmp_path / RESULTS / "real" / "posedscene"
    assert (results / "n3" / "posed" / "status.json").is_file(), log[-3000:]
    assert (results / "n3" / "posed" / "uniform" / "metrics.json").is_file(), log[-3000:]
    assert (tmp_path / RESULTS / "tables" / "tables.md").is_file(), log[-3000:]
    # nothing outside the results folder changed (Snakemake's own .snakemake/ aside)
    assert _snapshot(tmp_path, skip={RESULTS, ".snakemake"}) == before
