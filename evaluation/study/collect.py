"""The initialisation study's report: per-run records -> per-cell means with 95 % intervals
over seeds, paired mode differences, Markdown tables, plots and an HTML section.

Input: the study tree (workflow/rules/study_plan.smk)
``{root}/{cell}/s{seed}/{dataset}/{scene}/n{n}/{init}/{mode}/`` (``init`` one of
:data:`STUDY_INITS`: the oracle, or the posed initialiser on scenes with reference cameras)
read with :func:`evaluation.reports.results.read_run` (metrics.json, train.json, log.parquet, pose.json
of the initialiser) plus ``floaters.json`` (:mod:`evaluation.metrics.floaters`; only where the scene
has a ground-truth mesh); ``cells`` (the expanded grid,
:func:`evaluation.study.grid.expand_cells`) names each cell's axis, level and base.

Along the run: the trainer's held-out evaluations (``train/log.parquet`` columns ``test_psnr``,
``test_ssim``, ``test_lpips``, docs/contracts.md) give, per run, the best value of each measure
and its iteration (best = highest PSNR, highest SSIM, lowest LPIPS) and the curves against
training wall time (:func:`collect_curves`; tables and plots for the zero cell and the named
points). LPIPS along the run exists only when training ran with ``eval_lpips``; otherwise
those entries are "-".

Reference initialisers (``references``: regular run folders ``R/{dataset}/{scene}/n{n}/{init}``,
e.g. the COLMAP baseline of the same views and training budget): one run each, no seeds, so
no interval; shown as one row per (dataset, scene, n) beside the cells with their success
(registered / training views, and the reason when it failed). COLMAP has no confidence: its one
Bridge mode is ``uniform`` (the workflow's ``init_modes``), so gated and filtered do not apply.
A failed COLMAP (``success_paper`` false, nothing trained) is a row that says so.

Interval (the one definition): for k >= 2 seeds, mean +- t_{0.975, k-1} * sd / sqrt(k), sd the
sample standard deviation (ddof 1); k = 1 gives no interval (NaN half-width). Paired
differences (mode A - mode B) are taken per seed (the modes of a seed share the same oracle
output) and get the same interval.
"""

from __future__ import annotations

import html
import json
import logging
import math
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd

from camio.atomic import atomic_dir, write_json
from evaluation.reports.results import read_run

__all__ = ["MEASURES", "CURVE_MEASURES", "t_interval", "find_study_runs", "collect_study", "collect_curves",
           "best_along_run", "summarise", "paired_differences", "along_run_tables", "study_markdown",
           "study_plots", "collect_references", "reference_tables", "run_study"]

log = logging.getLogger(__name__)

# column -> (label, unit, digits): the measures of docs/init-study.md, in table order
MEASURES = {
    "psnr": ("PSNR (final)", "dB", 2),
    "best_test_psnr": ("PSNR (best it.)", "dB", 2),
    "best_test_iter": ("best iteration", "it.", 0),
    "ssim": ("SSIM (final)", "", 3),
    "best_test_ssim": ("SSIM (best it.: highest)", "", 3),
    "best_ssim_iter": ("best SSIM iteration", "it.", 0),
    "lpips": ("LPIPS (final)", "", 3),
    "best_test_lpips": ("LPIPS (best it.: lowest)", "", 3),
    "best_lpips_iter": ("best LPIPS iteration", "it.", 0),
    "num_gaussians": ("Gaussians (final)", "count", 0),
    "floater_seed": ("floater frac. (seed)", "fraction", 3),
    "floater_final": ("floater frac. (final)", "fraction", 3),
}
POSE_MEASURES = {"ate_pct_radius": ("ATE", "% radius", 2), "rel_rot_err_mean_deg": ("rel. rot. err.", "deg", 2)}
DIFF_MEASURES = ("psnr", "ssim", "lpips", "floater_final")
# log.parquet column -> (label, unit, digits, higher is better): the held-out curves along the run
CURVE_MEASURES = {"test_psnr": ("held-out PSNR", "dB", 2, True), "test_ssim": ("held-out SSIM", "", 3, True),
                  "test_lpips": ("held-out LPIPS-alex", "", 3, False)}
