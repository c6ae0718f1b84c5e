"""Per-run records -> Parquet -> Markdown tables.

* Table I (per dataset and n): COLMAP success k/N under the paper criterion and under the
  accuracy gate (k/N over scenes with reference cameras), VGGT's success the same way;
  matched COLMAP vs ours PSNR / SSIM / LPIPS over the scenes where COLMAP succeeded (paper
  criterion) and has held-out metrics, their difference (ours - COLMAP), and ours over all scenes,
  under each held-out protocol (header ``[strict]``: the paper's, first; ``[test-pose]``: held-out
  poses optimised with the model frozen, docs/protocols.md; "-" where a run was not scored so);
  beside the PSNRs, the floor's PSNR over the matched scenes and over the scenes of ours (all).
* Table II style summary: per dataset, initialiser and n: success under both criteria,
  registered / n, image metrics over successful runs (metrics.json at the final iteration, and
  the training log's held-out PSNR at the final and at the best evaluated iteration; both
  protocols, and the test-pose protocol's mean rotation change), per protocol the coverage and
  PSNR / SSIM / LPIPS over the covered pixels, ATE and rotation error; and per dataset and n one
  "floor" row: the floor's PSNR / SSIM / LPIPS over the scenes that have one (coverage "-").
* Pose accuracy: one row per run with reference cameras.
* Run time: mean seconds per stage and peak memory, per dataset, initialiser and n.
* COLMAP repeats: the spread over seeds, where runs were repeated.

The floor (``floor.json``, :mod:`evaluation.reports.results`) is a flat image of the training
views' mean colour, scored like a model; covered pixels are the held-out pixels whose accumulated
alpha reaches metrics.json's ``covered_alpha``. :func:`table_legends` says both under the tables.

Means ignore missing values (NaN); a cell with nothing to average is "-".
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd

from runtime.atomic import atomic_path
from evaluation.initialisers import registry
from evaluation.metrics.pose import GateConfig, success_criteria_text
from evaluation.reports.markup import counted, format_value, markdown_table
from evaluation.reports.results import COVERAGE_COLUMNS, FLOOR_COLUMNS, PROTOCOLS, collect_runs

__all__ = ["to_markdown", "table_notes", "table_legends", "FLOOR", "table_one", "table_two", "pose_table",
           "runtime_table", "repeats_table",
           "build_tables", "run_tables", "has_heldout", "HELDOUT_TABLES"]

log = logging.getLogger(__name__)


def to_markdown(df: pd.DataFrame, digits: dict[str, int] | None = None, default_digits: int = 2) -> str:
    """A GitHub-flavoured Markdown table; ``digits`` sets decimals per column."""
    digits = digits or {}
    cols = list(df.columns)
    return markdown_table([str(c) for c in cols],
                          [[format_value(row[c], digits.get(c, default_digits)) for c in cols]
                           for _, row in df.iterrows()])


def _k_of_n(flags: pd.Series) -> str:
    """'k/N' over the non-missing entries ('-' when none)."""
    f = flags.dropna()
    return f"{int(f.astype(bool).sum())}/{len(f)}" if len(f) else "-"


def _mean(s: pd.Series) -> float:
    s = pd.to_numeric(s, errors="coerce").dropna()
    return float(s.mean()) if len(s) else math.nan


def _col(df: pd.DataFrame, name: str) -> pd.Series:
    """Column ``name``, all NaN where the records lack it (runs read before it existed)."""
    return df[name] if name in df else pd.Series(math.nan, index=df.index)


# Every table gives LPIPS with both backbones: the 3DGS-family papers report VGG, the
# NeRF-family papers often AlexNet (docs/protocols.md).
LPIPS_NETS = ("alex", "vgg")


def _metrics(lpips: str | tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """(column, label) of PSNR, SSIM and LPIPS with each backbone of ``lpips`` (VGG first when
    both, as the 3DGS papers' column)."""
    nets = (lpips,) if isinstance(lpips, str) else tuple(lpips)
    nets = tuple(sorted(nets, key=lambda n: n != "vgg"))
    return (("psnr", "PSNR"), ("ssim", "SSIM"), *((f"lpips_{n}", f"LPIPS-{n}") for n in nets))


def _one_mode(rows: pd.DataFrame, mode: str | None) -> pd.DataFrame:
    """One row per scene: the rows of bridge ``mode`` when there are any, else the first mode."""
    if mode is not None and (rows["bridge_mode"] == mode).any():
        rows = rows[rows["bridge_mode"] == mode]
    return rows[~rows["scene"].duplicated()].set_index("scene")


#: The name of the floor's row (Table II) and columns (Table I).
FLOOR = "floor"


def table_one(runs: pd.DataFrame, ours: str | None = None, baseline: str | None = None,
              lpips: str | tuple[str, ...] = LPIPS_NETS, ours_mode: str | None = "gated",
              baseline_mode: str | None = "uniform") -> pd.DataFrame:
    """Table I: per dataset and n (see the module docstring); ``ours`` and ``baseline`` are the
    registry's initialisers of those roles unless given; ``*_mode`` picks the bridge mode (the
    paper's: ours gated, the baseline uniform) when a run has several."""
    ours = ours or registry.with_role("ours")
    baseline = baseline or registry.with_role("baseline")
    rows = []
    for (dataset, n), g in runs.groupby(["dataset", "n"], sort=True):
        base = _one_mode(g[g["init"] == baseline], baseline_mode)
        our = _one_mode(g[g["init"] == ours], ours_mode)
        scenes = sorted(set(base.index) | set(our.index))
        # image metrics are compared where COLMAP succeeded (paper) and could be evaluated
        # (a paper success with < 3 registered views has no held-out renders)
        ok = base["success_paper"].astype(bool) & base["psnr"].notna()
        matched = [s for s in base.index[ok] if s in our.index]
        row = {"dataset": dataset, "n": int(n), "scenes": len(scenes),
               f"{baseline} success (paper)": _k_of_n(base["success_paper"]),
               f"{baseline} success (accurate)": _k_of_n(base.loc[base["has_reference"].astype(bool), "success_gated"]),
               f"{baseline} registered": f"{int(np.nansum(base['registered']))}/{int(base['n_train'].sum())}"
               if len(base) else "-",
               f"{ours} success (paper)": _k_of_n(our["success_paper"]),
               f"{ours} success (accurate)": _k_of_n(our.loc[our["has_reference"].astype(bool), "success_gated"]),
               "matched": len(matched)}
        for protocol, prefix in PROTOCOLS.items():
            for metric, label in _metrics(lpips):
                col, head = prefix + metric, f"{label} [{protocol}]"
                b = _mean(_col(base, col).loc[matched]) if matched else math.nan
                o = _mean(_col(our, col).loc[matched]) if matched else math.nan
                row[f"{head} {baseline} (matched)"] = b
                row[f"{head} {ours} (matched)"] = o
                row[f"{head} delta"] = o - b
                row[f"{head} {ours} (all)"] = _mean(_col(our, col))
                if protocol == "strict" and metric == "psnr":  # the floor: the same under both protocols
                    floor = _col(our, FLOOR_COLUMNS[metric])
                    row[f"{label} {FLOOR} (matched)"] = _mean(floor.loc[matched]) if matched else math.nan
                    row[f"{label} {FLOOR} (all)"] = _mean(floor[_col(our, col).notna()])
        rows.append(row)
    return pd.DataFrame(rows)


def _recipes(g: pd.DataFrame) -> str:
    """The training recipes of a group's runs ("-" where none trained)."""
    names = sorted({str(r) for r in g.get("recipe", pd.Series(dtype=object)).dropna()})
    return ", ".join(names) or "-"


def _in_registry_order(table: pd.DataFrame) -> pd.DataFrame:
    """Rows of a per-initialiser table in the registry's order of their initialisers (within a
    dataset, keeping the order of the rest), each shown by its label
    (evaluation/initialisers/registry.py)."""
    if table.empty:
        return table
    order = table["init"].map(registry.rank)
    table = table.assign(_rank=order).sort_values(["dataset", "_rank"], kind="stable").drop(columns="_rank")
    return table.assign(init=table["init"].map(registry.label)).reset_index(drop=True)


def table_two(runs: pd.DataFrame, lpips: str | tuple[str, ...] = LPIPS_NETS) -> pd.DataFrame:
    """Table II style summary per dataset, initialiser, bridge mode and n."""
    rows = []
    for (dataset, init, mode, n), g in runs.groupby(["dataset", "init", "bridge_mode", "n"], sort=True, dropna=False):
        ok = g[g["success_paper"].astype(bool)]
        rows.append({
            "dataset": dataset, "init": init, "mode": mode, "n": int(n), "runs": len(g),
            "recipe": _recipes(g),
            "success (paper)": _k_of_n(g["success_paper"]),
            "success (accurate)": _k_of_n(g.loc[g["has_reference"].astype(bool), "success_gated"]),
            "registered/n": _mean(g["registered"] / g["n_train"]),
            **_quality(ok, lpips),
            "test-pose rot. change (deg)": _mean(_col(ok, "testpose_rot_deg_mean")),
            "log PSNR final": _mean(ok["final_test_psnr"]),
            "log PSNR best": _mean(ok["best_test_psnr"]),
            "best it.": _mean(ok["best_test_iter"]),
            "ATE % radius": _mean(ok["ate_pct_radius"]), "rel. rot. err (deg)": _mean(ok["rel_rot_err_mean_deg"]),
            "total s": _mean(g["total_s"]),
        })
    return _in_registry_order(pd.DataFrame(rows + _floor_rows(runs, lpips), columns=list(rows[0]) if rows else None))


def _quality(g: pd.DataFrame, lpips) -> dict[str, float]:
    """Table II's image columns of the runs ``g``, per protocol: the full-image measures, the
    coverage and the measures over the covered pixels (means over the runs)."""
    out = {}
    for protocol, prefix in PROTOCOLS.items():
        out.update({f"{label} [{protocol}]": _mean(_col(g, prefix + metric)) for metric, label in _metrics(lpips)})
        out[f"coverage [{protocol}]"] = _mean(_col(g, prefix + COVERAGE_COLUMNS[0]))
        out.update({f"{label} covered [{protocol}]": _mean(_col(g, f"{prefix}covered_{metric}"))
                    for metric, label in _metrics(lpips)})
    return out


def _floor_rows(runs: pd.DataFrame, lpips) -> list[dict]:
    """Table II's floor rows: per dataset and n with a floor, its measures averaged over the
    scenes that have one (the floor does not depend on the pose: the same under each protocol;
    no coverage); the other columns are empty."""
    if not len(runs):
        return []
    cols = [c for c in FLOOR_COLUMNS.values() if c in runs]
    scenes = runs.drop_duplicates(["dataset", "scene", "n"])
    scenes = scenes[scenes[cols].notna().any(axis=1)] if cols else scenes.iloc[:0]
    rows = []
    for (dataset, n), g in scenes.groupby(["dataset", "n"], sort=True):
        row = {"dataset": dataset, "init": FLOOR, "mode": None, "n": int(n), "runs": len(g), "recipe": "-",
               "success (paper)": "-", "success (accurate)": "-"}
        for protocol in PROTOCOLS:
            row.update({f"{label} [{protocol}]": _mean(_col(g, FLOOR_COLUMNS[metric]))
                        for metric, label in _metrics(lpips)})
        rows.append(row)
    return rows


def pose_table(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per run with reference cameras (or a registration count)."""
    g = runs[runs["has_reference"].astype(bool) | runs["registered"].notna()]
    g = g[~g[["dataset", "scene", "n", "init"]].duplicated()].copy()  # poses are shared by bridge modes
    g["registered/n"] = [f"{'-' if math.isnan(r) else int(r)}/{int(n)}" for r, n in zip(g["registered"], g["n_train"])]
    cols = {"dataset": "dataset", "scene": "scene", "n": "n", "init": "init", "registered/n": "registered/n",
            "success_paper": "success (paper)", "success_gated": "success (accurate)",
            "ate_rmse": "ATE", "ate_pct_radius": "ATE % radius", "rpe_rot_deg": "RPE rot (deg)",
            "rpe_trans_dir_deg": "RPE trans dir (deg)", "rel_rot_err_max_deg": "max rel. rot (deg)",
            "fy_fx_max_dev": "max abs(fy/fx - 1)"}
    return g[list(cols)].rename(columns=cols).sort_values(["dataset", "scene", "n", "init"]).reset_index(drop=True)


def runtime_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Mean stage times (s) and peak memory (MB) per dataset, initialiser, bridge mode and n."""
    rows = []
    for (dataset, init, mode, n), g in runs.groupby(["dataset", "init", "bridge_mode", "n"], sort=True,
                                                     dropna=False):
        rows.append({"dataset": dataset, "init": init, "mode": mode, "n": int(n), "runs": len(g),
                     "recipe": _recipes(g), "init s": _mean(g["init_s"]), "bridge s": _mean(g["bridge_s"]),
                     "train s": _mean(g["train_s"]), "eval s": _mean(g["eval_s"]),
                     "total s": _mean(g["total_s"]), "peak MB": float(g["peak_mem_mb"].max()),
                     "peak GPU MB": float(g["peak_gpu_mb"].max())})
    return _in_registry_order(pd.DataFrame(rows))


def repeats_table(runs: pd.DataFrame) -> pd.DataFrame:
    """The spread over repeated (seeded) runs, where any."""
    g = runs[runs["repeats"].fillna(0) > 1]
    g = g[~g[["dataset", "scene", "n", "init"]].duplicated()]
    cols = {"dataset": "dataset", "scene": "scene", "n": "n", "init": "init", "repeats": "runs",
            "repeats_success_rate": "success rate (paper)", "repeats_registered_min": "registered min",
            "repeats_registered_max": "registered max"}
    return g[list(cols)].rename(columns=cols).reset_index(drop=True)


_DIGITS = {"best it.": 0, "SSIM": 3, "ATE": 4, "registered/n": 2, "max abs(fy/fx - 1)": 4, "runs": 0,
           "registered min": 0, "registered max": 0}


TABLE_ONE = "Table I: COLMAP vs VGGT per dataset and n"
RUN_STATUS = "Run status: what ran, per initialiser and scene"
TABLE_TWO = "Table II: summary per initialiser"
POSE_TABLE = "Pose accuracy"
#: the tables of held-out image metrics and pose accuracy: left out of a report with no held-out view
HELDOUT_TABLES = (TABLE_ONE, TABLE_TWO, POSE_TABLE)


def has_heldout(runs: pd.DataFrame, photo_scenes: set[tuple[str, str]]) -> bool:
    """Whether any run of ``runs`` is on a scene with held-out views (``photo_scenes``: the
    (dataset, scene) pairs with none, :func:`evaluation.reports.photos.photo_scenes`); with no
    run at all, the held-out tables are kept (each then says it is empty)."""
    return not len(runs) or any((ds, sc) not in photo_scenes for ds, sc in zip(runs["dataset"], runs["scene"]))


def build_tables(runs: pd.DataFrame, gate: GateConfig = GateConfig(), lpips: str | tuple[str, ...] = LPIPS_NETS,
                 results: str | Path | None = None) -> dict[str, pd.DataFrame]:
    """All tables by title (ordered); the run status reads ``results`` for skipped and failed
    initialisers that left no result (see :mod:`evaluation.reports.run_status`)."""
    from evaluation.reports.run_status import run_status_table

    return {
        RUN_STATUS: run_status_table(runs, results),
        TABLE_ONE: table_one(runs, lpips=lpips),
        TABLE_TWO: table_two(runs, lpips=lpips),
        POSE_TABLE: pose_table(runs),
        "Run time": runtime_table(runs),
        "COLMAP repeats": repeats_table(runs),
    }


def table_notes(tables: dict[str, pd.DataFrame], ours: str | None = None,
                baseline: str | None = None) -> dict[str, str]:
    """Why a table is empty or partly empty, by title (shown instead of, or above, the table);
    ``ours`` and ``baseline``: Table I's (the registry's roles) unless given."""
    ours = ours or registry.with_role("ours")
    baseline = baseline or registry.with_role("baseline")
    notes: dict[str, str] = {}
    status = tables.get(RUN_STATUS)
    inits_ran = set()
    if status is not None and not status.empty:
        inits_ran = set(status.loc[status["status"].str.startswith("ran"), "init"])
    missing = [i for i in (baseline, ours) if i not in inits_ran]
    if TABLE_ONE in tables and missing:
        whys = []
        if status is not None and not status.empty:
            for i in missing:
                w = status.loc[status["init"] == i, "status"]
                whys.append(f"{i}: {w.iloc[0]}, see the run status for why" if len(w) else f"{i}: not configured")
        notes[TABLE_ONE] = (f"Not shown: Table I compares {ours} with {baseline}, and "
                            + " and ".join(missing) + " did not run (" + "; ".join(whys) + ").")
    return notes


def _thresholds(runs: pd.DataFrame) -> str:
    """The covered-alpha thresholds the runs' metrics.json record ("-" where none does)."""
    values = sorted(set(pd.to_numeric(_col(runs, "covered_alpha"), errors="coerce").dropna()))
    return " / ".join(f"{v:g}" for v in values) or "-"


def table_legends(runs: pd.DataFrame) -> dict[str, str]:
    """What the floor and the covered columns are, by title (shown under Table I and Table II)."""
    floor = (f"The {FLOOR} is a flat image of the training views' mean colour, scored like a model (floor.json): a "
             "model that learnt only that colour scores it, so a figure means something only above it")
    if _col(runs, FLOOR_COLUMNS["psnr"]).isna().all():
        floor += "; no scene here has one (python -m evaluation floor writes it)"
    covered = (f"Covered pixels are the held-out pixels whose accumulated alpha is at least {_thresholds(runs)} "
               "(metrics.json's covered_alpha): coverage is their share, and the columns marked covered score those "
               "pixels alone (elsewhere a render shows only the background colour); \"-\" where a run was scored "
               "without its alpha.")
    return {TABLE_ONE: f"{floor}; its (matched) and (all) columns average it over the scenes of the PSNR columns "
                       "beside them that have one.",
            TABLE_TWO: f"{floor}; its row averages it over the scenes that have one ({FLOOR} row, runs: scenes). "
                       + covered}


def protocol_note(runs: pd.DataFrame) -> str | None:
    """One sentence on the test-pose protocol's settings over the runs it scored (steps and
    patience as their testpose.json records them); None when no run has it."""
    if "testpose_steps" not in runs or runs["testpose_steps"].isna().all():
        return None
    tp = runs[runs["testpose_steps"].notna()]
    pairs = sorted({(int(s), int(p) if pd.notna(p) else 0) for s, p in zip(tp["testpose_steps"], tp["testpose_patience"])})
    words = "; ".join(f"at most {s} Adam steps per held-out view" + (f", a view ending after {p} steps without a "
                                                                        "lower loss" if p else "")
                      for s, p in pairs)
    same = "" if len(pairs) == 1 else " (the runs differ: compare like with like)"
    return (f"Held-out protocols: [strict] renders each test view at its reference pose mapped by the Sim(3) "
            f"fitted on the training cameras (the paper's); [test-pose] first optimises that pose alone "
            f"against the test image with the model frozen: {words}, in {counted(len(tp), 'run')}{same} "
            "(docs/protocols.md).")


def tables_markdown(tables: dict[str, pd.DataFrame], gate: GateConfig = GateConfig(), note: str | None = None,
                    legends: dict[str, str] | None = None) -> str:
    """The Markdown document: criteria (and ``note``, e.g. :func:`protocol_note`), then every
    non-empty table, each with its legend below it (``legends``, :func:`table_legends`); empty
    ones are named once at the end; a table that cannot be filled says why instead."""
    out = ["# Results", "",
           *success_criteria_text(gate),
           "Matched: scenes where COLMAP succeeded (paper criterion) and has held-out metrics at that n; "
           "delta = ours - COLMAP.", *([note] if note else []), ""]
    notes = table_notes(tables)
    empty = []
    for title, df in tables.items():
        if title in notes:
            out += [f"## {title}", "", notes[title], ""]
            continue
        if df.empty:
            empty.append(title)
            continue
        out += [f"## {title}", ""]
        digits = {c: (3 if "SSIM" in c or "LPIPS" in c or "coverage" in c else 2) for c in df.columns}
        digits.update({k: v for k, v in _DIGITS.items() if k in df.columns})
        out += [to_markdown(df, digits), ""]
        if (legends or {}).get(title):
            out += [legends[title], ""]
    if empty:
        out += ["Nothing to show (no runs of that kind): " + "; ".join(empty) + ".", ""]
    return "\n".join(out)


def run_tables(results: str | Path, out: str | Path, gate: GateConfig = GateConfig(),
               lpips: str | tuple[str, ...] = LPIPS_NETS) -> dict[str, pd.DataFrame]:
    """Collect the results tree, write ``out/runs.parquet`` and ``out/tables.md`` (with no
    held-out view anywhere, your own photos, the held-out tables are left out with one line
    saying why, as in the report)."""
    from evaluation.reports.photos import NO_HELDOUT_NOTE, photo_scenes

    t0 = time.perf_counter()
    out = Path(out)
    runs = collect_runs(results, gate)
    with atomic_path(out / "runs.parquet") as tmp:
        runs.to_parquet(tmp, index=False)
    tables = build_tables(runs, gate, lpips, results)
    heldout = has_heldout(runs, photo_scenes(results, runs))
    if not heldout:
        tables = {t: df for t, df in tables.items() if t not in HELDOUT_TABLES}
    with atomic_path(out / "tables.md") as tmp:
        tmp.write_text(tables_markdown(tables, gate, protocol_note(runs) if heldout else NO_HELDOUT_NOTE,
                                       table_legends(runs)) + "\n")
    log.info("tables: %s -> %s and %s in %.2f s", counted(len(runs), "run"), out / "runs.parquet", out / "tables.md",
             time.perf_counter() - t0)
    return tables
