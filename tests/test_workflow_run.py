"""The whole DAG on the CI config (.test/config.yaml: tiny synthetic scene, the tiny VGGT
fixture model, all three initialisers, a few training iterations), read from the shared
end-to-end run (the ``workflow_run`` fixture, tests/_workflow_run.py)."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_ci_config_runs_end_to_end(workflow_run):
    res = workflow_run.results
    scene = res / "ci" / "tiny"
    assert json.loads((scene / "split.json").read_text())["rule"] == "every8"
    for n in workflow_run.config["views"]:
        for init, mode in (("vggt", "gated"), ("oracle", "gated"), ("colmap", "uniform")):
            run = scene / f"n{n}" / init
            if init == "colmap":
                status = json.loads((run / "status.json").read_text())
                assert status["n_images"] == n
                if not status["aligned_ok"]:  # a recorded failure stops the branch
                    assert not (run / mode / "metrics.json").exists()
                    continue
            assert "ate_rel_radius" in json.loads((run / "pose.json").read_text())
            metrics = json.loads((run / mode / "metrics.json").read_text())
            assert metrics["n_images"] == len(json.loads((scene / "split.json").read_text())["test"])
            assert (run / mode / "train" / "model.ply").is_file()
            assert (run / "logs").is_dir() and (run / mode / "benchmarks" / "train.tsv").is_file()
        assert not (scene / f"n{n}" / "vggt" / "predictions.npz").exists()  # temp() removed it
        floor = json.loads((scene / f"n{n}" / "floor.json").read_text())  # one per (scene, n)
        assert floor["n_images"] == len(json.loads((scene / "split.json").read_text())["test"])
    assert (res / "tables" / "tables.md").read_text().startswith("#")
    assert (res / "report" / "index.html").is_file()
