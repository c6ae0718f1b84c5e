"""What ran: one row per initialiser and (dataset, scene, n) saying ran / skipped / failed, and why.

Three sources, so that an initialiser that left no result is still named:

* the runs the tables read (:func:`evaluation.reports.results.collect_runs`): "ran" (success under the
  paper criterion) or "ran, no model" with the initialiser's own reason (COLMAP's status.json);
  "ran, random-point fallback" when the run trained from random points for its cameras because
  the initialiser left too few (status.json ``fallback``), with that reason;
* run folders with logs but no result file (the job stopped): "failed" with the last ERROR
  line of its log;
* ``{results}/skipped.json``, written by the workflow (rule unavailable_initialisers) for the
  initialisers that cannot run here, e.g. VGGT without its checkpoint offline:
  ``{initialiser: "reason", ...}`` ({} when all can run); "skipped" with that reason, for every
  (dataset, scene, n) the other initialisers ran on.

The words are the same in Markdown and HTML (they are plain strings).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import pandas as pd

__all__ = ["SKIPPED_FILE", "read_skipped", "write_skipped", "failed_runs", "run_status_table"]

log = logging.getLogger(__name__)

SKIPPED_FILE = "skipped.json"
_N_DIR = re.compile(r"^n(\d+)$")


def read_skipped(results: str | Path) -> dict[str, str]:
    """``{initialiser: reason}`` from ``results/skipped.json`` ({} when absent or unreadable)."""
    p = Path(results) / SKIPPED_FILE
    if not p.is_file():
        return {}
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        log.warning("cannot read %s (%s); treating nothing as skipped", p, exc)
        return {}
    return {str(k): str(v) for k, v in data.items()} if isinstance(data, dict) else {}


def write_skipped(results: str | Path, skipped: dict[str, str]) -> Path:
    """Write (or, for an empty dict, remove) ``results/skipped.json``."""
    from runtime.atomic import write_json

    p = Path(results) / SKIPPED_FILE
    if not skipped:
        p.unlink(missing_ok=True)
        return p
    p.parent.mkdir(parents=True, exist_ok=True)
    write_json(p, dict(skipped))
    return p


def _last_error(log_dir: Path) -> str:
    lines: list[str] = []
    for f in sorted(log_dir.glob("*.log")):
        try:
            lines += [ln.strip() for ln in f.read_text(errors="replace").splitlines() if "ERROR" in ln]
        except OSError:
            continue
    if not lines:
        return "the job left no result files; see its logs/"
    return re.sub(r"^\d\d:\d\d:\d\d ERROR \S+: ", "", lines[-1])[:300]


def failed_runs(results: str | Path) -> list[dict]:
    """Run folders ``{dataset}/{scene}/n{n}/{init}`` with logs but no result files."""
    from evaluation.reports.results import _RUN_FILES, find_file

    out = []
    for p in sorted(Path(results).glob("*/*/n*/*")):
        m = _N_DIR.match(p.parent.name)
        if not (p.is_dir() and m) or p.parts[-4] == "benchmarks" or not (p / "logs").is_dir():
            continue
        if any(find_file(p, name) for name in _RUN_FILES):
            continue
        out.append({"dataset": p.parts[-4], "scene": p.parts[-3], "n": int(m.group(1)), "init": p.name,
                    "status": "failed", "why": _last_error(p / "logs")})
    return out


def run_status_table(runs: pd.DataFrame, results: str | Path | None) -> pd.DataFrame:
    """Columns dataset, scene, n, init, status (ran / ran, random-point fallback / ran, no model /
    failed / skipped), why."""
    rows: dict[tuple, dict] = {}
    for key, g in runs.groupby(["dataset", "scene", "n", "init"], sort=True):
        ok = bool(g["success_paper"].astype(bool).any())
        reasons = [r for r in g.get("reason", pd.Series(dtype=object)) if isinstance(r, str) and r]
        fallback = [r for r in g.get("seed_fallback", pd.Series(dtype=object)) if isinstance(r, str) and r]
        why = "" if ok else (reasons[0] if reasons else "no successful model")
        rows[key] = {"dataset": key[0], "scene": key[1], "n": int(key[2]), "init": key[3],
                     "status": "ran, random-point fallback" if fallback else "ran" if ok else "ran, no model",
                     "why": "; ".join(w for w in (why, fallback[0] if fallback else "") if w)}
    if results is not None and Path(results).is_dir():
        for r in failed_runs(results):
            rows.setdefault((r["dataset"], r["scene"], r["n"], r["init"]), r)
        skipped = read_skipped(results)
        triples = sorted({k[:3] for k in rows})
        for init, why in skipped.items():
            for t in triples:
                rows.setdefault((*t, init), {"dataset": t[0], "scene": t[1], "n": int(t[2]), "init": init,
                                             "status": "skipped", "why": why})
    cols = ["dataset", "scene", "n", "init", "status", "why"]
    if not rows:
        return pd.DataFrame(columns=cols)
    return pd.DataFrame([rows[k] for k in sorted(rows)], columns=cols)
