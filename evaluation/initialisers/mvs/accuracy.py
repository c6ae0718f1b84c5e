"""How good a dense initialiser's depth is: against exact depth, and on held-out views.

* :func:`depth_accuracy`: against ground-truth z-depth (the synthetic scene's ``gt/depth``):
  AbsRel = mean |z - z*| / z* and the share with max(z / z*, z* / z) < 1.25 (delta1), over the
  kept pixels that have ground truth; completeness = kept / pixels with ground truth; and the
  AbsRel per confidence decile (the confidence means something when it falls).
* :func:`heldout_reprojection`: on real scenes with reference cameras, the fused points seen
  from views that were not used: the share of a held-out view's pixels they cover, and how
  well they agree with the view's own photo (a point's colour against the pixel it lands on):
  the mean absolute colour difference of the nearest point per pixel, beside that of the same
  points shuffled (what a wrong geometry would score).
* :func:`heldout_depth_error`: the same held-out view against the scene's reference points
  (its COLMAP model, triangulated from all images by the dataset's authors): where a reference
  point is observed in the held-out view, the depth of the nearest fused point on that pixel
  against the reference point's depth; the fused points' geometric error where no training
  view looked from. A reference model without observations stands in with its points that are
  the nearest on their pixel of that view (:func:`visible_points`).
"""

from __future__ import annotations

import numpy as np

#: a held-out depth counts as right within this relative error of the reference point's
DEPTH_TOLERANCE = 0.05

__all__ = ["DEPTH_TOLERANCE", "depth_accuracy", "confidence_deciles", "heldout_reprojection", "heldout_depth_error",
           "zbuffer", "visible_points"]


def confidence_deciles(err: np.ndarray, conf: np.ndarray, bins: int = 10) -> list[dict]:
    """Mean of ``err`` [N] per ``bins`` equal-count bins of ``conf`` [N], lowest first."""
    if len(err) < bins:
        return []
    order = np.argsort(conf, kind="stable")
    out = []
    for part in np.array_split(order, bins):
        out.append({"conf_min": float(conf[part].min()), "conf_max": float(conf[part].max()),
                    "mean_error": float(err[part].mean()), "pixels": int(len(part))})
    return out


def depth_accuracy(depth: list[np.ndarray], conf: list[np.ndarray], gt: list[np.ndarray]) -> dict:
    """Accuracy of per-view depth against ground truth (module docstring).

    Args:
        depth: per view [H, W] z-depth, NaN (or <= 0) where no point was kept.
        conf: per view [H, W] confidence.
        gt: per view [H, W] ground-truth z-depth at the same pixels, 0 where none (sky).

    Returns:
        ``abs_rel``, ``delta1`` (share of kept pixels), ``completeness``, ``kept``,
        ``gt_pixels``, ``deciles`` (AbsRel per confidence decile, lowest first),
        ``per_view`` (the first three per view). NaN figures where nothing was kept.
    """
    errs, ratios, confs, per_view = [], [], [], []
    n_gt = n_kept = 0
    for d, c, g in zip(depth, conf, gt):
        g = np.asarray(g, np.float64)
        d = np.asarray(d, np.float64)
        has_gt = g > 0
        with np.errstate(invalid="ignore"):
            kept = np.isfinite(d) & (d > 0) & has_gt
        rel = np.abs(d[kept] - g[kept]) / g[kept]
        ratio = np.maximum(d[kept] / g[kept], g[kept] / d[kept])
        errs.append(rel)
        ratios.append(ratio)
        confs.append(np.asarray(c, np.float64)[kept])
        n_gt += int(has_gt.sum())
        n_kept += int(kept.sum())
        per_view.append({"abs_rel": float(rel.mean()) if len(rel) else float("nan"),
                         "delta1": float((ratio < 1.25).mean()) if len(rel) else float("nan"),
                         "completeness": float(kept.sum() / max(has_gt.sum(), 1))})
    err = np.concatenate(errs) if errs else np.zeros(0)
    ratio = np.concatenate(ratios) if ratios else np.zeros(0)
    cf = np.concatenate(confs) if confs else np.zeros(0)
    return {
        "abs_rel": float(err.mean()) if len(err) else float("nan"),
        "delta1": float((ratio < 1.25).mean()) if len(ratio) else float("nan"),
        "completeness": n_kept / max(n_gt, 1),
        "kept": n_kept, "gt_pixels": n_gt,
        "deciles": confidence_deciles(err, cf),
        "per_view": per_view,
    }


