"""VGGT's pose encoding and depth unprojection, numerically as the reference computes them.

Conventions: extrinsics are cam_from_world [R | t] in OpenCV axes (x right, y down,
z forward); intrinsics are in pixels of the network input with the principal point at
(W/2, H/2). The reference unprojection uses integer pixel indices (u = column, v = row,
no half-pixel offset); :func:`unproject_depth` reproduces that exactly.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["quat_xyzw_to_rotmat", "pose_encoding_to_extri_intri", "unproject_depth"]


def quat_xyzw_to_rotmat(quat: torch.Tensor) -> torch.Tensor:
    """[..., 4] quaternion (x, y, z, w), any norm (divided by |q|^2) -> [..., 3, 3]."""
    i, j, k, r = torch.unbind(quat, -1)
    two_s = 2.0 / (quat * quat).sum(-1)
    o = torch.stack((
        1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
        two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
        two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j),
    ), -1)
    return o.reshape(quat.shape[:-1] + (3, 3))


def pose_encoding_to_extri_intri(pose_enc: torch.Tensor, image_hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose encoding "absT_quaR_FoV" -> (extrinsics, intrinsics).

    Args:
        pose_enc: [..., 9] = t (3), quaternion XYZW (4), fov_h, fov_w (radians).
        image_hw: (H, W) of the network input.

    Returns:
        extrinsics [..., 3, 4] cam_from_world; intrinsics [..., 3, 3] with
        fx = (W/2)/tan(fov_w/2), fy = (H/2)/tan(fov_h/2), cx = W/2, cy = H/2, in the dtype
        of ``pose_enc``.
    """
    H, W = image_hw
    R = quat_xyzw_to_rotmat(pose_enc[..., 3:7])
    extr = torch.cat((R, pose_enc[..., :3, None]), dim=-1)
    fy = (H / 2.0) / torch.tan(pose_enc[..., 7] / 2.0)
    fx = (W / 2.0) / torch.tan(pose_enc[..., 8] / 2.0)
    K = torch.zeros(pose_enc.shape[:-1] + (3, 3), dtype=pose_enc.dtype, device=pose_enc.device)
    K[..., 0, 0] = fx
    K[..., 1, 1] = fy
    K[..., 0, 2] = W / 2
    K[..., 1, 2] = H / 2
    K[..., 2, 2] = 1.0
    return extr, K


def unproject_depth(depth: np.ndarray, extrinsics: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """World points from depth maps, as the reference ``unproject_depth_map_to_point_map``.

    Camera points X = (u - cx) d / fx, Y = (v - cy) d / fy, Z = d with u the column and v the
    row index (no half-pixel offset), cast to float32; then world = R^T (X - t) with the
    closed-form inverse in float64.

    Args:
        depth: [S, H, W] or [S, H, W, 1] z-depth.
        extrinsics: [S, 3, 4] cam_from_world.
        intrinsics: [S, 3, 3].

    Returns:
        [S, H, W, 3] float64 world points.
    """
    depth = np.asarray(depth)
    if depth.ndim == 4:
        depth = depth[..., 0]
    S, H, W = depth.shape
    extr = np.asarray(extrinsics)
    intr = np.asarray(intrinsics)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    out = np.empty((S, H, W, 3), dtype=np.float64)
    for s in range(S):
        d = depth[s]
        K = intr[s]
        cam = np.stack(((u - K[0, 2]) * d / K[0, 0], (v - K[1, 2]) * d / K[1, 1], d), axis=-1).astype(np.float32)
        R = extr[s, :3, :3]
        t = extr[s, :3, 3:]
        inv = np.tile(np.eye(4), (1, 1))
        inv[:3, :3] = R.T
        inv[:3, 3:] = -(R.T @ t)
        out[s] = np.dot(cam, inv[:3, :3].T) + inv[:3, 3]
    return out
