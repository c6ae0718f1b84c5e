"""Fault: Snakemake never consumes an incomplete output.

A tiny Snakefile stands in for a stage: rule ``produce`` writes its output in two parts with
a pause between them (a job caught half-way), rule ``consume`` copies it. snakemake is killed
during ``produce`` (its whole process group, SIGKILL: no clean-up runs), leaving a file that
exists but is incomplete (and a stale lock, which ``--unlock`` clears). A plain rerun must
refuse (IncompleteFilesException) without running ``consume``; ``--rerun-incomplete`` must
regenerate the file before ``consume`` reads it.
A SIGTERM to the group (a scheduler cancelling the job) must make snakemake delete the partial file.
The real workflow must not opt out of this (no ``ignore-incomplete`` in its profiles).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]

SNAKEFILE = """
rule all:
    input: "consumed.txt"

rule produce:
    output: "produced.txt"
    shell: "echo first-half > {output}; sleep ${{PAUSE:-60}}; echo second-half >> {output}"

rule consume:
    input: "produced.txt"
    output: "consumed.txt"
    shell: "cp {input} {output}"
"""


def _snakemake(workdir: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", "all", "--snakefile", str(workdir / "Snakefile"),
            "--directory", str(workdir), "--cores", "1", *extra]


def _env(pause: str) -> dict:
    return {**os.environ, "PAUSE": pause}


def _start_and_kill_during_produce(workdir: Path, sig: int) -> subprocess.Popen:
    """Start snakemake in its own session; once produced.txt holds its first half, send ``sig``
    to the whole process group (snakemake and its job), as a terminal's Ctrl-C or a batch
    scheduler's cancel does."""
    log = workdir / "snakemake.log"
    with open(log, "w") as f:
        proc = subprocess.Popen(_snakemake(workdir), env=_env("60"), stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True)
    out = workdir / "produced.txt"
    deadline = time.monotonic() + 120
    try:
        while not (out.is_file() and out.read_text().startswith("first-half")):
            assert proc.poll() is None, f"snakemake exited early:\n{log.read_text()}"
            assert time.monotonic() < deadline, "produce never started"
            time.sleep(0.02)
        os.killpg(proc.pid, sig)
        proc.wait(timeout=60)
    finally:
        try:  # nothing of this test may outlive it (the job's `sleep` included)
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
    return proc


@pytest.fixture
def workdir(tmp_path):
    (tmp_path / "Snakefile").write_text(SNAKEFILE)
    return tmp_path


def test_sigkill_leaves_incomplete_output_that_is_never_consumed(workdir):
    _start_and_kill_during_produce(workdir, signal.SIGKILL)
    produced, consumed = workdir / "produced.txt", workdir / "consumed.txt"
    assert produced.read_text() == "first-half\n"  # exists, looks like an output, is half
    assert not consumed.exists()

    # the killed run also left its lock (a plain rerun is refused for that first); free it
    unlock = subprocess.run(_snakemake(workdir, "--unlock"), capture_output=True, text=True, timeout=120)
    assert unlock.returncode == 0, unlock.stdout + unlock.stderr

    plain = subprocess.run(_snakemake(workdir), env=_env("0"), capture_output=True, text=True, timeout=120)
    text = plain.stdout + plain.stderr
    assert plain.returncode != 0, text
    assert "IncompleteFilesException" in text and "produced.txt" in text, text
    assert not consumed.exists(), "snakemake consumed an incomplete output"
    assert produced.read_text() == "first-half\n"

    rerun = subprocess.run(_snakemake(workdir, "--rerun-incomplete"), env=_env("0"), capture_output=True,
                           text=True, timeout=120)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert produced.read_text() == "first-half\nsecond-half\n"  # regenerated, not reused
    assert consumed.read_text() == "first-half\nsecond-half\n"


def test_sigterm_removes_the_partial_output(workdir):
    """snakemake catches SIGTERM, sees its job fail and deletes the job's output."""
    proc = _start_and_kill_during_produce(workdir, signal.SIGTERM)
    assert proc.returncode != 0
    assert not (workdir / "produced.txt").exists(), "partial output left behind after SIGTERM"
    assert not (workdir / "consumed.txt").exists()
    again = subprocess.run(_snakemake(workdir), env=_env("0"), capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr
    assert (workdir / "consumed.txt").read_text() == "first-half\nsecond-half\n"


def test_workflow_profiles_do_not_ignore_incomplete_outputs():
    """``ignore-incomplete`` would let the real workflow consume half-written files."""
    texts = [p.read_text() for p in (ROOT / "workflow").rglob("*") if p.is_file()
             and p.suffix in (".yaml", ".yml", ".smk", "") and p.name != "README"]
    texts.append((ROOT / "Snakefile").read_text())
    for text in texts:
        assert "ignore-incomplete" not in text and "ignore_incomplete" not in text
