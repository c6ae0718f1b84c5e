"""Point selection and initial Gaussian scales for the Bridge.

Every function takes points in one frame (the Bridge calls them in the normalised frame
of Eq. 1) and returns a boolean mask or row indices into its input, so the caller can
count what each step dropped and carry colours and confidences along.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = [
    "stride_mask",
    "percentile_mask",
    "voxel_downsample",
    "statistical_outlier_mask",
    "cap_points",
    "knn_scales",
    "MIN_DIST2",
    "SINGLE_POINT_SCALE",
]

log = logging.getLogger(__name__)

#: floor on the mean squared 3-NN distance, as the 3DGS reference (clamp_min(dist2, 1e-7)):
#: duplicate points get scale sqrt(1e-7) ~ 3.2e-4 instead of log(0) = -inf.
MIN_DIST2 = 1e-7

#: scale of a Gaussian that has no neighbour (a cloud of one point). In the normalised frame
#: of Eq. 1 the median distance of the cloud to the origin is 1 (for one point: its own
#: distance), so this is 1 % of the scene radius: visible, but not covering the views.
SINGLE_POINT_SCALE = 0.01


def stride_mask(n: int, stride: int) -> np.ndarray:
    """Keep every ``stride``-th row of a flattened pixel array: rows 0, stride, 2*stride...

    The seed code flattens the [S, H, W] point map to [S*H*W] and keeps ``[::stride]``
    (``point_subsample: 20``); ``stride = 1`` keeps every row.

    Returns:
        [n] bool.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    mask = np.zeros(n, bool)
    mask[::stride] = True
    return mask


def percentile_mask(conf: np.ndarray, percentile: float) -> tuple[np.ndarray, float]:
    """Drop the lowest ``percentile`` % of points by confidence.

    Keeps conf >= the ``percentile``-th percentile (linear interpolation, as the seed
    code's ``np.quantile(conf, p)``), so ties at the threshold are kept and equal
    confidences keep every point.

    Args:
        conf: [N] finite confidences.
        percentile: in [0, 100).

    Returns:
        keep: [N] bool keep mask.
        threshold: the confidence threshold (NaN for an empty input).
    """
    if not 0.0 <= percentile < 100.0:
        raise ValueError(f"percentile must be in [0, 100), got {percentile}")
    c = np.asarray(conf, np.float64).reshape(-1)
    if len(c) == 0:
        return np.zeros(0, bool), float("nan")
    thr = float(np.percentile(c, percentile))
    return c >= thr, thr


def voxel_downsample(points: np.ndarray, voxel_size: float, conf: np.ndarray | None = None) -> np.ndarray:
    """One representative point per occupied voxel.

    The grid is open3d's (``voxel_down_sample``): voxel index floor((p - min_bound) / size)
    with min_bound the cloud's minimum corner; the tests check the grouping against
    open3d's ``voxel_down_sample_and_trace``. It is computed here with numpy (vectorised,
    no per-voxel Python loop). The representative is an actual input point (its colour
    and confidence stay exact), the most confident one in the voxel (the lowest row when
    ``conf`` is None or tied), rather than open3d's voxel average, which would blend
    surfaces and confidences.

    Args:
        points: [N, 3] finite points.
        voxel_size: edge length, in the units of ``points`` (> 0).
        conf: [N] confidences or None.

    Returns:
        sorted int64 row indices of the kept points.
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    if n == 0:
        return np.zeros(0, np.int64)
    keys = np.floor((p - p.min(axis=0)) / voxel_size).astype(np.int64)
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = group.reshape(-1)
    score = np.zeros(n) if conf is None else np.asarray(conf, np.float64).reshape(-1)
    # sort by voxel, then by descending score, then by row: the first of each voxel wins
    order = np.lexsort((np.arange(n), -score, group))
    first = np.ones(n, bool)
    first[1:] = group[order[1:]] != group[order[:-1]]
    return np.sort(order[first].astype(np.int64))


def statistical_outlier_mask(points: np.ndarray, nb_neighbors: int = 20, std_ratio: float = 2.0) -> np.ndarray:
    """open3d statistical outlier removal: drop points whose mean distance to their
    ``nb_neighbors`` nearest neighbours exceeds the cloud mean by ``std_ratio`` std.

    Args:
        points: [N, 3] finite points.

    Returns:
        [N] bool keep mask (all True when N <= nb_neighbors: too few points for the test).
    """
    import open3d as o3d

    p = np.asarray(points, np.float64).reshape(-1, 3)
    keep = np.ones(len(p), bool)
    if len(p) <= nb_neighbors:
        log.info("outlier removal skipped: %d points <= %d neighbours", len(p), nb_neighbors)
        return keep
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    _, ind = pcd.remove_statistical_outlier(nb_neighbors=int(nb_neighbors), std_ratio=float(std_ratio))
    keep[:] = False
    keep[np.asarray(ind, np.int64)] = True
    return keep


def cap_points(n: int, max_points: int, conf: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """Row indices of at most ``max_points`` of ``n`` points.

    With confidences: the ``max_points`` most confident (ties broken by lower row index).
    Without (COLMAP input): a uniform random subset drawn with ``seed``.

    Returns:
        sorted int64 row indices.
    """
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    if n <= max_points:
        return np.arange(n, dtype=np.int64)
    if conf is None:
        idx = np.random.default_rng(seed).choice(n, size=max_points, replace=False)
    else:
        c = np.asarray(conf, np.float64).reshape(-1)
        idx = np.lexsort((np.arange(n), -c))[:max_points]
    return np.sort(idx.astype(np.int64))


def knn_scales(points: np.ndarray, k: int = 3, min_dist2: float = MIN_DIST2,
               single_point_scale: float = SINGLE_POINT_SCALE) -> tuple[np.ndarray, int]:
    """Initial isotropic Gaussian scales, the 3DGS convention.

        scale_i = sqrt(max(mean_{j in kNN(i)} ||p_i - p_j||^2, min_dist2))

    (3DGS stores log(scale_i) for all three axes.) kNN excludes the point itself; a
    duplicate of it counts as a neighbour at distance 0, so a stack of duplicates gets the
    floor ``sqrt(min_dist2)``. With fewer than k + 1 points the available n - 1
    neighbours are used; a single point gets ``single_point_scale``.

    Args:
        points: [N, 3] finite points (the frame the scales are for: normalised).
        k: neighbours (3).

    Returns:
        scales: [N] float64 linear scales, all finite and > 0.
        n_floored: how many hit the floor ``min_dist2``.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    if n == 0:
        return np.zeros(0), 0
    if n == 1:
        return np.array([float(single_point_scale)]), 0
    kk = min(k, n - 1)
    dist, _ = cKDTree(p).query(p, k=kk + 1)
    dist = np.asarray(dist).reshape(n, kk + 1)[:, 1:]  # column 0: the point itself (distance 0)
    d2 = np.mean(dist * dist, axis=1)
    floored = ~(d2 >= min_dist2)
    d2 = np.where(floored, min_dist2, d2)
    return np.sqrt(d2), int(np.count_nonzero(floored))
