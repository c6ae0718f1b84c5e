"""Running a stage command the way a user does, and reading a refusal (for the CLI tests)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    """``python ARGS`` from the repository root with this interpreter, output captured."""
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=ROOT, env=ENV,
                          timeout=timeout)


def refused(proc: subprocess.CompletedProcess, *needles: str) -> str:
    """The one error line of a refused command (exit 2, no traceback); it holds every needle."""
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    errors = [ln for ln in proc.stderr.splitlines() if "ERROR" in ln or "error" in ln]
    assert len(errors) == 1, text[-3000:]
    for n in needles:
        assert n in errors[0], (n, errors[0])
    return errors[0]
