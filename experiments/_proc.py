"""One way for the studies and the benchmarks to run a command: from the repository root, its output in a log file;
a stop signal of the benchmark is passed on to the command, which ends cleanly first
(:func:`runtime.stops.run_child`)."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

from runtime.stops import run_child

ROOT = Path(__file__).resolve().parents[1]


class StageError(RuntimeError):
    """A command returned a non-zero status."""


def run_logged(argv: list[str], log: Path, what: str | None = None) -> float:
    """Run ``argv`` from the repository root (on ``PYTHONPATH``, unbuffered) with stdout and
    stderr in ``log``; wall seconds. A non-zero status raises :class:`StageError` with the end
    of the log. ``what``: how the error names the command (default: its first words)."""
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONUNBUFFERED": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    with open(log, "w") as fh:
        rc = run_child(argv, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    dt = time.perf_counter() - t0
    if rc != 0:
        tail = Path(log).read_text(errors="replace")[-1500:]
        raise StageError(f"{what or ' '.join(argv[1:5])} failed with status {rc} after {dt:.1f} s; "
                         f"end of {log}:\n{tail}")
    return dt


def run_stage(args: list[str], log: Path) -> None:
    """Run the stage command ``python args...`` with this interpreter from the repository root,
    appending the command line and its output to ``log`` (one log for a cell's several
    stages); a non-zero status raises :class:`StageError` naming the log."""
    import sys

    log = Path(log)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(args) + "\n")
        fh.flush()
        rc = run_child([sys.executable, *args], cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
    if rc != 0:
        raise StageError(f"{' '.join(args[:2])} failed (exit {rc}); see {log}")
