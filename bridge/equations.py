"""The two equations of the Bridge (docs/reference.md section 2), one function each.

Both work in float64 and never return NaN: degenerate inputs either have a documented limit
(Eq. 2 with c_max = c_min) or raise a ValueError that says what to do (Eq. 1 with a zero
median).
"""

from __future__ import annotations

import logging

import numpy as np

from camio.cameras import to_homogeneous

__all__ = ["global_coordinate_normalisation", "uncertainty_gated_opacity", "confidence_ratio", "ALPHA_MIN", "ALPHA_MAX"]

log = logging.getLogger(__name__)

ALPHA_MIN = 0.05
ALPHA_MAX = 0.5


def global_coordinate_normalisation(
    points: np.ndarray, cam_from_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Eq. 1, Global Coordinate Normalisation.

        s  = 1 / median_i ||p_i||_2
        P' = s P
        t' = s t     for every camera (cam_from_world = [R | t]); R is unchanged.

    Scaling the world about its origin by s maps x_cam = R p + t to s x_cam = R (s p) + s t,
    so every camera sees the same (scaled) scene: relative geometry, rotations, intrinsics
    and image projections are preserved.

    The median runs over *every* row of ``points``: the caller decides the set. The Bridge
    passes all valid (finite) predicted points of every pixel of every view, before the
    pixel stride or any filter, as the paper does ("over all predicted points"; the seed
    code takes the median before its subsampling too), so that s does not depend on
    ``--stride``, ``--percentile``, the voxel size or the point cap.

    Args:
        points: [..., 3] world points (input world frame), all finite.
        cam_from_world: [S, 3, 4] or [S, 4, 4] extrinsics (OpenCV axes, input world frame);
            [3, 4] / [4, 4] for a single camera is accepted too.

    Returns:
        points_n: [..., 3] float64 points in the normalised frame, s * points.
        cam_from_world_n: [S, 3, 4] (or [3, 4]) float64, translation multiplied by s.
        s: the scale factor, a finite positive float.

    Raises:
        ValueError: no points, non-finite points, or a median norm of 0 (more than half of
            the points at the origin) or one so small that s overflows.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points must have shape [..., 3], got {p.shape}")
    flat = p.reshape(-1, 3)
    if len(flat) == 0:
        raise ValueError("Eq. 1 needs at least one point; the prediction has no valid point")
    if not np.all(np.isfinite(flat)):
        raise ValueError("Eq. 1 needs finite points; drop NaN/Inf rows before normalising")
    m = np.asarray(cam_from_world, dtype=np.float64)
    single = m.ndim == 2
    m = to_homogeneous(m[None] if single else m)[:, :3, :].copy()
    if not np.all(np.isfinite(m)):
        raise ValueError("Eq. 1: a camera pose is not finite; check the predicted extrinsics")

    # hypot avoids overflow of x^2 for coordinates near the float64 limit
    norms = np.hypot(np.hypot(flat[:, 0], flat[:, 1]), flat[:, 2])
    med = float(np.median(norms))
    if not med > 0.0:
        n_origin = int(np.count_nonzero(norms == 0.0))
        raise ValueError(
            f"Eq. 1 is undefined: the median distance to the origin is 0 ({n_origin} of "
            f"{len(norms)} points lie exactly at the origin), so s = 1/median is infinite. "
            "The prediction is degenerate; if zeros mark invalid pixels, write NaN there "
            "(the Bridge drops non-finite points) or check the point map."
        )
    s = 1.0 / med
    if not np.isfinite(s):
        raise ValueError(f"Eq. 1: median norm {med:.3g} is too small, s = 1/median overflows")
    p_n = p * s
    m[:, :, 3] *= s
    if not (np.all(np.isfinite(p_n)) and np.all(np.isfinite(m))):
        raise ValueError(f"Eq. 1: scaling by s = {s:.3g} overflows float64; the input spans too many orders")
    log.debug("Eq. 1: median ||p|| = %.6g over %d points, s = %.6g", med, len(norms), s)
    return p_n, (m[0] if single else m), s


def uncertainty_gated_opacity(
    conf: np.ndarray,
    alpha_min: float = ALPHA_MIN,
    alpha_max: float = ALPHA_MAX,
    c_min: float | None = None,
    c_max: float | None = None,
) -> np.ndarray:
    """Eq. 2, Uncertainty-Gated Seeding: initial opacity from confidence.

        alpha_i = a_min + (a_max - a_min) * (c_i - c_min) / (c_max - c_min)

    c_min and c_max are the min and max confidence over the scene's cloud; the Bridge
    passes the extremes over all valid predicted points (the same set as Eq. 1), as the
    seed code normalised confidence before subsampling. They default to the extremes of
    ``conf``.

    Limits and numerics:

    * c_max = c_min (every confidence equal, e.g. a single point): the ratio is 0/0. Its
      limit is defined as 1, i.e. alpha = a_max for every point. Eq. 2 ranks points
      relative to the most confident one; when all are equal, none is less trusted than
      the best, so none is gated down. (The seed code gives the same: it clipped the
      un-normalisable confidence into [0, 1], and VGGT confidences are > 1.)
    * The ratio is computed as (c/2 - c_min/2) / (c_max/2 - c_min/2) in float64, which
      cannot overflow for any finite input (confidences from 1e-6 to 1e6 and beyond), and
      is clipped to [0, 1], and alpha to [a_min, a_max] (a_min + (a_max - a_min) * 1 can
      round one ulp above a_max), so alpha is always in [a_min, a_max], even for a c_i
      outside [c_min, c_max].

    Args:
        conf: [N] finite confidences (any real values; VGGT's are > 1).
        alpha_min, alpha_max: the opacity range, 0 < alpha_min <= alpha_max < 1 (opacity
            is stored as a logit, so 0 and 1 are excluded).
        c_min, c_max: the confidence range of the scene; default min/max of ``conf``.

    Returns:
        [N] float64 alpha in [alpha_min, alpha_max].

    Raises:
        ValueError: non-finite confidence, an alpha range outside (0, 1) or reversed, or
            c_min > c_max.
    """
    c = np.asarray(conf, dtype=np.float64).reshape(-1)
    if not (0.0 < alpha_min <= alpha_max < 1.0):
        raise ValueError(
            f"need 0 < alpha_min <= alpha_max < 1, got alpha_min={alpha_min}, alpha_max={alpha_max}"
        )
    ratio = confidence_ratio(c, c_min, c_max)
    # the final clip removes the 1-ulp overshoot of a_min + (a_max - a_min) * 1 over a_max
    return np.clip(alpha_min + (alpha_max - alpha_min) * ratio, alpha_min, alpha_max)


def confidence_ratio(conf: np.ndarray, c_min: float | None = None, c_max: float | None = None) -> np.ndarray:
    """Eq. 2's normalised confidence, (c_i - c_min) / (c_max - c_min) clipped to [0, 1], with
    the limits documented in :func:`uncertainty_gated_opacity` (1 when c_max = c_min; no
    overflow). Also the depth prior's sample weight (:mod:`bridge.depth_prior`).

    Args:
        conf: [N] finite confidences; c_min, c_max: the scene's range (default: of ``conf``).

    Returns:
        [N] float64 in [0, 1].
    """
    c = np.asarray(conf, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(c)):
        raise ValueError("Eq. 2 needs finite confidences; drop NaN/Inf rows first")
    if len(c) == 0:
        return np.zeros(0, np.float64)
    lo = float(np.min(c)) if c_min is None else float(c_min)
    hi = float(np.max(c)) if c_max is None else float(c_max)
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo > hi:
        raise ValueError(f"need finite c_min <= c_max, got c_min={lo}, c_max={hi}")
    den = hi / 2.0 - lo / 2.0
    if den > 0.0:
        return np.clip((c / 2.0 - lo / 2.0) / den, 0.0, 1.0)
    return np.ones_like(c)  # c_max == c_min: the documented limit, ratio -> 1
