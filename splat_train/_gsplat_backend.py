"""Optional gsplat backend (CUDA only). UNTESTED on the development machine (no GPU there).

Used by :func:`splat_train.rasterize` with ``backend="auto"`` on CUDA tensors when ``gsplat``
imports. It maps our arguments onto ``gsplat.rasterization`` (same 3DGS semantics: eps2d 0.3,
near plane, 16x16 tiles, COLMAP-style pixel centres) and returns the same dict keys.
Differences to know: gsplat's ``means2d`` gradient and radii come from its own kernels;
``radii`` may be per axis in recent versions and is reduced to the max here.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["available", "rasterize_gsplat"]


def available() -> bool:
    """True when CUDA is present and gsplat imports."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize_gsplat(means, quats, scales, opacities, colors, cam_from_world, K, width, height,
                     background, sh_degree, near_plane) -> dict[str, Tensor]:
    """Render with gsplat; arguments and result keys as :func:`splat_train.rasterize`."""
    import gsplat

    dt = means.dtype
    view = torch.eye(4, device=means.device, dtype=dt)
    view[: cam_from_world.shape[0]] = cam_from_world.to(dt)
    rc, ra, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, view[None], K.to(dt)[None], width, height,
        near_plane=near_plane, sh_degree=sh_degree, backgrounds=background[None],
        render_mode="RGB+ED", eps2d=0.3, packed=False,
    )
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:
        radii = radii.max(dim=-1).values
    alpha = ra[0, ..., 0]
    depth = rc[0, ..., 3]
    return {
        "rgb": rc[0, ..., :3],
        "alpha": alpha,
        "depth": depth,
        "depth_accum": depth * alpha,
        "means2d": means2d,  # [1, N, 2] in gsplat; read .grad[0]
        "radii": radii.to(torch.int32),
        "visible": radii > 0,
        "depths": meta["depths"][0] if "depths" in meta else None,
        "conics": meta["conics"][0] if "conics" in meta else None,
        "colors": None,
    }