MODES = ("gated", "uniform", "filtered")
STUDY_INITS = ("oracle", "posed")  # what a study cell can degrade (config study.initialiser)
_SEED = re.compile(r"^s(\d+)$")
_N = re.compile(r"^n(\d+)$")


def t_interval(values) -> tuple[float, float, int]:
    """(mean, 95 % half-width, k) over the finite values (see the module docstring)."""
    from scipy.stats import t

    x = np.asarray(values, np.float64)
    x = x[np.isfinite(x)]
    k = len(x)
    if k == 0:
        return math.nan, math.nan, 0
    if k == 1:
        return float(x[0]), math.nan, 1
    half = float(t.ppf(0.975, k - 1) * x.std(ddof=1) / math.sqrt(k))
    return float(x.mean()), half, k


def find_study_runs(root: str | Path) -> list[tuple[str, int, Path, str]]:
    """(cell, seed, initialiser run folder, mode) of every mode folder under ``root``, sorted."""
    root = Path(root)
    out = []
    for run in sorted(r for init in STUDY_INITS for r in root.glob(f"*/s*/*/*/n*/{init}")):
        cell, seed = run.parts[-6], run.parts[-5]
        if not (_SEED.match(seed) and _N.match(run.parent.name)):
            continue
        for m in sorted(p for p in run.iterdir() if p.is_dir() and p.name in MODES):
            out.append((cell, int(_SEED.match(seed).group(1)), run, m.name))
    return out


def _floaters(path: Path) -> dict:
    if not path.is_file():
        return {"floater_seed": math.nan, "floater_final": math.nan, "floater_tau": math.nan}
    d = json.loads(path.read_text())
    get = lambda k: (d.get(k) or {}).get("floater_frac")  # noqa: E731
    return {"floater_seed": float(get("seed") if get("seed") is not None else math.nan),
            "floater_final": float(get("final") if get("final") is not None else math.nan),
            "floater_tau": float(d.get("tau", math.nan))}


def _read_log(run_dir: str | Path) -> pd.DataFrame | None:
    """The evaluation rows of ``run_dir/train/log.parquet`` (columns iteration, wall_time_s and
    the present CURVE_MEASURES), or None when there is no readable log."""
    f = Path(run_dir) / "train" / "log.parquet"
    if not f.is_file():
        return None
    try:
        lg = pd.read_parquet(f)
    except (OSError, ValueError) as exc:
        log.warning("study: cannot read %s (%s)", f, exc)
        return None
    if "test_psnr" not in lg:
        return None
    cols = ["iteration", "wall_time_s"] + [c for c in CURVE_MEASURES if c in lg]
    return lg.loc[lg["test_psnr"].notna(), cols].reset_index(drop=True)


def best_along_run(lg: pd.DataFrame | None) -> dict[str, float]:
    """Best held-out SSIM (highest) and LPIPS (lowest) along the run and their iterations
    (``best_test_ssim``, ``best_ssim_iter``, ``best_test_lpips``, ``best_lpips_iter``); NaN
    where the log lacks the column or every value is null. PSNR's are read_run's."""
    out = {}
    for col, key, higher in (("test_ssim", "ssim", True), ("test_lpips", "lpips", False)):
        v = lg[col].dropna() if lg is not None and col in lg else pd.Series(dtype=float)
        if v.empty:
            out[f"best_test_{key}"], out[f"best_{key}_iter"] = math.nan, math.nan
            continue
        i = v.idxmax() if higher else v.idxmin()
        out[f"best_test_{key}"], out[f"best_{key}_iter"] = float(v[i]), float(lg.loc[i, "iteration"])
    return out


