"""Dense pure-PyTorch alpha blending: every Gaussian against every pixel, no tiles, no kernels.

This is the test oracle for the fast paths (:mod:`splat_train.render._tiles`,
:mod:`splat_train.render.cpu.raster`). It follows the 3DGS forward rules literally, vectorised:

* Gaussians are blended front to back in ascending camera z (stable: ties keep index order).
* A Gaussian influences a pixel only when the pixel's 16x16 tile lies in its tile rectangle
  (3DGS renders a Gaussian in the tiles its 3-sigma square touches, nowhere else).
* ``power = -0.5 (a dx^2 + c dy^2) - b dx dy`` with ``d = mean2d - pixel_centre``; skipped when
  ``power > 0``; ``alpha = min(0.99, opacity exp(power))``; skipped when ``alpha < 1/255``.
* With ``T`` the transmittance in front of a Gaussian, the pixel stops at the first Gaussian
  whose ``T (1 - alpha) < 1e-4``; that Gaussian does not contribute (3DGS ``done`` rule).
  Since ``T`` only decreases, "contributes" is exactly ``cumprod(1 - alpha) >= 1e-4``.
* Output per pixel: ``accum = sum_i alpha_i T_i f_i`` for every feature channel and the final
  transmittance ``T_final = prod_i (1 - alpha_i)`` over contributing Gaussians.

Gradients come from autograd; the clamp at 0.99 passes no gradient where it is active, and
the skip / stop decisions are treated as constants (piecewise-smooth, as in 3DGS).
Memory is O(pixels x Gaussians): use it for small scenes only.
"""

from __future__ import annotations

import torch
from torch import Tensor

from splat_train.render.projection import Projected

__all__ = ["ALPHA_MAX", "ALPHA_MIN", "T_MIN", "blend_dense", "depth_order"]

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


def depth_order(depths: Tensor, visible: Tensor) -> Tensor:
    """Indices of visible Gaussians sorted by ascending depth, ties by index.

    Args:
        depths: [N] camera z. visible: [N] bool.

    Returns:
        [M] int64 indices into N.
    """
    idx = torch.nonzero(visible, as_tuple=False).squeeze(1)
    order = torch.sort(depths[idx].detach(), stable=True).indices
    return idx[order]


def blend_dense(proj: Projected, features: Tensor, opacities: Tensor) -> tuple[Tensor, Tensor]:
    """Dense front-to-back blending of projected Gaussians.

    Args:
        proj: the screen-space Gaussians of one image (:class:`splat_train.render.projection.Projected`);
            read: ``means2d`` [N, 2] pixel coordinates (COLMAP: pixel (i, j) centre at
            (j + .5, i + .5)), ``conics`` [N, 3] inverse 2D covariance (a, b, c), ``depths``
            [N] camera z (sort key only), ``rect`` [N, 4] int tile rectangle (x_min, x_max,
            y_min, y_max) in tiles of ``tile_size`` pixels, max exclusive, ``visible`` [N]
            bool, and the image size ``width`` x ``height``.
        features: [N, F] per-Gaussian values to blend (colour, depth, ...).
        opacities: [N] in [0, 1].

    Returns:
        accum [H, W, F] (no background) and T_final [H, W], rows = image y.
    """
    means2d, conics, rect = proj.means2d, proj.conics, proj.rect
    width, height, tile_size = proj.width, proj.height, proj.tile_size
    order = depth_order(proj.depths, proj.visible)
    dev, dt = means2d.device, means2d.dtype
    nf = features.shape[1]
    if order.numel() == 0:
        return means2d.new_zeros(height, width, nf) + 0 * features.sum(), means2d.new_ones(height, width)
    m = means2d[order]
    con = conics[order]
    op = opacities[order]
    feat = features[order]
    rc = rect[order]

    jj = torch.arange(width, device=dev)
    ii = torch.arange(height, device=dev)
    pix_i, pix_j = torch.meshgrid(ii, jj, indexing="ij")
    pix_i, pix_j = pix_i.reshape(-1), pix_j.reshape(-1)
    px = pix_j.to(dt) + 0.5
    py = pix_i.to(dt) + 0.5
    tx = (pix_j // tile_size)[:, None]
    ty = (pix_i // tile_size)[:, None]
    in_rect = (tx >= rc[None, :, 0]) & (tx < rc[None, :, 1]) & (ty >= rc[None, :, 2]) & (ty < rc[None, :, 3])

    dx = m[None, :, 0] - px[:, None]  # [P, M]
    dy = m[None, :, 1] - py[:, None]
    power = -0.5 * (con[None, :, 0] * dx * dx + con[None, :, 2] * dy * dy) - con[None, :, 1] * dx * dy
    power = torch.where(in_rect & (power <= 0), power, torch.full_like(power, -1e4))
    alpha = torch.clamp_max(op[None, :] * torch.exp(power), ALPHA_MAX)
    keep = in_rect & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        contributes = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
    alpha = torch.where(contributes, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    trans = torch.cumprod(one_minus, dim=1)
    t_front = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    weights = alpha * t_front  # [P, M]
    accum = weights @ feat  # [P, F]
    t_final = trans[:, -1]
    return accum.reshape(height, width, nf), t_final.reshape(height, width)
