"""Snakemake's progress lines, said so that they never seem to go backwards, briefly, with a heartbeat.

    python -m snakemake ... 2>&1 | python workflow/scripts/progress.py [--prefix "[demo]"] [--brief]
                                       [--heartbeat RESULTS]

Snakemake counts the jobs it knows of: after a checkpoint (colmap_index: the jobs after COLMAP
are planned once every COLMAP run has finished) the total grows, and "27 of 31 steps (87%)"
is followed by "28 of 47 steps (60%)". Every line passes through unchanged; before the first
progress line with a larger total comes one line that counts the new jobs into the total.

``--brief`` (:func:`brief`) leaves out snakemake's job blocks and banner (what each job's
files are; ``-v`` of scripts/photos.py shows them) and keeps the progress lines, each naming the
rule that finished, the workflow's own messages and everything from the first error on.
``--heartbeat RESULTS`` (:class:`Heartbeat`) prints, every :data:`HEARTBEAT_S` seconds (the
environment's ``PROGRESS_HEARTBEAT_S`` where set), the time elapsed and the newest line of the job
log under RESULTS written last since the run began, e.g. the trainer's "it 400/1000 ...": a long COLMAP or training
step shows it is alive. scripts/demo.sh and scripts/photos.py use both.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Iterator

_PROGRESS = re.compile(r"(\d+) of (\d+) steps \((\d+)%\) done")
_FINISHED = re.compile(r"^Finished jobid: \d+ \(Rule: ([^)]+)\)")
#: snakemake's own lines that --brief leaves out (its job blocks are indented, or start so)
_CHATTER = re.compile(r"^(\s|\[(Mon|Tue|Wed|Thu|Fri|Sat|Sun) |(local)?(rule|checkpoint) \S+:$|Finished jobid|"
                      r"Select jobs to execute|Execute \d+ jobs|Assuming unrestricted|SNAKEMAKE$|=+$|Building DAG|"
                      r"Using shell|Provided cores|Rules claiming|Conda environments|DAG of jobs will be updated|"
                      r"Updating checkpoint dependencies|Complete log|Job stats:|Will exit after finishing currently running jobs|job +count|-+ +-+$|\S+ +\d+$|$)")
_ERROR = re.compile(r"^(Error in rule|RuleException|WorkflowError|Traceback|Exiting because|MissingInputException|"
                    r"IncompleteFilesException|LockException)")
#: snakemake's line once it acts on a SIGINT ("Terminating processes on user request", in its
#: scheduler, or "Cancelling snakemake on user request." before or after it)
_STOP_SEEN = re.compile(r"on user request")
#: seconds between two heartbeat lines
HEARTBEAT_S = 30.0


def acts_on_stop(line: str) -> bool:
    """Whether snakemake's output ``line`` says it is stopping on a SIGINT."""
    return bool(_STOP_SEEN.search(line))


def annotate(lines: Iterable[str], prefix: str = "") -> Iterator[str]:
    """``lines`` (each ending in a newline), with a line before each growth of the total."""
    total = None
    for line in lines:
        m = _PROGRESS.search(line)
        if m:
            done, new_total = int(m.group(1)), int(m.group(2))
            if total is not None and new_total > total:
                yield (f"{prefix}{' ' if prefix else ''}{new_total - total} new job(s) planned now that the "
                       f"runs they depend on (the COLMAP checkpoint) have finished: {done - 1} of {total} "
                       f"done so far, {new_total} steps in all now\n")
            total = new_total
        yield line


def brief(lines: Iterable[str]) -> Iterator[str]:
    """``lines`` without snakemake's job blocks and banner: the progress lines (each followed by
    the rule that finished), the workflow's own messages, and every line from the first error on."""
    rule, failed = None, False
    for line in lines:
        failed = failed or bool(_ERROR.match(line))
        m = _FINISHED.match(line)
        if m:
            rule = m.group(1)
        if failed:
            yield line
        elif _PROGRESS.search(line):
            yield line.rstrip("\n") + (f" ({rule})" if rule else "") + "\n"
            rule = None
        elif not _CHATTER.match(line):
            yield line


def _clock(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600}h{s // 60 % 60:02d}m{s % 60:02d}s" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def newest_log_line(results: Path, since: float) -> tuple[str, str] | None:
    """(log path relative to ``results``, its last line with letters or digits) of the ``*.log``
    under ``results`` written last, if after ``since`` (a time.time()); None otherwise."""
    latest, mtime = None, since
    for path in results.rglob("*.log"):
        try:
            t = path.stat().st_mtime
        except OSError:
            continue
        if t > mtime:
            latest, mtime = path, t
    if latest is None:
        return None
    try:
        with open(latest, "rb") as f:
            f.seek(max(0, latest.stat().st_size - 2000))
            tail = f.read().decode("utf-8", "replace").replace("\r", "\n")
    except OSError:
        return None
    lines = [ln for ln in tail.splitlines() if re.search(r"[0-9A-Za-z]", ln)]
    return str(latest.relative_to(results)), (lines[-1][:140] if lines else "(started)")


class Heartbeat:
    """A thread that calls ``write`` with one line every ``every`` seconds until stopped:
    "<prefix> 2m30s elapsed; newest log photos/x/n6/colmap/logs/colmap.log: <its last line>".

    Use as a context manager around the run it watches."""

    def __init__(self, results: str | Path, write: Callable[[str], None], prefix: str = "",
                 every: float | None = None) -> None:
        self.results, self.write, self.prefix = Path(results), write, f"{prefix} " if prefix else ""
        self.every = float(os.environ.get("PROGRESS_HEARTBEAT_S", HEARTBEAT_S)) if every is None else every
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        t0 = time.time()
        while not self._stop.wait(self.every):
            now = time.time()
            newest = newest_log_line(self.results, t0) if self.results.is_dir() else None
            said = f"; newest log {newest[0]}: {newest[1]}" if newest else ""
            self.write(f"{self.prefix}{_clock(now - t0)} elapsed{said}\n")

    def __enter__(self) -> "Heartbeat":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="workflow/scripts/progress.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--prefix", default="", help="put before the added lines, e.g. [demo]")
    p.add_argument("--brief", action="store_true", help="leave out snakemake's job blocks and banner")
    p.add_argument("--heartbeat", metavar="RESULTS", type=Path,
                   help="every PROGRESS_HEARTBEAT_S seconds (default %g) say the time elapsed and the newest "
                        "job log line under RESULTS" % HEARTBEAT_S)
    args = p.parse_args(argv)
    lock = threading.Lock()

    def write(line: str) -> None:
        with lock:
            sys.stdout.write(line)
            sys.stdout.flush()

    lines = annotate(sys.stdin, args.prefix)
    if args.brief:
        lines = brief(lines)
    if args.heartbeat is None:
        for line in lines:
            write(line)
        return 0
    with Heartbeat(args.heartbeat, write, args.prefix):
        for line in lines:
            write(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
