"""How good a dense initialiser's depth is: against exact depth, and on held-out views.

* :func:`depth_accuracy`: against ground-truth z-depth (the synthetic scene's ``gt/depth``):
  AbsRel = mean |z - z*| / z* and the share with max(z / z*, z* / z) < 1.25 (delta1), over the
  kept pixels that have ground truth; completeness = kept / pixels with ground truth; and the
  AbsRel per confidence decile (the confidence means something when it falls).
* :func:`heldout_reprojection`: on real scenes with reference cameras, the fused points seen
  from views that were not used: the share of a held-out view's pixels they cover, and how
  well they agree with the view's own photo (a point's colour against the pixel it lands on,
  since no depth is known there): the mean absolute colour difference of the nearest point per
  pixel, beside that of the same points shuffled (what a wrong geometry would score).
"""

from __future__ import annotations

import numpy as np

__all__ = ["depth_accuracy", "confidence_deciles", "heldout_reprojection"]


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
