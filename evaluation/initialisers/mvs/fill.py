"""Points with no confidence on the rays stereo could not explain.

Three views around a scene overlap little: multi-view stereo keeps the pixels that two views
see and agree on, and a seed of those alone leaves the rest of every training view with no
Gaussian to fit it (the model covers less of the held-out views than 3DGS's random points do).
3DGS's random initialisation fills the whole volume; this fills only the rays that stereo left
unexplained: on a grid of every ``stride``-th pixel of each view, each pixel that kept no depth
gets one point on its ray, at an inverse depth drawn uniformly between the 5th and 95th
percentiles of the depths stereo found in that view (in all views' points seen from it when it
found none), with confidence 0. The Bridge then gives these points Eq. 2's lowest opacity in
``gated`` mode, and the optimisation moves, grows or prunes them like any seed.

Frames: cam_from_world, OpenCV axes; pixels in camio's convention (centres at +0.5).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FILL_PERCENTILES", "depth_range", "fill_unexplained"]

#: the percentiles of a view's stereo depths between which a filled point's inverse depth is drawn
FILL_PERCENTILES = (5.0, 95.0)


def depth_range(depths: np.ndarray) -> tuple[float, float] | None:
    """(near, far) z-depths: :data:`FILL_PERCENTILES` of the positive finite ``depths`` [N];
    None when there are fewer than 2 of them."""
    d = np.asarray(depths, np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < 2:
        return None
    near, far = np.percentile(d, FILL_PERCENTILES)
    return float(near), float(max(far, near * (1 + 1e-6)))


def fill_unexplained(points: np.ndarray, Ks: list[np.ndarray], cfws: list[np.ndarray], stride: int,
                     seed: int = 0) -> np.ndarray:
    """Points [S, H, W, 3] with NaN where stereo kept nothing -> the same with one point on every
    ``stride``-th unexplained pixel's ray (module docstring); other pixels are left as they are.

    Args:
        points: [S, H, W, 3] world points of the kept pixels, NaN elsewhere.
        Ks: per view [3, 3] intrinsics at the working size.
        cfws: per view [3, 4] cam_from_world (OpenCV axes).
        stride: grid step in pixels (rows and columns) of the filled pixels; >= 1.
        seed: the random generator's seed (the same inputs give the same points).

    Returns:
        [S, H, W, 3] float64; a view with no depth range to draw from is left unfilled.
    """
    from evaluation.initialisers.mvs.fusion import project, unproject

    if stride < 1:
        raise ValueError(f"fill stride must be >= 1, got {stride}")
    pts = np.array(points, np.float64, copy=True)
    S, H, W, _ = pts.shape
    everything = pts.reshape(-1, 3)
    everything = everything[np.isfinite(everything).all(1)]
    rng = np.random.default_rng(seed)
    grid = np.zeros((H, W), bool)
    grid[stride // 2::stride, stride // 2::stride] = True
    for r in range(S):
        empty = grid & ~np.isfinite(pts[r]).all(-1)
        if not empty.any():
            continue
        own = pts[r][np.isfinite(pts[r]).all(-1)]
        _, z = project(own if len(own) >= 2 else everything, Ks[r], cfws[r])
        span = depth_range(z)
        if span is None:
            continue
        inv = rng.uniform(1.0 / span[1], 1.0 / span[0], size=(H, W))
        ray = unproject(1.0 / inv, Ks[r], cfws[r])
        pts[r][empty] = ray[empty]
    return pts
