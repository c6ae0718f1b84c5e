"""The posed initialiser through the DAG on a converted posed scene (a COLMAP folder, so no
ground-truth depth: the oracle cannot run there and the DAG says so), and its planning beside
a scene without reference cameras."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = shutil.which("snakemake")
pytestmark = pytest.mark.skipif(SNAKEMAKE is None, reason="snakemake is not installed")


def _posed_source(root: Path) -> Path:
    """A posed real-style scene: images/ + sparse/0 (no gt/), from the synthetic generator."""
    from camio.synthetic import write_synthetic_scene

    synth = root / "_synth"
    write_synthetic_scene(synth, views=12, width=128, seed=0, n_gt_points=4000, n_ref_points=300)
    src = root / "posed_src"
    shutil.copytree(synth / "images", src / "images")
    shutil.copytree(synth / "sparse", src / "sparse")
    shutil.rmtree(synth)
    return src


def _config(tmp: Path) -> Path:
    (tmp / "photos").mkdir()
    for i in range(4):
        shutil.copy(tmp / "posed_src" / "images" / f"{i:04d}.png", tmp / "photos" / f"{i:04d}.png")
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


def _snakemake(tmp: Path, cfg: Path, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([SNAKEMAKE, *args, "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp),
                           "--configfile", str(cfg)], capture_output=True, text=True, timeout=timeout)


def test_posed_runs_through_the_dag(tmp_path):
    _posed_source(tmp_path)
    cfg = _config(tmp_path)
    dry = _snakemake(tmp_path, cfg, "-n", "-p")
    out = dry.stdout + dry.stderr
    assert dry.returncode == 0, out
    # named in the log: the oracle needs ground truth, posed needs reference cameras
    assert "real/posedscene: initialiser 'oracle' is not run" in out
    assert "real/photos: initialiser 'posed' is not run" in out
    assert "rule oracle_init" not in out and "rule posed_init" in out

    proc = _snakemake(tmp_path, cfg, "--cores", "2", "bridges", "poses",
                      "results/initialisers.json")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]
    run = tmp_path / "results" / "real" / "posedscene" / "n3" / "posed"
    status = json.loads((run / "status.json").read_text())
    assert status["success_paper"] and status["registered"] == 3 and status["points"] > 0
    pose = json.loads((run / "pose.json").read_text())
    assert pose["success_paper"] and pose["success_gated"] and pose["ate_rel_radius"] < 1e-6
    assert (run / "uniform" / "bridge" / "seed.ply").is_file()
    assert not (tmp_path / "results" / "real" / "photos" / "n3" / "posed").exists()
    notes = json.loads((tmp_path / "results" / "initialisers.json").read_text())["skipped"]
    assert {(s["scene"], s["init"]) for s in notes} == {("posedscene", "oracle"), ("photos", "posed"),
                                                       ("photos", "oracle")}