def collect_curves(runs: pd.DataFrame) -> pd.DataFrame:
    """Long table of the held-out evaluations along every run: the run's keys (dataset, scene,
    n, cell, bridge_mode, seed) and iteration, wall_time_s, test_psnr, test_ssim, test_lpips
    (NaN where a log lacks the column)."""
    keys = ["dataset", "scene", "n", "cell", "bridge_mode", "seed"]
    parts = []
    for rec in runs[keys + ["run_dir"]].to_dict("records"):
        lg = _read_log(rec["run_dir"])
        if lg is None or lg.empty:
            continue
        lg = lg.copy()
        for c in CURVE_MEASURES:
            if c not in lg:
                lg[c] = math.nan
        for k in keys:
            lg[k] = rec[k]
        parts.append(lg)
    cols = keys + ["iteration", "wall_time_s", *CURVE_MEASURES]
    return pd.concat(parts, ignore_index=True)[cols] if parts else pd.DataFrame(columns=cols)


def planned_runs(found, cells: dict | None = None, seeds=None, views=None):
    """Split :func:`find_study_runs` output into the runs the grid plans and the rest.

    A study tree can hold runs of an earlier grid (other views, seeds or cells, e.g. an
    interrupted run of another config): a run counts only when its cell is in ``cells`` (when
    given), its seed in ``seeds`` and its view count (the ``n{n}`` folder) in ``views``.
    Returns (kept, left_out), both lists of the same tuples."""
    keep, left = [], []
    for cell, seed, run, mode in found:
        n = int(_N.match(run.parent.name).group(1))
        ok = ((not cells or cell in cells) and (seeds is None or seed in seeds)
              and (views is None or n in views))
        (keep if ok else left).append((cell, seed, run, mode))
    return keep, left


def collect_study(root: str | Path, cells: dict | None = None, seeds=None, views=None) -> pd.DataFrame:
    """One row per (cell, seed, dataset, scene, n, mode) that the grid plans
    (:func:`planned_runs`): read_run's columns, ``lpips`` (alex when present, else vgg;
    ``lpips_net`` says which), the best SSIM / LPIPS along the run (:func:`best_along_run`),
    the floater fractions, the cell's axis / level / base and its oracle noise."""
    cells = cells or {}
    found, left = planned_runs(find_study_runs(root), cells, seeds, views)
    if left:
        log.warning("study: left out %d run folders under %s that the grid does not plan "
                    "(cells %s, seeds %s, views %s), e.g. %s", len(left), root,
                    "as given" if cells else "any", seeds if seeds is not None else "any",
                    views if views is not None else "any", left[0][2] / left[0][3])
    rows = []
    for cell, seed, run, mode in found:
        rec = read_run(run, mode=mode)
        rec.update(cell=cell, seed=seed, **_floaters(run / mode / "floaters.json"))
        rec.update(best_along_run(_read_log(run / mode)))
        net = "alex" if not math.isnan(rec["lpips_alex"]) else "vgg"
        rec["lpips"], rec["lpips_net"] = rec[f"lpips_{net}"], net
        info = cells.get(cell, {})
        rec.update(axis=info.get("axis"), level=info.get("level"), base=info.get("base"))
        status = run / "status.json"
        noise = json.loads(status.read_text()).get("noise", {}) if status.is_file() else {}
        rec.update({f"noise_{k}": v for k, v in noise.items()})
        rows.append(rec)
    df = pd.DataFrame(rows)
    log.info("study: %d runs under %s", len(df), root)
    return df


def collect_references(run_dirs) -> pd.DataFrame:
    """One row per reference run folder ``R/{dataset}/{scene}/n{n}/{init}``: read_run's
    columns of its (first) Bridge-mode folder, or of the run alone when nothing was trained
    (a failed COLMAP), plus ``lpips`` / ``lpips_net`` and :func:`best_along_run`."""
    rows = []
    for d in run_dirs or []:
        run = Path(d)
        if not run.is_dir():
            log.warning("study: reference run %s does not exist; skipped", run)
            continue
        modes = [m for m in MODES if (run / m).is_dir()]
        rec = read_run(run, mode=modes[0] if modes else None)
        rec["bridge_mode"] = modes[0] if modes else None
        net = "alex" if not math.isnan(rec["lpips_alex"]) else "vgg"
        rec["lpips"], rec["lpips_net"] = rec[f"lpips_{net}"], net
        rec.update(best_along_run(_read_log(run / modes[0]) if modes else None))
        rows.append(rec)
    return pd.DataFrame(rows)


