"""The mvs initialiser through the DAG (the shared end-to-end run, tests/_workflow_run.py): on
the posed scene it seeds every configured Bridge mode from dense points with a confidence,
trains and scores, and is in the tables; on the photo folder (no reference cameras) it is not
run, and the log and R/initialisers.json say why."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bridge.core import BridgeConfig


@pytest.mark.slow
def test_mvs_runs_through_the_dag(workflow_run):
    run = workflow_run.results / "real" / "posedscene" / "n3" / "mvs"
    status = json.loads((run / "status.json").read_text())
    assert status["success_paper"] and status["registered"] == 3 and status["points"] > 500
    assert not (run / "predictions.npz").exists()  # a temporary file of the workflow, read by the Bridge
    for mode in workflow_run.config["bridge"]["modes"]:
        bridge = json.loads((run / mode / "bridge" / "bridge.json").read_text())
        assert bridge["source"] == "vggt" and bridge["points_kept"] > 100  # a predictions.npz, as VGGT's
        # a full map, as VGGT's: stereo's points and the filled rays, read at the paper's stride
        assert bridge["stride"] == BridgeConfig().stride
        assert bridge["depth_prior"]["source"] == "dense"
        assert (run / mode / "train" / "model.ply").is_file()
        metrics = json.loads((run / mode / "metrics.json").read_text())
        assert metrics["n_images"] > 0 and np.isfinite(metrics["psnr"])
    pose = json.loads((run / "pose.json").read_text())
    assert pose["ate_rel_radius"] < 1e-6  # the reference cameras, unchanged
    assert "real/photos: initialiser 'mvs' is not run" in workflow_run.log
    assert "| mvs |" in (workflow_run.results / "tables" / "tables.md").read_text()
