"""Error against run time (PNG, matplotlib Agg).

* ``curves/{dataset}__{scene}__n{n}.png``: from each run's ``log.parquet`` (iteration,
  wall_time_s, loss, test_psnr, ...), held-out PSNR and training loss against wall time and
  against iteration, one line per initialiser.
* ``pareto__{dataset}__{scene}__n{n}.png``: per scene and view count, final held-out PSNR (metrics.json, else the log's last test_psnr) against
  total run time (initialisation + bridge + training + evaluation) over all runs, with the
  Pareto front (no other run is both faster and better), and the scene's floor (floor.json: a
  flat image of the training views' mean colour, scored like a model) as a dashed line where
  there is one.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd

from runtime.atomic import atomic_path
from evaluation.reports.results import collect_runs, find_file, read_log, run_label

__all__ = ["pyplot", "save_png", "training_curves", "pareto_front", "pareto_plot", "run_plots"]

log = logging.getLogger(__name__)


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fit_layout(fig, top: float = 1.0) -> None:
    """Margins that fit every label: matplotlib's tight layout (tick labels of any width, the
    axis labels beside them), below ``top`` (a fraction of the height, for a suptitle)."""
    fig.tight_layout(rect=(0.0, 0.0, 1.0, top))


def save_png(fig, path: Path, dpi: int = 100) -> Path:
    """Write ``fig`` to the PNG ``path`` (atomically) and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)  # no bbox "tight": 3x slower with log axes
    pyplot().close(fig)
    return path


def training_curves(runs: pd.DataFrame, out: str | Path) -> list[Path]:
    """One 2 x 2 figure per (dataset, scene, n) with a training log; returns the files."""
    plt = pyplot()
    out = Path(out)
    written = []
    for (dataset, scene, n), g in runs.groupby(["dataset", "scene", "n"], sort=True):
        logs = {run_label(row.init, row.bridge_mode): lg for row in g.itertuples()
                if (lg := read_log(find_file(Path(row.run_dir), "log.parquet"))) is not None}
        if not logs:
            continue
        fig, axes = plt.subplots(2, 2, figsize=(10, 7))
        panels = [("test_psnr", "wall_time_s", "held-out PSNR (dB)", "wall time (s)"),
                  ("test_psnr", "iteration", "held-out PSNR (dB)", "iteration"),
                  ("loss", "wall_time_s", "training loss", "wall time (s)"),
                  ("loss", "iteration", "training loss", "iteration")]
        for ax, (ycol, xcol, ylab, xlab) in zip(axes.flat, panels):
            for init, lg in sorted(logs.items()):
                if ycol not in lg or xcol not in lg:
                    continue
                d = lg[[xcol, ycol]].dropna()
                if len(d):
                    ax.plot(d[xcol], d[ycol], marker="o" if ycol == "test_psnr" else None,
                            markersize=3, label=init)
            ax.set_xlabel(xlab)
            ax.set_ylabel(ylab)
            if ycol == "loss":
                ax.set_yscale("log")
            ax.grid(alpha=0.3)
        axes[0, 0].legend()
        fig.suptitle(f"{dataset} / {scene}, n = {n}")
        fit_layout(fig, top=0.95)
        written.append(save_png(fig, out / "curves" / f"{dataset}__{scene}__n{n}.png"))
    return written


def pareto_front(times: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """Indices of the Pareto-optimal points (minimise both time and error), sorted by time.

    Args:
        times: [M] run times; errors: [M] errors (lower is better). NaN entries are ignored.
    """
    t = np.asarray(times, np.float64)
    e = np.asarray(errors, np.float64)
    idx = [i for i in np.lexsort((e, t)) if np.isfinite(t[i]) and np.isfinite(e[i])]
    front, best = [], math.inf
    for i in idx:
        if e[i] < best:
            front.append(i)
            best = e[i]
    return np.asarray(front, dtype=np.int64)


def pareto_plot(runs: pd.DataFrame, out: str | Path) -> list[Path]:
    """``out/pareto__{dataset}__{scene}__n{n}.png``: held-out PSNR against total run time, one
    plot (and one front) per scene and view count, since times and errors of different scenes
    are not comparable. One legend entry per run label, and the floor's PSNR (a dashed line)
    where the scene has one. Empty when no run has both."""
    psnr = runs["psnr"].where(runs["psnr"].notna(), runs["final_test_psnr"])
    d = runs.assign(psnr_final=psnr, label=[run_label(i, m) for i, m in zip(runs["init"], runs["bridge_mode"])])
    floors = d.groupby(["dataset", "scene", "n"])["floor_psnr"].first() if "floor_psnr" in d else None
    d = d[["dataset", "scene", "label", "n", "total_s", "psnr_final"]].dropna()
    if d.empty:
        log.warning("plots: no run has both a run time and a PSNR; no Pareto plot")
        return []
    plt = pyplot()
    colors = {lab: f"C{i}" for i, lab in enumerate(sorted(d["label"].unique()))}
    files = []
    for (dataset, scene, n), g in d.groupby(["dataset", "scene", "n"], sort=True):
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for lab, gl in g.groupby("label", sort=True):
            ax.scatter(gl["total_s"], gl["psnr_final"], c=colors[lab], label=lab, alpha=0.85)
        front = pareto_front(g["total_s"].to_numpy(), -g["psnr_final"].to_numpy())
        if len(front) > 1:
            ax.step(g["total_s"].to_numpy()[front], g["psnr_final"].to_numpy()[front], where="post",
                    color="k", lw=1, label="Pareto front")
        floor = floors.get((dataset, scene, n), math.nan) if floors is not None else math.nan
        if np.isfinite(floor):
            ax.axhline(floor, color="0.5", ls="--", lw=1, label="floor (mean colour)")
        if g["total_s"].max() > 10 * max(g["total_s"].min(), 1e-9):
            ax.set_xscale("log")
        ax.set_title(f"{dataset} / {scene}, n = {int(n)}", fontsize=9)
        ax.set_xlabel("total run time (s): init + bridge + train + eval")
        ax.set_ylabel("held-out PSNR (dB), higher = lower error")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fit_layout(fig)
        files.append(save_png(fig, Path(out) / f"pareto__{dataset}__{scene}__n{int(n)}.png"))
    return files


def run_plots(results: str | Path, out: str | Path, runs: pd.DataFrame | None = None) -> list[Path]:
    """Write every plot of the results tree into ``out``; returns the files."""
    t0 = time.perf_counter()
    Path(out).mkdir(parents=True, exist_ok=True)  # exists even with nothing to plot (a declared output)
    runs = collect_runs(results) if runs is None else runs
    files = training_curves(runs, out)
    files += pareto_plot(runs, out)
    log.info("plots: %d PNG files in %s (%.2f s)", len(files), out, time.perf_counter() - t0)
    return files