_REF_COLUMNS = [("ate_pct_radius", "ATE [% radius]", 2), ("rel_rot_err_mean_deg", "rel. rot. err. [deg]", 2),
                ("psnr", "PSNR (final) [dB]", 2), ("best_test_psnr", "PSNR (best it.) [dB]", 2),
                ("ssim", "SSIM (final)", 3), ("best_test_ssim", "SSIM (best it.: highest)", 3),
                ("lpips", "LPIPS (final)", 3), ("best_test_lpips", "LPIPS (best it.: lowest)", 3),
                ("num_gaussians", "Gaussians (final)", 0)]


def _one(v, digits: int) -> str:
    v = float(v) if v is not None else math.nan
    return f"{v:.{digits}f}" if np.isfinite(v) else "-"


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
                        + [_one(r.get(c), d) for c, _, d in _REF_COLUMNS])
        out[f"{ds}/{sc}, n = {n}: reference initialisers (one regular run each, no seeds)"] = (
            ["init", "Bridge mode", "success"] + [label for _, label, _ in _REF_COLUMNS], rows)
    return out


def _cell_order(df: pd.DataFrame, cells: dict | None) -> list[str]:
    present = list(dict.fromkeys(df["cell"]))
    if not cells:
        return sorted(present)
    return [c for c in cells if c in present] + sorted(set(present) - set(cells))


def summarise(runs: pd.DataFrame, measures=tuple(MEASURES) + tuple(POSE_MEASURES)) -> pd.DataFrame:
    """Mean, 95 % half-width and seed count of each measure per (dataset, scene, n, cell, mode):
    columns ``{m}_mean``, ``{m}_hw``, ``{m}_k``."""
    keys = ["dataset", "scene", "n", "cell", "bridge_mode"]
    rows = []
    for key, g in runs.groupby(keys, sort=False):
        rec = dict(zip(keys, key))
        for m in measures:
            rec[f"{m}_mean"], rec[f"{m}_hw"], rec[f"{m}_k"] = t_interval(g[m]) if m in g else (math.nan,) * 2 + (0,)
        rows.append(rec)
    return pd.DataFrame(rows)


def paired_differences(runs: pd.DataFrame, a: str, b: str, measures=DIFF_MEASURES) -> pd.DataFrame:
    """Per (dataset, scene, n, cell): mean and 95 % interval of (mode a - mode b), paired by seed."""
    keys = ["dataset", "scene", "n", "cell"]
    rows = []
    for key, g in runs.groupby(keys, sort=False):
        pa = g[g["bridge_mode"] == a].set_index("seed")
        pb = g[g["bridge_mode"] == b].set_index("seed")
        common = pa.index.intersection(pb.index)
        if not len(common):
            continue
        rec = dict(zip(keys, key))
        for m in measures:
            rec[f"{m}_mean"], rec[f"{m}_hw"], rec[f"{m}_k"] = t_interval(pa.loc[common, m] - pb.loc[common, m])
        rows.append(rec)
    return pd.DataFrame(rows)


def _fmt(mean: float, hw: float, digits: int) -> str:
    if mean is None or not np.isfinite(mean):
        return "-"
    if hw is None or not np.isfinite(hw):
        return f"{mean:.{digits}f} (no interval: 1 seed)"
    return f"{mean:.{digits}f} ± {hw:.{digits}f}"


def _cell_label(cell: str, cells: dict) -> str:
    info = cells.get(cell) or {}
    base = info.get("base")
    if info.get("axis") and base and base != "zero":
        return f"{cell} (on {base})"
    return cell


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


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
                rows = [[_cell_label(c, cells), _fmt(*g1[g1["cell"] == c][[f"{m}_mean", f"{m}_hw"]].iloc[0], digits)]
                        for c in order if (g1["cell"] == c).any()]
                header = ["cell", f"{label} [{unit}]"]
            else:
                rows = []
                for c in order:
                    gc = g[g["cell"] == c].set_index("bridge_mode")
                    if gc.empty:
                        continue
                    rows.append([_cell_label(c, cells)] + [
                        _fmt(gc.loc[md, f"{m}_mean"], gc.loc[md, f"{m}_hw"], digits) if md in gc.index else "-"
                        for md in modes])
                header = ["cell"] + modes
                label = f"{label}" + (f" [{unit}]" if unit else "")
            out[f"{ds}/{sc}, n = {n}: {label}"] = (header, rows)
    return out


