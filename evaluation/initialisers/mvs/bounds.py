"""Which depths to sweep: bounds from the cameras alone, from points, and how many planes.

* :func:`overlap_bounds`: the inverse depths at which a reference pixel (a grid of them) lands
  inside at least one source image in front of its camera, from the cameras alone. Forward-
  facing views give rho_min = 0 (a plane at infinity is seen) and rho_max where the disparity
  reaches the image's size; converging views give a finite range on both sides.
* :func:`point_bounds`: the 2nd-98th percentile of the inverse depth of points (the coarse
  sweep's confident points, or any sparse points) in the reference camera, widened.
* :func:`plane_count`: enough planes that consecutive ones move a pixel at most ``step_px``
  along its epipolar line in any source.

All inverse depths are 1/z of the reference camera (OpenCV axes, z forward).
"""

from __future__ import annotations

import numpy as np

from evaluation.initialisers.mvs.sweep import relative_pose

__all__ = ["sample_rays", "overlap_bounds", "point_bounds", "plane_count", "epipolar_lengths"]


def sample_rays(K: np.ndarray, width: int, height: int, per_side: int = 12) -> np.ndarray:
    """Rays K^-1 [u, v, 1] of a ``per_side`` x ``per_side`` grid of pixels, corners included,
    [3, per_side^2] float64."""
    u = np.linspace(0.5, width - 0.5, per_side)
    v = np.linspace(0.5, height - 0.5, per_side)
    uu, vv = np.meshgrid(u, v)
    return np.linalg.solve(K, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)]))


