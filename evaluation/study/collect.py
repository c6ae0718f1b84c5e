"""The initialisation study's runs: per-run records of the study tree and of the reference runs.

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

The report of these records: :mod:`evaluation.study.stats` (intervals), :mod:`evaluation.study.tables`,
:mod:`evaluation.study.plots`, :mod:`evaluation.study.report` (:func:`~evaluation.study.report.run_study`).
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path

import pandas as pd

from runtime.modes import BRIDGE_MODES
from evaluation.initialisers import registry
from evaluation.reports.results import best_along, read_log, read_run

__all__ = ["MEASURES", "POSE_MEASURES", "DIFF_MEASURES", "CURVE_MEASURES", "MODES", "STUDY_INITS",
           "find_study_runs", "best_along_run", "collect_curves", "planned_runs", "collect_study",
           "collect_references", "point_cells"]

log = logging.getLogger(__name__)

# column -> (label, unit, digits): the study's measures (docs/reference.md section 6), in table order
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
    # metrics.json's share of held-out pixels covered, and the PSNR over them (where scored with alpha)
    "coverage": ("coverage (final)", "fraction", 3),
    "covered_psnr": ("PSNR covered (final)", "dB", 2),
    "num_gaussians": ("Gaussians (final)", "count", 0),
    "floater_seed": ("floater frac. (seed)", "fraction", 3),
    "floater_final": ("floater frac. (final)", "fraction", 3),
}
POSE_MEASURES = {"ate_pct_radius": ("ATE", "% radius", 2), "rel_rot_err_mean_deg": ("rel. rot. err.", "deg", 2)}
DIFF_MEASURES = ("psnr", "ssim", "lpips", "floater_final")
# log.parquet column -> (label, unit, digits, higher is better): the held-out curves along the run
CURVE_MEASURES = {"test_psnr": ("held-out PSNR", "dB", 2, True), "test_ssim": ("held-out SSIM", "", 3, True),
                  "test_lpips": ("held-out LPIPS-alex", "", 3, False)}
MODES = BRIDGE_MODES  # runtime.modes: the Bridge modes, listed once
STUDY_INITS = registry.studied()  # what a study cell can degrade (config study.initialiser)
_SEED = re.compile(r"^s(\d+)$")
_N = re.compile(r"^n(\d+)$")


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
    lg = read_log(Path(run_dir) / "train" / "log.parquet")
    if lg is None or "test_psnr" not in lg:
        return None
    cols = ["iteration", "wall_time_s"] + [c for c in CURVE_MEASURES if c in lg]
    return lg.loc[lg["test_psnr"].notna(), cols].reset_index(drop=True)


def best_along_run(lg: pd.DataFrame | None) -> dict[str, float]:
    """Best held-out SSIM (highest) and LPIPS (lowest) along the run and their iterations
    (``best_test_ssim``, ``best_ssim_iter``, ``best_test_lpips``, ``best_lpips_iter``); NaN
    where the log lacks the column or every value is null. PSNR's are read_run's."""
    out = {}
    for col, key, higher in (("test_ssim", "ssim", True), ("test_lpips", "lpips", False)):
        out[f"best_test_{key}"], out[f"best_{key}_iter"] = best_along(lg, col, higher)
    return out


def _with_lpips(rec: dict) -> dict:
    """``rec`` with ``lpips`` (LPIPS-alex when measured, else vgg) and ``lpips_net`` (which)."""
    net = "alex" if not math.isnan(rec["lpips_alex"]) else "vgg"
    rec["lpips"], rec["lpips_net"] = rec[f"lpips_{net}"], net
    return rec


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
        _with_lpips(rec)
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
        rec = _with_lpips(read_run(run, mode=modes[0] if modes else None))
        rec["bridge_mode"] = modes[0] if modes else None
        rec.update(best_along_run(_read_log(run / modes[0]) if modes else None))
        rows.append(rec)
    return pd.DataFrame(rows)


def point_cells(cells: dict, g: pd.DataFrame) -> list[str]:
    """The cells of the along-the-run record: the zero cell and the named points (no axis)."""
    return [c for c, info in cells.items() if not info.get("axis")] or sorted(set(g["cell"]))
