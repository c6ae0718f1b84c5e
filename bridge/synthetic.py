"""A small synthetic ``predictions.npz`` (docs/contracts.md schema) with known geometry.

For tests and dry runs of the workflow without VGGT: S cameras on a circle look at a unit
sphere inside a background sphere of radius 4; every pixel's world point is the exact
ray-cast hit, so the point map, cameras and intrinsics are mutually consistent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from runtime.atomic import save_npz
from camio.cameras import invert_cam_from_world, look_at, scale_intrinsics

__all__ = ["synthetic_predictions", "write_synthetic_predictions", "pixel_rays"]


def pixel_rays(K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the pixel centres (COLMAP convention: (j + 0.5, i + 0.5)).

    Returns:
        origin: [3] camera centre (world).
        dirs: [H, W, 3] unit ray directions (world).
    """
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pix = np.stack([jj, ii, np.ones_like(jj)], axis=-1)
    x_cam = pix @ np.linalg.inv(K).T
    world_from_cam = invert_cam_from_world(cam_from_world)
    d = x_cam @ world_from_cam[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return world_from_cam[:3, 3], d


def _hit_spheres(o: np.ndarray, d: np.ndarray, r_in: float, r_out: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance along unit rays d [..., 3] from o [3] to the first hit of the inner sphere
    (radius r_in) or else the inside of the outer sphere (o inside it); and the hit mask."""
    b = d @ o
    c_in = o @ o - r_in**2
    disc = b * b - c_in
    t_in = -b - np.sqrt(np.maximum(disc, 0.0))
    hit = (disc >= 0) & (t_in > 0)
    t_out = -b + np.sqrt(b * b - (o @ o - r_out**2))
    return np.where(hit, t_in, t_out), hit


def synthetic_predictions(n_views: int = 4, height: int = 14, width: int = 18, scale: float = 1.0,
                          original_factor: float = 4.0, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays of a predictions.npz for a synthetic scene.

    Args:
        n_views: S.
        height, width: the network-input point-map size (H, W).
        scale: global scale of the world (points and camera translations).
        original_factor: original image size = factor * (W, H); K scaled to match.
        seed: seed of the random confidences (in [1, 11), higher on the unit sphere).

    Returns:
        dict with every key of the contract, float32 geometry, uint8 colours.
    """
    rng = np.random.default_rng(seed)
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    exts, pts, conf, cols = [], [], [], []
    for k in range(n_views):
        a = 2 * np.pi * k / max(n_views, 1)
        eye = np.array([2.5 * np.sin(a), -0.3, -2.5 * np.cos(a)])
        cfw = look_at(eye, np.zeros(3))[:3]
        o, d = pixel_rays(K, cfw, height, width)
        t, hit = _hit_spheres(o, d, 1.0, 4.0)
        p = o + t[..., None] * d
        exts.append(cfw)
        pts.append(p)
        conf.append(np.where(hit, 6.0, 1.0) + rng.uniform(0.0, 5.0, size=(height, width)))
        cols.append(np.clip(np.rint((p / 8.0 + 0.5) * 255), 0, 255).astype(np.uint8))
    ext = np.stack(exts)
    ext[:, :, 3] *= scale
    w_o, h_o = int(round(width * original_factor)), int(round(height * original_factor))
    K_o = scale_intrinsics(K, w_o / width, h_o / height)
    return {
        "image_names": np.array([f"view_{k:03d}.png" for k in range(n_views)]),
        "cam_from_world": ext.astype(np.float32),
        "intrinsics": np.repeat(K[None], n_views, 0).astype(np.float32),
        "intrinsics_original": np.repeat(K_o[None], n_views, 0).astype(np.float32),
        "image_sizes_original": np.tile([w_o, h_o], (n_views, 1)).astype(np.int64),
        "world_points": (np.stack(pts) * scale).astype(np.float32),
        "world_points_conf": np.stack(conf).astype(np.float32),
        "colors": np.stack(cols),
    }


def write_synthetic_predictions(path: str | Path, **kwargs) -> Path:
    """:func:`synthetic_predictions` written to ``path`` (atomically, compressed npz)."""
    return save_npz(path, **synthetic_predictions(**kwargs))
