"""The study's tables, as {title: (header, rows)} of strings: the reference initialisers, one
table per measure (a row per cell, a column per Bridge mode), the paired mode differences and
the held-out measures along the run. Every entry is mean ± 95 % half-width over seeds
(:mod:`evaluation.study.stats`)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from evaluation.reports.markup import format_value
from evaluation.study.collect import (CURVE_MEASURES, DIFF_MEASURES, MEASURES, MODES, POSE_MEASURES, collect_curves,
                                      point_cells)
from evaluation.study.stats import mean_curves, paired_differences

__all__ = ["reference_tables", "cell_order", "cell_label", "measure_tables", "difference_tables", "along_run_tables",
           "all_tables"]

_REF_COLUMNS = [("ate_pct_radius", "ATE [% radius]", 2), ("rel_rot_err_mean_deg", "rel. rot. err. [deg]", 2),
                ("psnr", "PSNR (final) [dB]", 2), ("best_test_psnr", "PSNR (best it.) [dB]", 2),
                ("ssim", "SSIM (final)", 3), ("best_test_ssim", "SSIM (best it.: highest)", 3),
                ("lpips", "LPIPS (final)", 3), ("best_test_lpips", "LPIPS (best it.: lowest)", 3),
                ("num_gaussians", "Gaussians (final)", 0)]


def reference_tables(refs: pd.DataFrame) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: per (dataset, scene, n), a row per reference initialiser
    (one run, no interval), its success first."""
    out = {}
    if refs is None or refs.empty:
        return out
    for (ds, sc, n), g in refs.groupby(["dataset", "scene", "n"], sort=True):
        rows = []
        for r in g.to_dict("records"):
            reg = "?" if not np.isfinite(float(r.get("registered", math.nan))) else str(int(r["registered"]))
            ok = bool(r.get("success_paper"))
            status = f"yes ({reg}/{int(n)} registered)" if ok else f"no: {r.get('reason') or 'failed'} ({reg}/{int(n)})"
            mode = r.get("bridge_mode")
            rows.append([str(r["init"]), mode if isinstance(mode, str) else "-", status]
                        + [format_value(r.get(c), d) for c, _, d in _REF_COLUMNS])
        out[f"{ds}/{sc}, n = {n}: reference initialisers (one regular run each, no seeds)"] = (
            ["init", "Bridge mode", "success"] + [label for _, label, _ in _REF_COLUMNS], rows)
    return out


def cell_order(df: pd.DataFrame, cells: dict | None) -> list[str]:
    """The cells in ``df``: in the grid's order (``cells``), then any others sorted."""
    present = list(dict.fromkeys(df["cell"]))
    if not cells:
        return sorted(present)
    return [c for c in cells if c in present] + sorted(set(present) - set(cells))


def _fmt(mean: float, hw: float, digits: int) -> str:
    if mean is None or not np.isfinite(mean):
        return "-"
    if hw is None or not np.isfinite(hw):
        return f"{mean:.{digits}f} (no interval: 1 seed)"
    return f"{mean:.{digits}f} ± {hw:.{digits}f}"


def cell_label(cell: str, cells: dict) -> str:
    """A cell's row label: ``name (on base)`` for an axis cell on a base other than zero."""
    info = cells.get(cell) or {}
    base = info.get("base")
    if info.get("axis") and base and base != "zero":
        return f"{cell} (on {base})"
    return cell


