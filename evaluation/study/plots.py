"""The study's plots (PNG): per axis, the measures against the level; per point cell, the held-out
measures against training wall time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from evaluation.reports.plots import pyplot, save_png
from evaluation.study.collect import CURVE_MEASURES, MEASURES, MODES, collect_curves, point_cells
from evaluation.study.stats import mean_curves

__all__ = ["study_plots"]


def study_plots(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, out: Path,
                curves: pd.DataFrame | None = None) -> list[Path]:
    """Per (dataset, scene, n): for each axis, PSNR and floater fraction (SSIM where no run has
    a floater measure) against the level
    (mean and 95 % interval, one line per mode, the base cell at the axis's reference level);
    and each held-out measure along the run (PSNR, SSIM, LPIPS where logged) against training
    wall time for the zero cell and the named points."""
    curves = collect_curves(runs) if curves is None else curves
    plt = pyplot()
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    axes = {}
    for name, info in cells.items():
        if info.get("axis"):
            axes.setdefault((info["axis"], info["base"]), []).append(name)
    modes = [m for m in MODES if m in set(summary["bridge_mode"])]
    for (ds, sc, n), g in summary.groupby(["dataset", "scene", "n"], sort=True):
        # the floater fraction needs a ground-truth mesh; without one (posed cells) plot SSIM
        panels = ("psnr", "floater_final" if np.isfinite(g["floater_final_mean"].astype(float)).any() else "ssim")
        for (param, base), names in axes.items():
            fig, axs = plt.subplots(1, 2, figsize=(10, 3.6))
            base_level = cells[base]["noise"][param]
            levels = [base_level] + [cells[c]["level"] for c in names]
            numeric = all(isinstance(v, (int, float)) for v in levels)
            xs = levels if numeric else list(range(len(levels)))
            for mode in modes:
                gm = g[g["bridge_mode"] == mode].set_index("cell")
                for ax, m in zip(axs, panels):
                    ys = [gm.loc[c, f"{m}_mean"] if c in gm.index else np.nan for c in [base] + names]
                    es = [gm.loc[c, f"{m}_hw"] if c in gm.index else np.nan for c in [base] + names]
                    ax.errorbar(xs, ys, yerr=np.nan_to_num(es), marker="o", capsize=3, label=mode)
            for ax, m in zip(axs, panels):
                ax.set_xlabel(param + ("" if base == "zero" else f" (on {base})"))
                ax.set_ylabel(MEASURES[m][0] + (f" [{MEASURES[m][1]}]" if MEASURES[m][1] else ""))
                if not numeric:
                    ax.set_xticks(xs, [str(v) for v in levels])
                ax.grid(alpha=0.3)
            axs[0].legend()
            fig.suptitle(f"{ds}/{sc}, n = {n}: {param} (mean, 95 % interval over seeds)")
            fig.tight_layout()
            paths.append(save_png(fig, out / f"{ds}__{sc}__n{n}__axis_{param}__{base}.png", dpi=90))
        # error against time: zero cell and the named operating points, one plot per measure
        sub = curves[(curves["dataset"] == ds) & (curves["scene"] == sc) & (curves["n"] == n)
                     & curves["cell"].isin(point_cells(cells, g))]
        for col, (label, unit, _, _) in CURVE_MEASURES.items():
            if sub.empty or sub[col].isna().all():
                continue
            fig, ax = plt.subplots(figsize=(6, 4))
            for (cell, mode), gm in mean_curves(sub, col).groupby(["cell", "bridge_mode"], sort=True):
                ax.plot(gm["wall_time_s"], gm[col], marker=".", label=f"{cell} / {mode}")
            ax.set_xlabel("training wall time [s] (mean over seeds)")
            ax.set_ylabel(f"{label}" + (f" [{unit}]" if unit else "") + " (mean over seeds)")
            ax.set_title(f"{ds}/{sc}, n = {n}: error against time")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            fig.tight_layout()
            paths.append(save_png(fig, out / f"{ds}__{sc}__n{n}__{col.removeprefix('test_')}_vs_time.png", dpi=90))
    return paths
