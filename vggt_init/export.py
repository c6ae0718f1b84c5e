"""Writing vggt_init's outputs (docs/contracts.md, "vggt_init output").

``predictions.npz`` keys (exactly these; the last two only when the depth head ran):

=====================  ====================  =========================================================
key                    shape / dtype         meaning
=====================  ====================  =========================================================
image_names            [S] str               file names, in input order
cam_from_world         [S,3,4] float32       OpenCV axes, VGGT's world frame (frame 0's camera)
intrinsics             [S,3,3] float32       network-input pixels (principal point at the input centre)
intrinsics_original    [S,3,3] float64       original-image pixels (K mapped through resize/crop/pad)
image_sizes_original   [S,2] int64           (width, height) of the original images
world_points           [S,H,W,3] float32     point head, or depth + cameras (``points_from='depth'``)
world_points_conf      [S,H,W] float32       point-head confidence (> 1), or depth_conf for 'depth'
colors                 [S,H,W,3] uint8       the network-input image
depth                  [S,H,W] float32       depth head (z in the camera frame), optional
depth_conf             [S,H,W] float32       depth confidence (> 1), optional
=====================  ====================  =========================================================

Pixel convention for K: VGGT puts the principal point at (W/2, H/2), the image centre in
the continuous convention of camio (pixel centres at +0.5), which is how K is mapped back.

``sparse/0``: a COLMAP text model at the original resolution (PINHOLE, K from
``intrinsics_original``), with the ``max_points`` most confident finite points that lie on
image pixels (padding excluded), coloured from the input images.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from runtime.atomic import save_npz
from camio.cameras import Camera
from camio.colmap import write_text_model
from runtime.names import check_name_list
from vggt_init.preprocess import ImageGeometry

__all__ = ["PREDICTION_KEYS", "OPTIONAL_KEYS", "write_predictions", "select_points", "write_colmap"]

log = logging.getLogger(__name__)

PREDICTION_KEYS = ("image_names", "cam_from_world", "intrinsics", "intrinsics_original", "image_sizes_original",
                   "world_points", "world_points_conf", "colors")
OPTIONAL_KEYS = ("depth", "depth_conf")


def write_predictions(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Validate the key set and shapes, cast the dtypes of the table above, save atomically."""
    keys = set(arrays)
    missing = set(PREDICTION_KEYS) - keys
    extra = keys - set(PREDICTION_KEYS) - set(OPTIONAL_KEYS)
    if missing or extra:
        raise ValueError(f"predictions: missing {sorted(missing)}, unexpected {sorted(extra)}")
    if ("depth" in keys) != ("depth_conf" in keys):
        raise ValueError("predictions: depth and depth_conf go together")
    S, H, W = np.asarray(arrays["world_points"]).shape[:3]
    dtypes = {"cam_from_world": np.float32, "intrinsics": np.float32, "intrinsics_original": np.float64,
              "image_sizes_original": np.int64, "world_points": np.float32, "world_points_conf": np.float32,
              "colors": np.uint8, "depth": np.float32, "depth_conf": np.float32}
    shapes = {"cam_from_world": (S, 3, 4), "intrinsics": (S, 3, 3), "intrinsics_original": (S, 3, 3),
              "image_sizes_original": (S, 2), "world_points": (S, H, W, 3), "world_points_conf": (S, H, W),
              "colors": (S, H, W, 3), "depth": (S, H, W), "depth_conf": (S, H, W), "image_names": (S,)}
    out = {}
    for k, v in arrays.items():
        v = np.asarray(v)
        if k == "image_names":  # plain names, none twice: every reader of the file checks them too
            v = np.asarray(check_name_list([str(x) for x in v], path), dtype=str)
        else:
            v = v.astype(dtypes[k], copy=False)
        if v.shape != shapes[k]:
            raise ValueError(f"predictions[{k!r}] has shape {v.shape}, expected {shapes[k]}")
        out[k] = v
    return save_npz(path, **out)


def select_points(world_points: np.ndarray, conf: np.ndarray, colors: np.ndarray, valid: np.ndarray,
                  max_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``max_points`` most confident points (finite, on image pixels).

    Args:
        world_points: [S,H,W,3]; conf: [S,H,W]; colors: [S,H,W,3] uint8;
        valid: [S,H,W] bool (False on padding).

    Returns:
        points [N,3] float64, colours [N,3] uint8, confidences [N], by decreasing confidence.
    """
    pts = world_points.reshape(-1, 3)
    c = conf.reshape(-1)
    ok = valid.reshape(-1) & np.isfinite(c) & np.all(np.isfinite(pts), axis=1)
    idx = np.flatnonzero(ok)
    if max_points is not None and len(idx) > max_points:
        part = np.argpartition(-c[idx], max_points - 1)[:max_points]
        idx = idx[part]
    idx = idx[np.argsort(-c[idx], kind="stable")]
    return pts[idx].astype(np.float64), colors.reshape(-1, 3)[idx], c[idx]


def write_colmap(path: str | Path, names: list[str], geometries: list[ImageGeometry], cam_from_world: np.ndarray,
                 intrinsics_original: np.ndarray, points: np.ndarray, colors: np.ndarray) -> Path:
    """COLMAP text model (PINHOLE, original resolution) via camio.colmap.write_text_model."""
    cams = []
    for name, geo, T, K in zip(names, geometries, cam_from_world, intrinsics_original):
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(K))):
            raise ValueError(f"camera for {name} is not finite; the model produced NaN/Inf (see timing.json)")
        cams.append(Camera(name, geo.width, geo.height, K, np.asarray(T, dtype=np.float64)))
    return write_text_model(path, cams, points, colors)
