"""Real spherical harmonics for view-dependent Gaussian colour (degrees 0 to 3).

Convention: the constants and the basis order are the 3DGS / gsplat ones (``C0``, ``C1``,
``C2[5]``, ``C3[7]``); coefficients are stored as ``[N, K, 3]`` with ``K = (degree + 1) ** 2``
(or more; extra bands are ignored). The view direction is the unit vector from the camera
centre to the Gaussian mean, in world coordinates. Colour is ``max(sh(dir) + 0.5, 0)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from camio.ply import SH_C0  # the DC constant, shared with the PLY format's colour conversion

__all__ = ["SH_C0", "num_sh_bases", "eval_sh", "sh_to_color", "rgb_to_sh"]

SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH basis functions ``(degree + 1) ** 2`` for degree 0..3."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"sh_degree must be 0, 1, 2 or 3, got {degree}")
    return (degree + 1) ** 2


def sh_concat(dc: Tensor, rest: Tensor, degree: int) -> Tensor:
    """The coefficients of degree ``degree`` as one tensor: DC [N, 3] and the higher bands
    rest [N, K - 1, 3] (K >= (degree + 1)^2, the trainer's ``sh_dc`` / ``sh_rest``) ->
    [N, (degree + 1)^2, 3]."""
    return torch.cat([dc[:, None, :], rest[:, : num_sh_bases(degree) - 1, :]], dim=1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate real SH up to ``degree`` (no +0.5 offset, no clamp).

    Args:
        degree: 0..3.
        coeffs: [N, K, 3] coefficients, K >= (degree + 1) ** 2 (the first bases are used).
        dirs: [N, 3] unit view directions (world frame, camera centre -> mean).

    Returns:
        [N, 3] the SH value per colour channel.
    """
    nb = num_sh_bases(degree)
    if coeffs.dim() != 3 or coeffs.shape[-1] != 3 or coeffs.shape[1] < nb:
        raise ValueError(
            f"SH coefficients must be [N, K>={nb}, 3] for degree {degree}, got {tuple(coeffs.shape)}"
        )
    result = SH_C0 * coeffs[:, 0]
    if degree == 0:
        return result
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    result = result - SH_C1 * y * coeffs[:, 1] + SH_C1 * z * coeffs[:, 2] - SH_C1 * x * coeffs[:, 3]
    if degree == 1:
        return result
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    result = (
        result
        + SH_C2[0] * xy * coeffs[:, 4]
        + SH_C2[1] * yz * coeffs[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[:, 6]
        + SH_C2[3] * xz * coeffs[:, 7]
        + SH_C2[4] * (xx - yy) * coeffs[:, 8]
    )
    if degree == 2:
        return result
    return (
        result
        + SH_C3[0] * y * (3.0 * xx - yy) * coeffs[:, 9]
        + SH_C3[1] * xy * z * coeffs[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * coeffs[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * coeffs[:, 13]
        + SH_C3[5] * z * (xx - yy) * coeffs[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * coeffs[:, 15]
    )


def sh_to_color(degree: int, coeffs: Tensor, means: Tensor, cam_center: Tensor) -> Tensor:
    """View-dependent RGB ``max(sh(dir) + 0.5, 0)`` (the 3DGS rule).

    Args:
        degree: 0..3.
        coeffs: [N, K, 3] SH coefficients.
        means: [N, 3] Gaussian centres, world frame.
        cam_center: [3] camera centre, world frame.

    Returns:
        [N, 3] colours (non-negative, not clamped above).
    """
    dirs = means - cam_center[None, :]
    # A mean exactly at the camera centre has no direction; any unit vector is as good.
    norm = dirs.norm(dim=-1, keepdim=True)
    dirs = torch.where(norm > 1e-12, dirs / norm.clamp_min(1e-12), torch.zeros_like(dirs))
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient that renders ``rgb`` at degree 0: ``(rgb - 0.5) / C0`` (shape kept)."""
    return (rgb - 0.5) / SH_C0

