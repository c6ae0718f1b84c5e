"""The workflow on a machine without the VGGT-1B checkpoint, offline (a fresh clone): the real
`snakemake` on the bundled scene (config.yaml, shrunk by overrides) skips VGGT with one line
at the start, exits 0 and lists VGGT as skipped with the reason in skipped.json, the tables and
the report; `unavailable_initialisers: error` stops it before anything runs (exit 2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
REASON = "HF_HUB_OFFLINE is set"


def _offline_env(tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("VGGT_CHECKPOINT", "HF_HUB_CACHE", "HF_HOME")}
    env.update(HF_HUB_OFFLINE="1", HF_HOME=str(tmp_path / "hf"))
    return env


def _config(tmp_path: Path, **extra) -> Path:
    cfg = yaml.safe_load((REPO / "config.yaml").read_text())
    cfg.update(results="results", views=[3], initialisers=["vggt", "oracle"], **extra)
    cfg["train"] = {"enabled": False}  # initialisers, pose accuracy, tables and report only
    cfg["evaluation"].update(testpose=False, lpips_nets=["alex"])
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _snakemake(tmp_path: Path, config: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["snakemake", "--cores", "2", "--snakefile", str(REPO / "Snakefile"), "--directory",
                           str(tmp_path), "--configfile", str(config), *args],
                          capture_output=True, text=True, timeout=900, env=_offline_env(tmp_path))


@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake is not installed")
def test_missing_checkpoint_is_an_error_when_asked(tmp_path):
    proc = _snakemake(tmp_path, _config(tmp_path, unavailable_initialisers="error"), "-n")
    assert proc.returncode == 2, proc.stdout + proc.stderr
    err = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: VGGT cannot run")]
    assert len(err) == 1 and REASON in err[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake is not installed")
def test_missing_checkpoint_skips_vggt_and_the_run_succeeds(tmp_path):
    proc = _snakemake(tmp_path, _config(tmp_path))
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-6000:]
    said = [ln for ln in out.splitlines() if ln.startswith("VGGT skipped:")]
    assert len(said) == 1 and REASON in said[0], out[-3000:]
    assert out.index("VGGT skipped:") < out.index("rule synth_scene") or "Job stats" not in out

    res = tmp_path / "results"
    skipped = json.loads((res / "skipped.json").read_text())
    assert set(skipped) == {"vggt"} and REASON in skipped["vggt"]
    assert not (res / "synthetic" / "bundled" / "n3" / "vggt").exists()
    assert (res / "synthetic" / "bundled" / "n3" / "oracle" / "pose.json").is_file()
    tables = (res / "tables" / "tables.md").read_text()
    row = [ln for ln in tables.splitlines() if "vggt" in ln and "skipped" in ln]
    assert row and REASON in row[0], tables
    report = (res / "report" / "index.html").read_text()
    assert "skipped" in report and REASON in report

    # a rerun with the checkpoint still missing has nothing to do
    again = _snakemake(tmp_path, _config(tmp_path), "-n")
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr, again.stderr[-3000:]
