"""CI checks of the workflow code: snakefmt formatting and `snakemake --lint`."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("snakefmt") is None, reason="snakefmt is not installed")
def test_snakefmt_check():
    proc = subprocess.run(["snakefmt", "--check", "Snakefile", "workflow"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake is not installed")
def test_snakemake_lint_is_clean(tmp_path):
    proc = subprocess.run(["snakemake", "--lint", "--snakefile", str(REPO / "Snakefile"),
                           "--configfile", str(REPO / "config.yaml"), "--directory", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert "Lints for" not in out, out
