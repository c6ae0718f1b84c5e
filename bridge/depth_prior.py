"""The depth prior the Bridge writes beside the seed (``depth_prior.npz``, :mod:`camio.depth_prior`).

The initialiser's own depth of each training camera, in the seed's normalised frame (Eq. 1):

* a point map per view (VGGT, the oracle, ``ba_init --seed-points dense``): every valid pixel's
  point of view s, seen from camera s (camera z, projected pixel), weighted by Eq. 2's
  normalised confidence (:func:`bridge.equations.confidence_ratio`) over the same range as the
  seed's opacity: the confidence keeps acting in training through this weight;
* a COLMAP-style model (COLMAP, ``posed``): each camera's observed points at their observed
  pixels, weight 1 (a sparse prior); a model without observations gives no prior.

Samples behind a camera or projecting outside its image are dropped; a view keeps at most
``max_per_view`` samples (an evenly spread random subset, seeded).
"""

from __future__ import annotations

import logging

import numpy as np

from bridge.equations import confidence_ratio
from camio.cameras import Camera
from camio.depth_prior import DepthSamples

__all__ = ["dense_depth_samples", "observed_depth_samples"]

log = logging.getLogger(__name__)


def _camera_z_xy(points: np.ndarray, cam_from_world: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera z [M] and pixel xy [M, 2] of world ``points`` [M, 3] (OpenCV camera, K in pixels)."""
    x = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = x[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (x @ K.T)[:, :2] / z[:, None]
    return z, uv


def _keep(z: np.ndarray, xy: np.ndarray, cam: Camera) -> np.ndarray:
    return (np.isfinite(z) & (z > 0) & np.all(np.isfinite(xy), axis=1) & (xy[:, 0] >= 0) & (xy[:, 0] < cam.width)
            & (xy[:, 1] >= 0) & (xy[:, 1] < cam.height))


def _cap(idx: np.ndarray, max_per_view: int, rng: np.random.Generator) -> np.ndarray:
    if len(idx) <= max_per_view:
        return idx
    return np.sort(rng.choice(idx, size=max_per_view, replace=False))


def _pack(cameras: list[Camera], per_view: list[tuple[np.ndarray, np.ndarray, np.ndarray]], source: str) -> DepthSamples:
    view = np.concatenate([np.full(len(z), k, np.int64) for k, (z, _, _) in enumerate(per_view)])
    return DepthSamples([c.name for c in cameras], [[c.width, c.height] for c in cameras], view,
                        np.concatenate([xy for _, xy, _ in per_view]).reshape(-1, 2),
                        np.concatenate([z for z, _, _ in per_view]), np.concatenate([w for _, _, w in per_view]),
                        source)


def dense_depth_samples(points_n: np.ndarray, rows: np.ndarray, conf: np.ndarray, grid_shape: tuple[int, int, int],
                        cameras: list[Camera], c_min: float, c_max: float, max_per_view: int,
                        seed: int = 0) -> DepthSamples:
    """Depth samples from a per-view point map.

    Args:
        points_n: [M, 3] valid points in the normalised frame.
        rows: [M] their flat pixel index s*H*W + i*W + j in the (S, H, W) point map.
        conf: [M] their confidences; c_min, c_max: Eq. 2's range (the seed's).
        grid_shape: (S, H, W) of the point map.
        cameras: the S normalised cameras (K at their width x height), in point-map order.
        max_per_view: cap on the samples of one view.
        seed: seed of the subset drawn under the cap.

    Returns:
        the samples (``source`` "dense").
    """
    S, H, W = grid_shape
    if len(cameras) != S:
        raise ValueError(f"{S} point-map views but {len(cameras)} cameras")
    rng = np.random.default_rng(seed)
    view_of = rows // (H * W)
    weight = confidence_ratio(conf, c_min, c_max)
    per_view = []
    for k, cam in enumerate(cameras):
        idx = np.flatnonzero(view_of == k)
        z, xy = _camera_z_xy(points_n[idx], cam.cam_from_world, cam.K)
        keep = _cap(np.flatnonzero(_keep(z, xy, cam)), max_per_view, rng)
        per_view.append((z[keep], xy[keep], weight[idx][keep]))
    return _pack(cameras, per_view, "dense")


def observed_depth_samples(points_n: np.ndarray, observations: dict[str, tuple[np.ndarray, np.ndarray]],
                           cameras: list[Camera], max_per_view: int, seed: int = 0) -> DepthSamples | None:
    """Depth samples from a model's observations (weight 1); None when it has none.

    Args:
        points_n: [P, 3] the model's points in the normalised frame (rows as in ``observations``).
        observations: image name -> (xy [K, 2] observed pixels, point rows [K]).
        cameras: the normalised cameras.
        max_per_view: cap on the samples of one view; seed: of the subset drawn under it.
    """
    if not any(len(observations.get(c.name, ((), ()))[1]) for c in cameras):
        return None
    rng = np.random.default_rng(seed)
    per_view = []
    for cam in cameras:
        xy, pidx = observations.get(cam.name, (np.zeros((0, 2)), np.zeros(0, np.int64)))
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        z, _ = _camera_z_xy(points_n[np.asarray(pidx, np.int64)], cam.cam_from_world, cam.K)
        keep = _cap(np.flatnonzero(_keep(z, xy, cam)), max_per_view, rng)
        per_view.append((z[keep], xy[keep], np.ones(len(keep))))
    return _pack(cameras, per_view, "sparse")
