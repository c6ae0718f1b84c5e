"""The posed initialiser through the DAG on a converted posed scene (a COLMAP folder, so no
ground-truth depth: the oracle cannot run there and the DAG says so), and its planning beside
a scene without reference cameras. The run itself is the shared end-to-end run
(tests/_workflow_run.py), whose ``real`` dataset is this test's two scenes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from _workflow_run import SNAKEMAKE_MISSING, photo_folder, posed_source, snakemake

pytestmark = pytest.mark.skipif(SNAKEMAKE_MISSING, reason="snakemake is not installed")


def _config(tmp: Path) -> Path:
    photo_folder(tmp, tmp / "posed_src")
    cfg = {
        "results": "results",
        "datasets": {"real": {"scenes": {"posedscene": {"path": "posed_src"},
                                         "photos": {"path": "photos", "format": "folder"}}}},
        "views": [3],
        "initialisers": ["posed", "oracle"],
        "train": {"iterations": 10},
    }
    f = tmp / "config.yaml"
    f.write_text(yaml.safe_dump(cfg))
    return f


def test_posed_is_planned_where_reference_cameras_exist(tmp_path):
    posed_source(tmp_path)
    cfg = _config(tmp_path)
    dry = snakemake(tmp_path, cfg, "-n", "-p", timeout=600)
    out = dry.stdout + dry.stderr
    assert dry.returncode == 0, out
    # named in the log: the oracle needs ground truth, posed needs reference cameras
    assert "real/posedscene: initialiser 'oracle' is not run" in out
    assert "real/photos: initialiser 'posed' is not run" in out
    assert "rule oracle_init" not in out and "rule posed_init" in out


@pytest.mark.slow
def test_posed_runs_through_the_dag(workflow_run):
    assert "real/posedscene: initialiser 'oracle' is not run" in workflow_run.log
    assert "real/photos: initialiser 'posed' is not run" in workflow_run.log
    run = workflow_run.results / "real" / "posedscene" / "n3" / "posed"
    status = json.loads((run / "status.json").read_text())
    assert status["success_paper"] and status["registered"] == 3 and status["points"] > 0
    pose = json.loads((run / "pose.json").read_text())
    assert pose["success_paper"] and pose["success_gated"] and pose["ate_rel_radius"] < 1e-6
    assert (run / "uniform" / "bridge" / "seed.ply").is_file()
    assert not (workflow_run.results / "real" / "photos" / "n3" / "posed").exists()
    notes = json.loads((workflow_run.results / "initialisers.json").read_text())["skipped"]
    assert {(s["scene"], s["init"]) for s in notes} == {("posedscene", "oracle"), ("photos", "posed"),
                                                       ("photos", "mvs"), ("photos", "oracle")}
