"""A CPU stand-in for ``gsplat.rasterization`` (gsplat 1.5.3) to test our adapter without a GPU.

What is gsplat's code and what is ours:

* gsplat's own pure-PyTorch twins from ``gsplat.cuda._torch_impl`` (imported, not copied):
  ``_quat_scale_to_covar_preci`` (3D covariance), ``_fully_fused_projection`` (EWA projection,
  eps2d dilation, near/far culling, per-axis radii [C, N, 2], means2d [C, N, 2] in pixels,
  conics, depths), ``_isect_tiles`` (which 16x16 tiles each Gaussian touches) and
  ``_spherical_harmonics`` (SH -> RGB, then gsplat's ``clamp_min(+0.5, 0)``).
* Ours: the glue below, written after ``gsplat.rendering._rasterization`` (camera centre from
  the inverse viewmat, SH masked to visible Gaussians, "RGB+ED" depth channel with a zero
  background, expected depth = accumulated / alpha.clamp(1e-10)), the opacity-aware radii of
  gsplat's CUDA projection (:func:`opacity_aware_radii`, written after its .cu source, as the
  twin lacks them), and the pixel compositing,
  which is :func:`splat_train.render._reference.blend_dense` (3DGS rules: alpha <= 0.99) over each
  Gaussian's gsplat tile rectangle. ``Ks`` enters the projection detached: gsplat 1.5.3's
  projection backward returns no gradient for it (``_FullyFusedProjection.backward``), while
  the PyTorch twin would differentiate it. gsplat's compositing (``_rasterize_to_pixels``) needs its
  CUDA kernels and nerfacc, so it is not exercised here; its alpha clamp is 0.999.

Signature: the subset of ``gsplat.rasterization`` arguments our adapter passes, for one camera
batch without leading batch dimensions; other values raise NotImplementedError.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from splat_train.render._reference import blend_dense
from splat_train.render.projection import Projected


def _tile_rects(isect_ids: Tensor, flatten_ids: Tensor, n: int, tile_width: int, tile_height: int
                ) -> tuple[Tensor, Tensor]:
    """Per-Gaussian tile rectangle from gsplat's intersection list (camera 0 only).

    Args:
        isect_ids: [M] int64 (image id | tile id) << 32 | depth bits, as ``_isect_tiles``.
        flatten_ids: [M] flattened (camera, Gaussian) index.
        n: number of Gaussians N.

    Returns:
        rect [N, 4] int64 (x_min, x_max, y_min, y_max), max exclusive; hit [N] bool.
    """
    tile_bits = (tile_width * tile_height).bit_length()
    tile = (isect_ids >> 32) & ((1 << tile_bits) - 1)
    g = flatten_ids.long() % n
    tx, ty = tile % tile_width, tile // tile_width
    big = torch.full((n,), 1 << 30, dtype=torch.int64)
    lo_x = big.scatter_reduce(0, g, tx, "amin")
    lo_y = big.scatter_reduce(0, g, ty, "amin")
    hi_x = torch.full((n,), -1, dtype=torch.int64).scatter_reduce(0, g, tx, "amax")
    hi_y = torch.full((n,), -1, dtype=torch.int64).scatter_reduce(0, g, ty, "amax")
    hit = hi_x >= 0
    rect = torch.stack([lo_x, hi_x + 1, lo_y, hi_y + 1], dim=-1)
    return torch.where(hit[:, None], rect, torch.zeros_like(rect)), hit


@torch.no_grad()
def opacity_aware_radii(radii: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor, width: int,
                        height: int) -> Tensor:
    """The per-axis radii of gsplat 1.5.3's CUDA projection, which ``rasterization`` calls with
    the opacities (``ProjectionEWA3DGSFused.cu``), from the PyTorch twin's (which has no
    opacity argument and uses 3.33 sigma): a Gaussian of opacity < 1/255 is culled, the others
    get ceil(min(3.33, sqrt(2 ln(255 opacity))) sqrt(Sigma_axis)), and one whose box then lies
    off the image is culled.

    Args:
        radii: [C, N, 2] int32 from ``_fully_fused_projection`` (0 = culled);
        means2d: [C, N, 2] pixels; conics: [C, N, 3] inverse dilated 2D covariance (A, B, C);
        opacities: [N].

    Returns:
        [C, N, 2] int32.
    """
    A, B, C = conics.unbind(-1)
    det = A * C - B * B  # 1 / det(Sigma)
    sig = torch.stack([C / det, A / det], dim=-1).clamp_min(0.0)  # Sigma_xx, Sigma_yy
    op = opacities[None, :, None].to(sig.dtype)
    extend = torch.sqrt(2.0 * torch.log((op * 255.0).clamp_min(1.0))).clamp(max=3.33)
    r = torch.ceil(extend * torch.sqrt(sig))
    inside = ((means2d[..., 0] + r[..., 0] > 0) & (means2d[..., 0] - r[..., 0] < width)
              & (means2d[..., 1] + r[..., 1] > 0) & (means2d[..., 1] - r[..., 1] < height))
    keep = (radii > 0).all(dim=-1) & (op[..., 0] >= 1.0 / 255.0) & inside
    return torch.where(keep[..., None], r, torch.zeros_like(r)).to(radii.dtype)


def rasterization(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3] or [N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,  # [C, 3]
    render_mode: str = "RGB",
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    **unsupported,
) -> tuple[Tensor, Tensor, dict]:
    """``gsplat.rasterization`` for C = 1, packed=False, classic mode (see the module docstring).

    Returns:
        render_colors [C, H, W, 3 or 4], render_alphas [C, H, W, 1], meta with ``radii``
        [C, N, 2] int32, ``means2d`` [C, N, 2] (non-leaf; call ``retain_grad``), ``depths``
        [C, N], ``conics`` [C, N, 3], ``opacities`` [C, N], tile data, ``width``, ``height``.
    """
    from gsplat.cuda._torch_impl import (
        _fully_fused_projection,
        _isect_tiles,
        _quat_scale_to_covar_preci,
        _spherical_harmonics,
    )

    if unsupported or packed or absgrad or rasterize_mode != "classic" or viewmats.shape[0] != 1:
        raise NotImplementedError(f"fake gsplat: unsupported {sorted(unsupported)} packed={packed} "
                                  f"absgrad={absgrad} mode={rasterize_mode} C={viewmats.shape[0]}")
    if render_mode not in ("RGB", "RGB+ED"):
        raise NotImplementedError(f"fake gsplat: render_mode {render_mode!r}")
    n = means.shape[0]
    covars, _ = _quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    radii, means2d, depths, conics, _ = _fully_fused_projection(
        means, covars, viewmats, Ks.detach(), width, height, eps2d=eps2d, near_plane=near_plane,
        far_plane=far_plane)  # [C, N, 2] int32, [C, N, 2], [C, N], [C, N, 3]
    radii = opacity_aware_radii(radii, means2d, conics, opacities, width, height)
    visible = (radii > 0).all(dim=-1)  # [C, N]
    if sh_degree is None:
        rgb = colors[None]  # [C, N, 3]
    else:
        campos = torch.inverse(viewmats)[:, :3, 3]  # [C, 3]
        dirs = means[None] - campos[:, None]  # [C, N, 3]
        rgb = _spherical_harmonics(sh_degree, dirs, colors[None].expand(1, -1, -1, -1))
        rgb = torch.where(visible[..., None], rgb, torch.zeros_like(rgb))
        rgb = torch.clamp_min(rgb + 0.5, 0.0)
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    tiles_per_gauss, isect_ids, flatten_ids = _isect_tiles(
        means2d, radii, depths, tile_size, tile_width, tile_height, sort=True)
    rect, hit = _tile_rects(isect_ids, flatten_ids, n, tile_width, tile_height)
    with_depth = render_mode == "RGB+ED"
    feats = torch.cat([rgb[0], depths[0, :, None]], dim=-1) if with_depth else rgb[0]
    a, b, c = conics[0].unbind(-1)  # the dilated 2D covariance is the conic's inverse
    det = (a * c - b * b).detach()
    det = torch.where(det > 0, det, torch.ones_like(det))
    shown = visible[0] & hit
    proj = Projected(means2d=means2d[0], conics=conics[0], cov2d=torch.stack([c, -b, a], -1) / det[:, None],
                     depths=depths[0], radii=torch.where(shown, radii[0].amax(-1), 0).to(torch.int32), rect=rect,
                     visible=shown, width=width, height=height, tile_size=tile_size)
    accum, t_final = blend_dense(proj, feats, opacities)
    bg = torch.zeros(feats.shape[-1], dtype=means.dtype, device=means.device)
    if backgrounds is not None:
        bg[:3] = backgrounds[0]
    render = accum + t_final[..., None] * bg
    alpha = (1.0 - t_final)[..., None]
    if with_depth:
        render = torch.cat([render[..., :3], render[..., 3:] / alpha.clamp(min=1e-10)], dim=-1)
    meta = {"radii": radii, "means2d": means2d, "depths": depths, "conics": conics,
            "opacities": opacities[None], "tile_width": tile_width, "tile_height": tile_height,
            "tiles_per_gauss": tiles_per_gauss, "isect_ids": isect_ids, "flatten_ids": flatten_ids,
            "width": width, "height": height, "tile_size": tile_size, "n_cameras": 1,
            "camera_ids": None, "gaussian_ids": None}  # None when packed=False, as in gsplat
    return render[None], alpha[None], meta