def _project(A: np.ndarray, b: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of rays A [3, N] at inverse depths rho [M] through b [3]: (u, v, z) each [M, N]."""
    uvw = A[None] + rho[:, None, None] * b[None, :, None]
    z = uvw[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return uvw[:, 0] / z, uvw[:, 1] / z, z


def overlap_bounds(ref_K: np.ndarray, ref_cfw: np.ndarray, ref_size: tuple[int, int],
                   sources: list[tuple[np.ndarray, np.ndarray, tuple[int, int]]],
                   scale: float, samples: int = 4000) -> tuple[float, float] | None:
    """Inverse-depth range [rho_min, rho_max] seen by the reference and >= 1 source.

    Args:
        ref_K, ref_cfw: reference intrinsics [3, 3] and cam_from_world [3, 4].
        ref_size: (width, height) of the reference.
        sources: per source (K [3, 3], cam_from_world [3, 4], (width, height)).
        scale: a length of the scene (e.g. the median distance between camera centres): depths
            from 1e-3 to 1e4 times it are searched, log-spaced.
        samples: depths searched.

    Returns:
        (rho_min, rho_max), or None when no sampled pixel is seen by any source at any depth
        (views that do not overlap).
    """
    rays = sample_rays(ref_K, *ref_size)
    z = np.geomspace(1e-3 * scale, 1e4 * scale, samples)
    rho = np.concatenate([1.0 / z, [0.0]])  # the plane at infinity too
    seen = np.zeros(len(rho), bool)
    for K, cfw, (w, h) in sources:
        R, t = relative_pose(ref_cfw, cfw)
        u, v, zz = _project(K @ R @ rays, K @ t, rho)
        ins = (zz > 0) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
        seen |= ins.any(1)
    if not seen.any():
        return None
    return float(rho[seen].min()), float(rho[seen].max())


def point_bounds(points: np.ndarray, ref_cfw: np.ndarray, widen: float = 0.15,
                 q: tuple[float, float] = (2.0, 98.0)) -> tuple[float, float] | None:
    """Inverse-depth range of world points [N, 3] in the reference: the ``q`` percentiles of
    1/z over points in front of it, widened by ``widen`` of the range on each side (rho_min
    floored at 0). None with fewer than 10 points in front."""
    p = np.asarray(points, np.float64)
    z = p @ ref_cfw[:3, :3].T[:, 2] + ref_cfw[2, 3]
    z = z[np.isfinite(z) & (z > 0)]
    if len(z) < 10:
        return None
    lo, hi = np.percentile(1.0 / z, q)
    pad = widen * max(hi - lo, 1e-3 * hi)
    return max(float(lo - pad), 0.0), float(hi + pad)


def epipolar_lengths(ref_K: np.ndarray, ref_cfw: np.ndarray, ref_size: tuple[int, int],
                     sources: list[tuple[np.ndarray, np.ndarray, tuple[int, int]]],
                     rho_min: float, rho_max: float) -> np.ndarray:
    """Per source, the longest pixel distance that a sampled reference pixel moves in it
    between ``rho_min`` and ``rho_max`` (its epipolar segment clipped to depths in front of
    the source), [S] float64; 0 for a source that sees none of them."""
    rays = sample_rays(ref_K, *ref_size)
    rho = np.linspace(rho_min, rho_max, 257)
    out = []
    for K, cfw, (w, h) in sources:
        R, t = relative_pose(ref_cfw, cfw)
        u, v, z = _project(K @ R @ rays, K @ t, rho)
        ins = (z > 0) & (u >= -w) & (u <= 2 * w) & (v >= -h) & (v <= 2 * h)  # near the image
        du = np.where(ins[1:] & ins[:-1], np.hypot(np.diff(u, axis=0), np.diff(v, axis=0)), 0.0)
        out.append(float(np.nan_to_num(du).sum(0).max()) if du.size else 0.0)
    return np.asarray(out)


def plane_count(lengths: np.ndarray, step_px: float, min_planes: int, max_planes: int) -> int:
    """Planes such that consecutive ones move a pixel <= ``step_px`` in the source of longest
    epipolar segment (``lengths``, :func:`epipolar_lengths`), within [min_planes, max_planes]."""
    longest = float(np.max(lengths)) if len(lengths) else 0.0
    return int(np.clip(np.ceil(longest / step_px) + 1, min_planes, max_planes))


def dominant_planes(points: np.ndarray, tol: float, max_planes: int = 2, min_share: float = 0.1,
                    iterations: int = 300, seed: int = 0, apart_deg: float = 30.0,
                    known: list[np.ndarray] = ()) -> list[tuple[np.ndarray, np.ndarray]]:
    """Up to ``max_planes`` planes that each hold at least ``min_share`` of ``points`` [N, 3]
    within ``tol`` (sequential RANSAC, seeded): the scene's dominant planes (a ground, a wall),
    each as (unit normal [3], centroid of its inliers [3]) in the world frame, for the sweep's
    slanted plane families. A plane within ``apart_deg`` of a ``known`` normal or of one found
    before adds no direction: its points are set aside and the search goes on."""
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    total = len(pts)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    while len(out) < max_planes and len(pts) >= 3 and total:
        tri = pts[rng.integers(0, len(pts), (iterations, 3))]  # [I, 3, 3]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        if not good.any():
            break
        n = n[good] / norm[good, None]
        d = np.einsum("ij,ij->i", n, tri[good, 0])
        inl = np.abs(pts @ n.T - d) < tol  # [N, I]
        best = int(inl.sum(0).argmax())
        if inl[:, best].sum() < min_share * total:
            break
        sel = inl[:, best]
        centred = pts[sel] - pts[sel].mean(0)  # refit on the inliers
        normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
        normal = normal / np.linalg.norm(normal)
        seen = list(known) + [n for n, _ in out]
        if all(abs(normal @ m) < np.cos(np.deg2rad(apart_deg)) for m in seen):
            out.append((normal, pts[sel].mean(0)))
        pts = pts[~sel]
    return out


def plane_family_range(points: np.ndarray, plane: tuple[np.ndarray, np.ndarray], cfw: np.ndarray,
                       min_angle_deg: float = 25.0,
                       beyond: float = 1.3) -> tuple[np.ndarray, tuple[float, float]] | None:
    """The planes parallel to a dominant ``plane`` (normal, a point on it) that a reference
    camera sweeps: from the median distance of ``points`` [N, 3] on the plane's side of the
    camera out to ``beyond`` times their 99th percentile.

    In the camera frame the family is n_c . X_c = 1 / sigma with n_c = R n turned so that the
    dominant plane lies at sigma > 0 (a ground below the camera, a wall ahead). A dominant plane
    bounds the scene on its side (nothing lies beyond a ground or a back wall), so the farther
    half of the points' distances is where it and its parallels are. None when the plane is
    within ``min_angle_deg`` of fronto-parallel for this camera (the fronto-parallel sweep
    covers it), or fewer than 10 points lie on its side.

    Returns:
        (world normal [3] turned as above, (sigma_lo, sigma_hi)) or None.
    """
    p = np.asarray(points, np.float64)
    pc = p @ cfw[:3, :3].T + cfw[:3, 3]
    pc = pc[np.all(np.isfinite(pc), axis=1) & (pc[:, 2] > 0)]
    n = np.asarray(plane[0], np.float64) / np.linalg.norm(plane[0])
    n_c = cfw[:3, :3] @ n
    if abs(n_c[2]) > np.cos(np.deg2rad(min_angle_deg)):
        return None
    if n_c @ (cfw[:3, :3] @ np.asarray(plane[1], np.float64) + cfw[:3, 3]) < 0:
        n, n_c = -n, -n_c
    d = pc @ n_c
    d = d[d > 1e-9]
    if len(d) < 10:
        return None
    near, far = np.percentile(d, [50.0, 99.0])
    return n, (1.0 / (beyond * far), 1.0 / near)


def camera_up(cfws: list[np.ndarray]) -> np.ndarray | None:
    """The world's up as the cameras hold it, unit [3] (world frame), or None.

    People hold cameras level (no roll), so every camera's x axis is horizontal: when the x
    axes spread (cameras turned about the scene), up is the direction normal to all of them,
    signed like the cameras' image-up (-y); when they do not (forward-facing views), up is the
    mean image-up. None when the image-ups cancel out (cameras rolled every way).
    """
    R = np.stack([np.asarray(c, np.float64)[:3, :3] for c in cfws])
    mean_up = -R[:, 1].sum(0)
    if np.linalg.norm(mean_up) < 0.5 * len(cfws):
        return None
    mean_up /= np.linalg.norm(mean_up)
    sv, vt = np.linalg.svd(R[:, 0], full_matrices=False)[1:]
    if len(cfws) >= 2 and sv[1] > 0.2 * sv[0]:
        up = vt[-1]
        return up if up @ mean_up > 0 else -up
    return mean_up