def measure_tables(summary: pd.DataFrame, order: list[str], cells: dict) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: one table per (dataset, scene, n) and measure, a row per cell,
    a column per mode, each entry mean ± 95 % half-width."""
    out = {}
    modes = [m for m in MODES if m in set(summary["bridge_mode"])]
    for (ds, sc, n), g in summary.groupby(["dataset", "scene", "n"], sort=True):
        for m, (label, unit, digits) in {**MEASURES, **POSE_MEASURES}.items():
            if f"{m}_mean" not in g or not np.isfinite(g[f"{m}_mean"].astype(float)).any():
                continue  # not measured in these runs (e.g. LPIPS along the run was off)
            if m in POSE_MEASURES:  # a property of the oracle output: the same for every mode
                g1 = g.drop_duplicates("cell")
                rows = [[cell_label(c, cells), _fmt(*g1[g1["cell"] == c][[f"{m}_mean", f"{m}_hw"]].iloc[0], digits)]
                        for c in order if (g1["cell"] == c).any()]
                header = ["cell", f"{label} [{unit}]"]
            else:
                rows = []
                for c in order:
                    gc = g[g["cell"] == c].set_index("bridge_mode")
                    if gc.empty:
                        continue
                    rows.append([cell_label(c, cells)] + [
                        _fmt(gc.loc[md, f"{m}_mean"], gc.loc[md, f"{m}_hw"], digits) if md in gc.index else "-"
                        for md in modes])
                header = ["cell"] + modes
                label = f"{label}" + (f" [{unit}]" if unit else "")
            out[f"{ds}/{sc}, n = {n}: {label}"] = (header, rows)
    return out


def difference_tables(runs: pd.DataFrame, order: list[str], cells: dict) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: gated - uniform and filtered - uniform, paired by seed."""
    out = {}
    for a in (m for m in MODES if m != "uniform"):
        d = paired_differences(runs, a, "uniform")
        if d.empty:
            continue
        for (ds, sc, n), g in d.groupby(["dataset", "scene", "n"], sort=True):
            header = ["cell"] + [f"Δ {MEASURES[m][0]}" for m in DIFF_MEASURES]
            rows = []
            for c in order:
                r = g[g["cell"] == c]
                if r.empty:
                    continue
                r = r.iloc[0]
                rows.append([cell_label(c, cells)] + [_fmt(r[f"{m}_mean"], r[f"{m}_hw"], MEASURES[m][2])
                                                       for m in DIFF_MEASURES])
            out[f"{ds}/{sc}, n = {n}: {a} − uniform (paired by seed)"] = (header, rows)
    return out


def along_run_tables(curves: pd.DataFrame, order: list[str], cells: dict) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: per (dataset, scene, n) and held-out measure, a row per
    (point cell, mode) and a column per evaluation iteration (mean ± 95 % half-width over
    seeds), and the mean training time at the last evaluation."""
    out = {}
    if curves.empty:
        return out
    modes = [m for m in MODES if m in set(curves["bridge_mode"])]
    for (ds, sc, n), g in curves.groupby(["dataset", "scene", "n"], sort=True):
        g = g[g["cell"].isin(point_cells(cells, g))]
        its = sorted(int(i) for i in g["iteration"].unique())
        for col, (label, unit, digits, higher) in CURVE_MEASURES.items():
            if g[col].isna().all():
                continue
            mc = mean_curves(g, col)
            rows = []
            for c in order:
                for md in modes:
                    r = mc[(mc["cell"] == c) & (mc["bridge_mode"] == md)].set_index("iteration")
                    if r.empty:
                        continue
                    rows.append([cell_label(c, cells), md]
                                + [_fmt(r.loc[i, col], r.loc[i, f"{col}_hw"], digits) if i in r.index else "-"
                                   for i in its]
                                + [f"{r['wall_time_s'].iloc[-1]:.1f}"])
            unit_s = f" [{unit}]" if unit else ""
            best = "higher" if higher else "lower"
            out[f"{ds}/{sc}, n = {n}: {label}{unit_s} along the run ({best} is better)"] = (
                ["cell", "mode"] + [f"it. {i}" for i in its] + ["training time at the last [s]"], rows)
    return out


def all_tables(runs, summary, cells, curves, refs=None) -> dict[str, tuple[list, list]]:
    """Every table of the study's report by title, in the report's order."""
    order = cell_order(runs, cells)
    return {**reference_tables(refs), **measure_tables(summary, order, cells),
            **difference_tables(runs, order, cells),
            **along_run_tables(collect_curves(runs) if curves is None else curves, order, cells)}
