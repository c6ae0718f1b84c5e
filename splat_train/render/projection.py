"""EWA projection of 3D Gaussians to the image plane (the 3DGS "preprocess" step).

Convention (see :mod:`camio`): ``cam_from_world`` maps world points to the OpenCV camera frame
(x right, y down, z forward); ``K`` maps camera points to continuous pixel coordinates with the
top-left pixel centre at (0.5, 0.5) (COLMAP). Quaternions are (w, x, y, z) and need not be unit.

Per Gaussian (3DGS / gsplat semantics):

* ``t = R_cw mean + t_cw``; culled when ``t.z < near`` (0.01).
* ``Sigma = R S S^T R^T``; ``Sigma_2d = J R_cw Sigma R_cw^T J^T + 0.3 I`` (the low-pass
  dilation, no opacity compensation), where J is the perspective Jacobian evaluated at x/z, y/z
  clamped to 1.3 x the half field of view (gsplat's ``lim_x_pos/lim_x_neg`` rule, identical to
  3DGS for a centred principal point).
* radius = ceil(3 sqrt(lambda_max)) with lambda_max = mid + sqrt(max(0.1, mid^2 - det))
  (:func:`screen_radius`).
* 16x16 tile rectangle as in 3DGS ``getRect`` (computed on the 3DGS pixel grid, whose centres
  are at integers, i.e. our coordinates minus 0.5); a Gaussian touching no tile is culled
  (radius 0).

The covariance maths runs in float64 whatever the input dtype (N-sized, cheap), so huge scales
and extreme focal lengths neither overflow nor lose the 0.3-pixel dilation to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "screen_radius",
    "TILE_SIZE",
    "NEAR_PLANE",
    "EPS2D",
    "Projected",
    "quat_to_rotmat",
    "covariance_3d",
    "project_gaussians",
]

TILE_SIZE = 16
NEAR_PLANE = 0.01
EPS2D = 0.3


@dataclass
class Projected:
    """Screen-space Gaussians of one image: what the blending backends read (``means2d``,
    ``conics``, ``depths``, ``rect``, ``visible`` and the image size), one argument instead of
    their former nine positional tensors. All tensors have N rows; culled rows hold harmless
    finite values. Pixel coordinates follow COLMAP (top-left pixel centre at (0.5, 0.5)).

    Attributes:
        means2d: [N, 2] pixel coordinates (COLMAP convention), dtype of the input means.
        conics: [N, 3] inverse 2D covariance (a, b, c) of [[a, b], [b, c]], pixels^-2.
        cov2d: [N, 3] dilated 2D covariance (xx, xy, yy), pixels^2.
        depths: [N] camera-frame z.
        radii: [N] int32 3-sigma radius in pixels, 0 when culled.
        rect: [N, 4] int64 tile rectangle (x_min, x_max, y_min, y_max), max exclusive.
        visible: [N] bool, ``radii > 0``.
        width, height: the image size in pixels that ``means2d`` and ``rect`` refer to.
        tile_size: edge in pixels of the tiles that ``rect`` counts (16).
    """

    means2d: Tensor
    conics: Tensor
    cov2d: Tensor
    depths: Tensor
    radii: Tensor
    rect: Tensor
    visible: Tensor
    width: int
    height: int
    tile_size: int = TILE_SIZE


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from (w, x, y, z) quaternions [N, 4] -> [N, 3, 3].

    Quaternions are normalised; a zero quaternion gives the identity (finite gradients).
    """
    q = torch.nn.functional.normalize(quats, dim=-1, eps=1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-frame covariance ``R diag(s)^2 R^T``.

    Args:
        quats: [N, 4] (w, x, y, z).
        scales: [N, 3] linear standard deviations along the local axes.

    Returns:
        [N, 3, 3] symmetric positive semi-definite covariances.
    """
    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m @ m.transpose(-1, -2)


def screen_radius(a: Tensor, b: Tensor | None, c: Tensor, det: Tensor | None = None) -> Tensor:
    """3DGS's screen-space radius: ceil(3 sqrt(lambda_max)) pixels, with lambda_max = mid +
    sqrt(max(0.1, mid^2 - det)) the larger eigenvalue of the (dilated) 2D covariance
    [[a, b], [b, c]] (pixels^2), mid = (a + c) / 2, det = a c - b^2.

    Args:
        a, b, c: [N] entries of the 2D covariance, any float dtype (``b`` may be None when
            ``det`` is given).
        det: [N] the covariance's determinant when the caller already has it (the gsplat
            adapter: 1 / det of the conic), else computed as a c - b^2.

    Returns:
        [N] radius in pixels (float, integral values).
    """
    mid = 0.5 * (a + c)
    if det is None:
        det = a * c - b * b
    lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
    return torch.ceil(3.0 * torch.sqrt(lam))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    cam_from_world: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    eps2d: float = EPS2D,
    tile_size: int = TILE_SIZE,
) -> Projected:
    """Project 3D Gaussians (EWA splatting with dilation), compute radii and tile rectangles.

    Args:
        means: [N, 3] world-frame centres.
        quats: [N, 4] (w, x, y, z) rotations, not necessarily unit.
        scales: [N, 3] linear scales.
        cam_from_world: [4, 4] (or [3, 4]) world -> OpenCV camera.
        K: [3, 3] pinhole intrinsics (zero skew) mapping to COLMAP pixel coordinates.
        width, height: image size in pixels.
        near: near plane; Gaussians with z < near are culled.
        eps2d: dilation added to the 2D covariance diagonal (pixels^2).
        tile_size: tile edge in pixels (16).

    Returns:
        :class:`Projected`.
    """
    dtype = means.dtype
    wd = torch.float64
    R = cam_from_world[:3, :3].to(wd)
    tvec = cam_from_world[:3, 3].to(wd)
    fx, fy, cx, cy = K[0, 0].to(wd), K[1, 1].to(wd), K[0, 2].to(wd), K[1, 2].to(wd)

    p_cam = means.to(wd) @ R.T + tvec
    z = p_cam[:, 2]
    in_front = z >= near
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    x, y = p_cam[:, 0], p_cam[:, 1]
    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy

    # Perspective Jacobian at the clamped direction (3DGS / gsplat), covariance in camera frame.
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [
            fx / z_safe, zero, -fx * tx / (z_safe * z_safe),
            zero, fy / z_safe, -fy * ty / (z_safe * z_safe),
        ],
        dim=-1,
    ).reshape(-1, 2, 3)
    cov_world = covariance_3d(quats.to(wd), scales.to(wd))
    T = J @ R
    cov = T @ cov_world @ T.transpose(-1, -2)
    a = cov[:, 0, 0] + eps2d
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = in_front & torch.isfinite(det) & (det > 0) & torch.isfinite(u) & torch.isfinite(v)
    a_s = torch.where(ok, a, torch.ones_like(a))
    b_s = torch.where(ok, b, torch.zeros_like(b))
    c_s = torch.where(ok, c, torch.ones_like(c))
    det_s = a_s * c_s - b_s * b_s
    conics = torch.stack([c_s / det_s, -b_s / det_s, a_s / det_s], dim=-1)

    with torch.no_grad():
        radius = screen_radius(a_s, b_s, c_s)
        # 3DGS getRect on its integer-centred pixel grid (ours minus 0.5).
        px = torch.where(ok, u, torch.zeros_like(u)) - 0.5
        py = torch.where(ok, v, torch.zeros_like(v)) - 0.5
        gx = (width + tile_size - 1) // tile_size
        gy = (height + tile_size - 1) // tile_size
        big = 1e9  # keeps the float -> int conversion defined for far-off-screen means
        x_min = torch.clamp(torch.floor(((px - radius) / tile_size).clamp(-1.0, big)), 0, gx)
        x_max = torch.clamp(torch.floor(((px + radius + tile_size - 1) / tile_size).clamp(-1.0, big)), 0, gx)
        y_min = torch.clamp(torch.floor(((py - radius) / tile_size).clamp(-1.0, big)), 0, gy)
        y_max = torch.clamp(torch.floor(((py + radius + tile_size - 1) / tile_size).clamp(-1.0, big)), 0, gy)
        rect = torch.stack([x_min, x_max, y_min, y_max], dim=-1).to(torch.int64)
        area = (rect[:, 1] - rect[:, 0]) * (rect[:, 3] - rect[:, 2])
        visible = ok & (area > 0)
        radii = torch.where(visible, radius.clamp(max=2**30), torch.zeros_like(radius)).to(torch.int32)
        rect = torch.where(visible[:, None], rect, torch.zeros_like(rect))

    means2d = torch.stack(
        [torch.where(ok, u, torch.zeros_like(u)), torch.where(ok, v, torch.zeros_like(v))], dim=-1
    )
    return Projected(
        means2d=means2d.to(dtype),
        conics=conics.to(dtype),
        cov2d=torch.stack([a_s, b_s, c_s], dim=-1).to(dtype),
        depths=torch.where(ok, z, torch.zeros_like(z)).to(dtype),
        radii=radii,
        rect=rect,
        visible=visible,
        width=int(width),
        height=int(height),
        tile_size=int(tile_size),
    )