def heldout_reprojection(points: np.ndarray, colors: np.ndarray, image: np.ndarray, K: np.ndarray,
                         cfw: np.ndarray, seed: int = 0) -> dict:
    """Fused points [N, 3] with colours [N, 3] uint8 seen from a held-out view.

    Args:
        image: [H, W, 3] uint8 the held-out photo.
        K, cfw: its intrinsics at [H, W] and cam_from_world.

    Returns:
        ``coverage`` (share of the view's pixels with a point in front), ``colour_error`` (mean
        absolute difference in [0, 255] of the nearest point per covered pixel against the
        photo), ``colour_error_shuffled`` (the same with the points' colours shuffled: the
        score of geometry that says nothing), ``points_in_view``.
    """
    from evaluation.initialisers.mvs.fusion import project

    H, W = image.shape[:2]
    uv, z = project(np.asarray(points, np.float64), K, cfw)
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = np.isfinite(col) & (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    if not ok.any():
        return {"coverage": 0.0, "colour_error": float("nan"), "colour_error_shuffled": float("nan"),
                "points_in_view": 0}
    flat = (row[ok] * W + col[ok]).astype(np.int64)
    zz = z[ok]
    order = np.lexsort((zz, flat))  # per pixel, nearest first
    flat, first = flat[order], np.ones(len(order), bool)
    first[1:] = flat[1:] != flat[:-1]
    px = flat[first]
    cols = np.asarray(colors)[ok][order][first].astype(np.float64)
    photo = image.reshape(-1, 3)[px].astype(np.float64)
    shuffled = cols[np.random.default_rng(seed).permutation(len(cols))]
    return {"coverage": float(len(px) / (H * W)),
            "colour_error": float(np.abs(cols - photo).mean()),
            "colour_error_shuffled": float(np.abs(shuffled - photo).mean()),
            "points_in_view": int(ok.sum())}


def zbuffer(points: np.ndarray, K: np.ndarray, cfw: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth [H, W] of the nearest of ``points`` [N, 3] on each pixel (NaN where none)."""
    from evaluation.initialisers.mvs.fusion import project

    uv, z = project(np.asarray(points, np.float64), K, cfw)
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = np.isfinite(col) & (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, (row[ok] * width + col[ok]).astype(np.int64), z[ok])
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(height, width)


def heldout_depth_error(points: np.ndarray, ref_points: np.ndarray, obs_xy: np.ndarray, obs_idx: np.ndarray,
                        K: np.ndarray, cfw: np.ndarray, width: int, height: int) -> dict:
    """Fused points [N, 3] against reference points observed in a held-out view (module docstring).

    Args:
        ref_points: [P, 3] the reference model's points (same world frame as ``points``).
        obs_xy, obs_idx: [M, 2] pixels and [M] point indices of the view's observations.
        K, cfw, width, height: the held-out camera.

    Returns:
        ``observations`` (M), ``matched`` (share with a fused point on the pixel),
        ``median_rel_error`` and ``share_within_5pct`` of |z - z_ref| / z_ref over the matched.
    """
    from evaluation.initialisers.mvs.fusion import project

    depth = zbuffer(points, K, cfw, width, height)
    _, z_ref = project(np.asarray(ref_points, np.float64)[obs_idx], K, cfw)
    col = np.clip(np.floor(obs_xy[:, 0]).astype(np.int64), 0, width - 1)
    row = np.clip(np.floor(obs_xy[:, 1]).astype(np.int64), 0, height - 1)
    z = depth[row, col]
    ok = np.isfinite(z) & (z_ref > 0)
    rel = np.abs(z[ok] - z_ref[ok]) / z_ref[ok]
    return {"observations": int(len(obs_idx)), "matched": float(ok.mean()) if len(ok) else 0.0,
            "median_rel_error": float(np.median(rel)) if len(rel) else float("nan"),
            "share_within_5pct": float((rel < DEPTH_TOLERANCE).mean()) if len(rel) else float("nan")}


def visible_points(points: np.ndarray, K: np.ndarray, cfw: np.ndarray, width: int, height: int,
                   tol: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Pixels [M, 2] and indices [M] of ``points`` [N, 3] that a camera sees: in front, inside
    the image and within ``tol`` (relative) of the nearest point on their pixel."""
    from evaluation.initialisers.mvs.fusion import project

    uv, z = project(np.asarray(points, np.float64), K, cfw)
    depth = zbuffer(points, K, cfw, width, height)
    with np.errstate(invalid="ignore"):
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = np.isfinite(col) & (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    idx = np.flatnonzero(ok)
    near = z[idx] <= depth[row[idx].astype(np.int64), col[idx].astype(np.int64)] * (1 + tol)
    return uv[idx[near]], idx[near]
