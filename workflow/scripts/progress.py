"""Snakemake's progress lines, said so that they never seem to go backwards.

    python -m snakemake ... 2>&1 | python workflow/scripts/progress.py [--prefix "[demo]"]

Snakemake counts the jobs it knows of: after a checkpoint (colmap_index: the jobs after COLMAP
are planned once every COLMAP run has finished) the total grows, and "27 of 31 steps (87%)"
is followed by "28 of 47 steps (60%)". Every line passes through unchanged; before the first
progress line with a larger total comes one line that counts the new jobs into the total.
"""

from __future__ import annotations

import argparse
import re
import sys
from typing import Iterable, Iterator

_PROGRESS = re.compile(r"(\d+) of (\d+) steps \((\d+)%\) done")


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="workflow/scripts/progress.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--prefix", default="", help="put before the added lines, e.g. [demo]")
    args = p.parse_args(argv)
    for line in annotate(sys.stdin, args.prefix):
        sys.stdout.write(line)
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
