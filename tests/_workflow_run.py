"""The one end-to-end Snakemake run of a pytest run, shared by the tests that read its outputs
(through the session fixture ``workflow_run`` of tests/conftest.py).

The config is the CI config (.test/config.yaml: a 16-view, 128-px synthetic scene, the tiny VGGT
fixture model, 30 iterations) with a second dataset for the initialisers that need reference
cameras, so that each test's runs are made once and nothing more is run than the tests read:

* ``ci/tiny`` (synthetic): vggt, colmap and oracle at n = 3 and 6 (tests/test_workflow_run.py);
* ``real/posedscene`` (a converted posed scene: images and reference cameras, no ground-truth
  depth): posed, random and oracle at n = 3, where the oracle cannot run
  (tests/test_workflow_posed.py, tests/test_workflow_random.py);
* ``real/photos`` (a bare photo folder): posed and oracle, neither of which can run there.

Its default target runs everything: initialisers, Bridges, training, evaluation, tables, the
report. A test that needs a DAG of its own (a kill, a different scene) runs it itself.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / "tests" / "data" / "vggt" / "shared"
SNAKEMAKE_MISSING = shutil.which("snakemake") is None and not (Path(sys.executable).parent / "snakemake").is_file()
#: the random initialiser's settings in the shared run (its tests check them in status.json)
RANDOM = {"points": 2000, "seed": 1}


@dataclass
class WorkflowRun:
    """A finished shared run: its working folder, results tree, config and Snakemake's log."""

    root: Path
    results: Path
    config: dict
    log: str


def snakemake(workdir: Path, config_file: Path, *args: str, timeout: int = 1500) -> subprocess.CompletedProcess:
    """Snakemake on the repository's workflow in ``workdir``, with this interpreter's scripts
    first on PATH (the rules call ``python -m ...``)."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run([sys.executable, "-m", "snakemake", *args, "--snakefile", str(REPO / "Snakefile"),
                           "--directory", str(workdir), "--configfile", str(config_file)],
                          capture_output=True, text=True, timeout=timeout, env=env)


def posed_source(root: Path) -> Path:
    """A posed real-style scene ``root/posed_src``: images/ + sparse/0 (no gt/), from the
    synthetic generator."""
    from camio.synthetic import write_synthetic_scene

    synth = root / "_synth"
    write_synthetic_scene(synth, views=12, width=128, seed=0, n_gt_points=4000, n_ref_points=300)
    src = root / "posed_src"
    shutil.copytree(synth / "images", src / "images")
    shutil.copytree(synth / "sparse", src / "sparse")
    shutil.rmtree(synth)
    return src


def photo_folder(root: Path, posed_src: Path) -> Path:
    """``root/photos``: four of the posed scene's images as a bare folder (no cameras)."""
    photos = root / "photos"
    photos.mkdir()
    for i in range(4):
        shutil.copy(posed_src / "images" / f"{i:04d}.png", photos / f"{i:04d}.png")
    return photos


def shared_config(root: Path) -> dict:
    """The shared run's config; its scene folders are made under ``root``."""
    src = posed_source(root)
    photos = photo_folder(root, src)
    cfg = yaml.safe_load((REPO / ".test" / "config.yaml").read_text())
    cfg["results"] = "results"
    cfg["vggt"]["checkpoint"] = str(FIXTURE / "weights.safetensors")
    cfg["vggt"]["model_config"] = str(FIXTURE / "config.json")
    cfg["random"] = dict(RANDOM)
    cfg["datasets"]["real"] = {"scenes": {
        "posedscene": {"path": str(src), "views": [3], "initialisers": ["posed", "mvs", "random", "oracle"]},
        "photos": {"path": str(photos), "format": "folder", "views": [3], "initialisers": ["posed", "mvs", "oracle"]},
    }}
    return cfg


def run_shared_workflow(root: Path) -> WorkflowRun:
    """Write the shared config into ``root`` and run its whole DAG there (2 cores)."""
    cfg = shared_config(root)
    cfg_file = root / "config.yaml"
    cfg_file.write_text(yaml.safe_dump(cfg))
    proc = snakemake(root, cfg_file, "--cores", "2")
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    return WorkflowRun(root=root, results=root / "results", config=cfg, log=log)
