"""The random-point initialiser through the DAG: planned like the other initialisers (uniform
Bridge mode only) on a synthetic scene; seeded from random points for a posed scene's reference
cameras, trained and scored, and in the tables (the shared end-to-end run); and posed's
random-point fallback on a scene where triangulation finds no point, seeding the Bridge from the
fallback's model."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from _workflow_run import RANDOM

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = shutil.which("snakemake") or (str(Path(sys.executable).parent / "snakemake")
                                          if (Path(sys.executable).parent / "snakemake").is_file() else None)
pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def _snakemake(tmp: Path, cfg: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run([SNAKEMAKE, *args, "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp),
                           "--configfile", str(cfg)], capture_output=True, text=True, timeout=900, env=env)


def test_random_initialiser_is_planned_like_the_others(tmp_path):
    """Planned alone on a synthetic scene: its own rule, the COLMAP-model Bridge (uniform), no
    posed initialiser."""
    cfg = {
        "results": "results",
        "datasets": {"syn": {"scenes": {"tiny": {"synth": {"views": 10, "width": 64, "seed": 0}}}}},
        "views": [3],
        "initialisers": ["random"],
        "random": dict(RANDOM),
        "bridge": {"modes": ["gated"]},
        "train": {"iterations": 10, "eval_every": 10},
        "evaluation": {"lpips_nets": ["alex"]},
    }
    f = tmp_path / "config.yaml"
    f.write_text(yaml.safe_dump(cfg))
    dry = _snakemake(tmp_path, f, "-n")
    assert dry.returncode == 0, (dry.stdout + dry.stderr)[-4000:]
    assert "random_init" in dry.stdout and "bridge_colmap" in dry.stdout and "posed_init" not in dry.stdout


@pytest.mark.slow
def test_random_initialiser_runs_through_the_dag(workflow_run):
    """The shared end-to-end run (tests/_workflow_run.py), on its posed scene: seeded from
    random points for the reference cameras, uniform mode only (gated configured), trained,
    scored and tabled."""
    run = workflow_run.results / "real" / "posedscene" / "n3" / "random"
    status = json.loads((run / "status.json").read_text())
    assert status["success_paper"] and status["points"] == RANDOM["points"] and status["registered"] == 3
    assert status["seed"] == RANDOM["seed"] and status["random"]["n_points"] == RANDOM["points"]
    bridge = json.loads((run / "uniform" / "bridge" / "bridge.json").read_text())
    assert bridge["mode"] == "uniform" and bridge["input"].endswith("random/sparse/0")
    assert bridge["depth_prior"] is None  # random points carry no depth
    assert (run / "uniform" / "train" / "model.ply").is_file()
    metrics = json.loads((run / "uniform" / "metrics.json").read_text())
    assert metrics["n_images"] > 0
    assert workflow_run.config["bridge"]["modes"] == ["gated"]
    assert not (run / "gated").exists()  # no confidence: uniform only
    pose = json.loads((run / "pose.json").read_text())
    assert pose["ate_rel_radius"] < 1e-6  # the reference cameras themselves
    tables = (workflow_run.results / "tables" / "tables.md").read_text()
    assert "random" in tables


def test_posed_fallback_seeds_the_bridge_through_the_dag(tmp_path):
    import numpy as np

    from camio.images import read_image, write_image
    from camio.synthetic import write_synthetic_scene

    synth = tmp_path / "_synth"
    write_synthetic_scene(synth, views=10, width=64, seed=0, n_gt_points=500, n_ref_points=50)
    src = tmp_path / "flat_src"  # a posed scene (images + sparse/0) whose images have no feature
    shutil.copytree(synth / "sparse", src / "sparse")
    for p in sorted((synth / "images").iterdir()):
        write_image(src / "images" / p.name, np.full(read_image(p).shape, 0.5, np.float32))
    cfg = {
        "results": "results",
        "datasets": {"real": {"scenes": {"flat": {"path": "flat_src"}}}},
        "views": [3],
        "initialisers": ["posed"],
        "random": {"points": 1500, "fallback_min_points": 50},
        "train": {"iterations": 10},
    }
    f = tmp_path / "config.yaml"
    f.write_text(yaml.safe_dump(cfg))
    proc = _snakemake(tmp_path, f, "--cores", "2", "bridges")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]
    run = tmp_path / "results" / "real" / "flat" / "n3" / "posed"
    status = json.loads((run / "status.json").read_text())
    assert status["points"] == 0 and status["success_paper"] is False
    assert status["fallback"]["applied"] and status["fallback"]["min_points"] == 50
    bridge = json.loads((run / "uniform" / "bridge" / "bridge.json").read_text())
    assert bridge["input"].endswith("posed/random_fallback/sparse/0")
    assert "Gaussians" in (run / "uniform" / "logs" / "bridge.log").read_text()
