"""Compare the quality numbers of two results folders (tables/runs.parquet): exit 1 if any
differ. Timing, memory and host columns are left out (they differ between any two runs).

    python scripts/compare_tables.py RESULTS_A RESULTS_B
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pandas as pd

VARYING = re.compile(r"time|wall|_s$|seconds|rss|peak|mem|host|date|path|dir|file|log|version|threads",
                     re.IGNORECASE)


def compare(a: Path, b: Path) -> list[str]:
    ta, tb = (pd.read_parquet(d / "tables" / "runs.parquet") for d in (a, b))
    cols = sorted(c for c in set(ta.columns) & set(tb.columns) if not VARYING.search(c))
    keys = [c for c in ("dataset", "scene", "n", "init", "mode") if c in cols]
    ta, tb = (t[cols].sort_values(keys).reset_index(drop=True) for t in (ta, tb))
    problems = []
    if len(ta) != len(tb):
        problems.append(f"{len(ta)} runs vs {len(tb)}")
        return problems
    for c in cols:
        x, y = ta[c], tb[c]
        same = (x == y) | (x.isna() & y.isna())
        if not same.all():
            problems.append(f"{c}: {list(x[~same])} vs {list(y[~same])}")
    print(f"compared {len(ta)} runs x {len(cols)} columns (timings left out): "
          f"{'identical' if not problems else f'{len(problems)} columns differ'}")
    return problems


if __name__ == "__main__":
    problems = compare(Path(sys.argv[1]), Path(sys.argv[2]))
    for p in problems:
        print("differs:", p)
    sys.exit(1 if problems else 0)