def difference_tables(runs: pd.DataFrame, order: list[str], cells: dict) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: gated - uniform and filtered - uniform, paired by seed."""
    out = {}
    for a in ("gated", "filtered"):
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
                rows.append([_cell_label(c, cells)] + [_fmt(r[f"{m}_mean"], r[f"{m}_hw"], MEASURES[m][2])
                                                       for m in DIFF_MEASURES])
            out[f"{ds}/{sc}, n = {n}: {a} − uniform (paired by seed)"] = (header, rows)
    return out


def _pyplot():
    from evaluation.reports.plots import _pyplot as pp

    return pp()


def _points(cells: dict, g: pd.DataFrame) -> list[str]:
    """The cells of the along-the-run record: the zero cell and the named points (no axis)."""
    return [c for c, info in cells.items() if not info.get("axis")] or sorted(set(g["cell"]))


def _mean_curves(sub: pd.DataFrame, col: str) -> pd.DataFrame:
    """Per (cell, mode, iteration): mean wall time, and mean, 95 % half-width and seed count of
    ``col`` over the seeds (:func:`t_interval`)."""
    rows = []
    for (cell, mode, it), g in sub.groupby(["cell", "bridge_mode", "iteration"], sort=True):
        m, hw, k = t_interval(g[col])
        rows.append({"cell": cell, "bridge_mode": mode, "iteration": int(it),
                     "wall_time_s": float(g["wall_time_s"].mean()), col: m, f"{col}_hw": hw, f"{col}_k": k})
    return pd.DataFrame(rows)


def along_run_tables(curves: pd.DataFrame, order: list[str], cells: dict) -> dict[str, tuple[list, list]]:
    """{title: (header, rows)}: per (dataset, scene, n) and held-out measure, a row per
    (point cell, mode) and a column per evaluation iteration (mean ± 95 % half-width over
    seeds), and the mean training time at the last evaluation."""
    out = {}
    if curves.empty:
        return out
    modes = [m for m in MODES if m in set(curves["bridge_mode"])]
    for (ds, sc, n), g in curves.groupby(["dataset", "scene", "n"], sort=True):
        g = g[g["cell"].isin(_points(cells, g))]
        its = sorted(int(i) for i in g["iteration"].unique())
        for col, (label, unit, digits, higher) in CURVE_MEASURES.items():
            if g[col].isna().all():
                continue
            mc = _mean_curves(g, col)
            rows = []
            for c in order:
                for md in modes:
                    r = mc[(mc["cell"] == c) & (mc["bridge_mode"] == md)].set_index("iteration")
                    if r.empty:
                        continue
                    rows.append([_cell_label(c, cells), md]
                                + [_fmt(r.loc[i, col], r.loc[i, f"{col}_hw"], digits) if i in r.index else "-"
                                   for i in its]
                                + [f"{r['wall_time_s'].iloc[-1]:.1f}"])
            unit_s = f" [{unit}]" if unit else ""
            best = "higher" if higher else "lower"
            out[f"{ds}/{sc}, n = {n}: {label}{unit_s} along the run ({best} is better)"] = (
                ["cell", "mode"] + [f"it. {i}" for i in its] + ["training time at the last [s]"], rows)
    return out


def study_plots(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, out: Path,
                curves: pd.DataFrame | None = None) -> list[Path]:
    """Per (dataset, scene, n): for each axis, PSNR and floater fraction (SSIM where no run has
    a floater measure) against the level
    (mean and 95 % interval, one line per mode, the base cell at the axis's reference level);
    and each held-out measure along the run (PSNR, SSIM, LPIPS where logged) against training
    wall time for the zero cell and the named points."""
    curves = collect_curves(runs) if curves is None else curves
    plt = _pyplot()
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
            p = out / f"{ds}__{sc}__n{n}__axis_{param}__{base}.png"
            fig.savefig(p, dpi=90)
            plt.close(fig)
            paths.append(p)
        # error against time: zero cell and the named operating points, one plot per measure
        sub = curves[(curves["dataset"] == ds) & (curves["scene"] == sc) & (curves["n"] == n)
                     & curves["cell"].isin(_points(cells, g))]
        for col, (label, unit, _, _) in CURVE_MEASURES.items():
            if sub.empty or sub[col].isna().all():
                continue
            fig, ax = plt.subplots(figsize=(6, 4))
            for (cell, mode), gm in _mean_curves(sub, col).groupby(["cell", "bridge_mode"], sort=True):
                ax.plot(gm["wall_time_s"], gm[col], marker=".", label=f"{cell} / {mode}")
            ax.set_xlabel("training wall time [s] (mean over seeds)")
            ax.set_ylabel(f"{label}" + (f" [{unit}]" if unit else "") + " (mean over seeds)")
            ax.set_title(f"{ds}/{sc}, n = {n}: error against time")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            fig.tight_layout()
            p = out / f"{ds}__{sc}__n{n}__{col.removeprefix('test_')}_vs_time.png"
            fig.savefig(p, dpi=90)
            plt.close(fig)
            paths.append(p)
    return paths


SIMULATION_NOTE = ("Every cell is the oracle (ground truth with seeded noise), never VGGT. Named operating "
                   "points ending in `_sim` are simulations of VGGT-like error (pose noise calibrated to the "
                   "ATE and rotation errors the paper reports for VGGT), not VGGT output.")
POSED_NOTE = ("Every cell is the posed initialiser (the scene's reference cameras, estimated from all of its "
              "images, and points triangulated with them; evaluation/initialisers/posed.py) with the oracle's seeded noise, "
              "never VGGT. It has no confidence: Bridge mode uniform only; no floater measure without a "
              "ground-truth mesh.")


def _init_note(runs: pd.DataFrame) -> str:
    inits = set(runs["init"]) if "init" in runs else {"oracle"}
    return " ".join(([SIMULATION_NOTE] if "oracle" in inits else []) + ([POSED_NOTE] if "posed" in inits else []))


def _all_tables(runs, summary, cells, curves, refs=None) -> dict[str, tuple[list, list]]:
    order = _cell_order(runs, cells)
    return {**reference_tables(refs), **measure_tables(summary, order, cells),
            **difference_tables(runs, order, cells),
            **along_run_tables(collect_curves(runs) if curves is None else curves, order, cells)}


REFERENCE_NOTE = ("Reference initialisers (e.g. the COLMAP baseline) are the regular runs of the same views and "
                  "training budget: one run each, no seeds, no interval, Bridge mode uniform (COLMAP has no "
                  "confidence, so gated and filtered do not apply); a failed COLMAP is reported as such.")


def study_markdown(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, plots: list[Path],
                   out_dir: Path, curves: pd.DataFrame | None = None, refs: pd.DataFrame | None = None) -> str:
    order = _cell_order(runs, cells)
    k = runs.groupby(["dataset", "scene", "n", "cell", "bridge_mode"])["seed"].nunique()
    lpips_nets = sorted(set(runs["lpips_net"]))
    parts = ["# Initialisation study", "", _init_note(runs), "",
             f"{len(runs)} runs; {runs['cell'].nunique()} cells; seeds per cell and mode: "
             f"{int(k.min())}-{int(k.max())}; training iterations: "
             f"{', '.join(str(int(i)) for i in sorted(runs['iterations'].dropna().unique()))}; "
             f"LPIPS network: {', '.join(lpips_nets)}. Every entry: mean ± 95 % t-interval half-width "
             "over seeds (evaluation/study/collect.py). \"Final\" is `python -m evaluation images` on the final "
             "model's PNG renders; \"best it.\" is the best of the trainer's held-out evaluations along the "
             "run (`train/log.parquet`; float renders): the highest PSNR, the highest SSIM, the lowest "
             "LPIPS, each at its own iteration.", "", "## Cells", ""]
    rows = []
    for c in order:
        info = cells.get(c, {})
        noise = info.get("noise") or {}
        rows.append([c, str(info.get("axis") or "-"), str(info.get("base") or "-")]
                    + [str(noise.get(key, "-")) for key in ("rot_deg", "trans_frac", "depth_rel", "outlier_frac",
                                                            "conf_noise", "conf_mode")])
    parts.append(_md_table(["cell", "axis", "base", "rot_deg", "trans_frac", "depth_rel", "outlier_frac",
                            "conf_noise", "conf_mode"], rows))
    if refs is not None and not refs.empty:
        parts += ["", REFERENCE_NOTE]
    for title, (header, rows) in _all_tables(runs, summary, cells, curves, refs).items():
        parts += ["", f"## {title}", "", _md_table(header, rows)]
    if plots:
        parts += ["", "## Plots", ""]
        parts += [f"![{p.stem}]({p.relative_to(out_dir).as_posix()})" for p in plots]
    return "\n".join(parts) + "\n"


def _md_to_html_table(header, rows) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def study_section_html(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, plots: list[Path],
                       img_prefix: str, curves: pd.DataFrame | None = None,
                       refs: pd.DataFrame | None = None) -> str:
    """The study as an HTML section (h2 + tables + plots); images at ``img_prefix + name``."""
    inits = ", ".join(sorted(set(runs["init"]))) if "init" in runs else "oracle"
    parts = [f"<h2>Initialisation study ({html.escape(inits)} cells; mean ± 95 % interval over seeds)</h2>",
             f"<p>{html.escape(_init_note(runs))}</p>"]
    if refs is not None and not refs.empty:
        parts.append(f"<p>{html.escape(REFERENCE_NOTE)}</p>")
    for title, (header, rows) in _all_tables(runs, summary, cells, curves, refs).items():
        parts += [f"<h3>{html.escape(title)}</h3>", _md_to_html_table(header, rows)]
    for p in plots:
        parts.append(f'<p><img src="{html.escape(img_prefix + p.name)}" alt="{html.escape(p.stem)}"></p>')
    return "\n".join(parts)


def run_study(root: str | Path, out: str | Path, cells: dict | None = None, references=None,
              seeds=None, views=None) -> Path:
    """Write ``out/``: study.md, runs.csv, summary.csv, curves.csv (:func:`collect_curves`),
    references.csv (:func:`collect_references` of the ``references`` run folders), plots/*.png,
    section.html, index.html. Only the runs the grid plans are read (``cells``, ``seeds``,
    ``views``: :func:`planned_runs`)."""
    root, out = Path(root), Path(out)
    cells = cells or {}
    runs = collect_study(root, cells, seeds, views)
    if runs.empty:
        raise ValueError(f"no study runs under {root} "
                         f"({{cell}}/s{{seed}}/{{dataset}}/{{scene}}/n{{n}}/{{init}}/{{mode}}, init one of {STUDY_INITS})")
    summary = summarise(runs)
    t0 = time.perf_counter()
    curves = collect_curves(runs)
    refs = collect_references(references)
    with atomic_dir(out) as tmp:
        plots = study_plots(runs, summary, cells, tmp / "plots", curves)
        runs.to_csv(tmp / "runs.csv", index=False)
        summary.to_csv(tmp / "summary.csv", index=False)
        curves.to_csv(tmp / "curves.csv", index=False)
        refs.to_csv(tmp / "references.csv", index=False)
        (tmp / "study.md").write_text(study_markdown(runs, summary, cells, plots, tmp, curves, refs))
        section = study_section_html(runs, summary, cells, plots, "plots/", curves, refs)
        (tmp / "section.html").write_text(section)
        (tmp / "index.html").write_text(
            "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>Initialisation study</title>"
            "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;font-size:13px}"
            "td,th{border:1px solid #ccc;padding:3px 6px}</style></head><body>"
            + section + "</body></html>\n")
        write_json(tmp / "cells.json", cells)
    log.info("study: %d runs, %d cells, %d reference runs (%d succeeded), %d plots -> %s (%.1f s)", len(runs),
             runs["cell"].nunique(), len(refs), int(refs["success_paper"].sum()) if len(refs) else 0, len(plots),
             out, time.perf_counter() - t0)
    return out / "study.md"
