"""The whole DAG on the CI config (.test/config.yaml): tiny synthetic scene, the tiny VGGT
fixture model, all three initialisers, a few training iterations. Runs in a temporary
working directory; a few minutes on 2 CPU cores."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / "tests" / "data" / "vggt" / "shared"


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake is not installed")
@pytest.mark.skipif(not (FIXTURE / "weights.safetensors").is_file(), reason="VGGT fixture missing")
def test_ci_config_runs_end_to_end(tmp_path):
    cfg = yaml.safe_load((REPO / ".test" / "config.yaml").read_text())
    cfg["results"] = "results"
    cfg["vggt"]["checkpoint"] = str(FIXTURE / "weights.safetensors")
    cfg["vggt"]["model_config"] = str(FIXTURE / "config.json")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    proc = subprocess.run(
        ["snakemake", "--cores", "2", "--snakefile", str(REPO / "Snakefile"), "--directory",
         str(tmp_path), "--configfile", str(tmp_path / "config.yaml")],
        capture_output=True, text=True, timeout=1500)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]

    res = tmp_path / "results"
    scene = res / "ci" / "tiny"
    assert json.loads((scene / "split.json").read_text())["rule"] == "every8"
    for n in cfg["views"]:
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
    assert (res / "tables" / "tables.md").read_text().startswith("#")
    assert (res / "report" / "index.html").is_file()
