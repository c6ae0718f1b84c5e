"""The study's statistics: means with 95 % intervals over seeds, and paired mode differences.

Interval (the one definition): for k >= 2 seeds, mean +- t_{0.975, k-1} * sd / sqrt(k), sd the
sample standard deviation (ddof 1); k = 1 gives no interval (NaN half-width). Paired
differences (mode A - mode B) are taken per seed (the modes of a seed share the same oracle
output) and get the same interval.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from evaluation.study.collect import DIFF_MEASURES, MEASURES, POSE_MEASURES

__all__ = ["t_interval", "welch_interval", "summarise", "paired_differences", "mean_curves"]


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


def welch_interval(a, b) -> tuple[float, float, float]:
    """(mean(a) - mean(b), 95 % half-width, Welch-Satterthwaite degrees of freedom) for two
    unpaired samples of different size and spread (finite values; each needs k >= 2, else the
    half-width and df are NaN): half = t_{0.975, df} sqrt(var_a / k_a + var_b / k_b)."""
    from scipy.stats import t

    x, y = (np.asarray(v, np.float64) for v in (a, b))
    x, y = x[np.isfinite(x)], y[np.isfinite(y)]
    if len(x) == 0 or len(y) == 0:
        return math.nan, math.nan, math.nan
    diff = float(x.mean() - y.mean())
    if len(x) < 2 or len(y) < 2:
        return diff, math.nan, math.nan
    va, vb = x.var(ddof=1) / len(x), y.var(ddof=1) / len(y)
    if va + vb == 0:
        return diff, 0.0, math.inf
    df = (va + vb) ** 2 / (va ** 2 / (len(x) - 1) + vb ** 2 / (len(y) - 1))
    return diff, float(t.ppf(0.975, df) * math.sqrt(va + vb)), float(df)


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


def mean_curves(sub: pd.DataFrame, col: str) -> pd.DataFrame:
    """Per (cell, mode, iteration): mean wall time, and mean, 95 % half-width and seed count of
    ``col`` over the seeds (:func:`t_interval`)."""
    rows = []
    for (cell, mode, it), g in sub.groupby(["cell", "bridge_mode", "iteration"], sort=True):
        m, hw, k = t_interval(g[col])
        rows.append({"cell": cell, "bridge_mode": mode, "iteration": int(it),
                     "wall_time_s": float(g["wall_time_s"].mean()), col: m, f"{col}_hw": hw, f"{col}_k": k})
    return pd.DataFrame(rows)
