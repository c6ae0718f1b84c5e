"""Optional gsplat backend (CUDA): maps :func:`splat_train.rasterize` onto ``gsplat.rasterization``.

Used by :func:`splat_train.rasterize` with ``backend="gsplat"``, or ``"auto"`` on CUDA tensors
when gsplat imports (``pip install -e ".[gpu]"`` pins the version this was written against,
:data:`GSPLAT_VERSION`). The mapping (checked on CPU by tests/test_raster_gsplat.py, with
gsplat's own pure-PyTorch projection and SH and our dense compositing standing in for its
CUDA kernels):

* ``viewmats`` [1, 4, 4] = ``cam_from_world`` padded to 4x4 (world -> OpenCV camera, as ours);
  ``Ks`` [1, 3, 3] = ``K`` (both use pixel centres at +0.5, COLMAP);
* ``eps2d`` = :data:`splat_train.projection.EPS2D`, ``near_plane`` passed through,
  ``sh_degree`` passed through (None = plain colours), ``packed=False``, ``render_mode="RGB+ED"``;
* returned ``means2d`` is [N, 2] in pixels and its ``.grad`` after ``backward()`` is
  dL/d(means2d) in pixels, the units :meth:`splat_train.densify.DensifyStrategy.update_state`
  expects (gsplat's own meta["means2d"] is [1, N, 2]; a hook copies its gradient);
* ``radii`` [N] int32 = max over gsplat 1.5's per-axis radii [1, N, 2];
  ``visible`` = both axes > 0 (gsplat's own mask).

Known differences from our backends (gsplat's semantics, not mapping errors): gsplat's radius is
ceil(3.33 sqrt(Sigma_xx)) per axis (ours ceil(3 sqrt(lambda_max))), so the tile footprint
and the screen-size prune differ slightly; its kernels clamp alpha at 0.999 (3DGS: 0.99).
The H100 run (benchmarks/README.md) measured the resulting image and gradient differences.
"""

from __future__ import annotations

import functools
import importlib.metadata

import torch
from torch import Tensor

from splat_train.projection import EPS2D

__all__ = ["GSPLAT_VERSION", "available", "installed_version", "rasterize_gsplat"]

# The version pinned by the "gpu" and "dev" extras in pyproject.toml (keep them equal).
GSPLAT_VERSION = "1.5.3"


def installed_version() -> str | None:
    """gsplat's installed version, or None when it is not installed (never imports it)."""
    try:
        return importlib.metadata.version("gsplat")
    except importlib.metadata.PackageNotFoundError:
        return None


@functools.lru_cache(maxsize=1)
def _imports() -> bool:
    try:
        import gsplat  # noqa: F401  (pure Python at import; CUDA kernels compile on first use)
    except ImportError:
        return False
    return True


def available() -> bool:
    """True when CUDA is present and gsplat imports."""
    return torch.cuda.is_available() and _imports()


def _rasterization():
    """``gsplat.rasterization`` (a function so that tests can substitute a CPU stand-in)."""
    try:
        import gsplat
    except ImportError as exc:
        raise ImportError(f"backend 'gsplat' needs gsplat: pip install -e '.[gpu]' (gsplat=={GSPLAT_VERSION})"
                          ) from exc
    return gsplat.rasterization


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    cam_from_world: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor,
    sh_degree: int | None,
    near_plane: float,
) -> dict[str, Tensor]:
    """Render with gsplat; arguments, shapes and result keys as :func:`splat_train.rasterize`.

    Args:
        means: [N, 3] world frame; quats: [N, 4] (w, x, y, z); scales: [N, 3] linear;
        opacities: [N]; colors: [N, 3] RGB or [N, K, 3] SH coefficients (``sh_degree`` set);
        cam_from_world: [4, 4] or [3, 4] world -> OpenCV camera; K: [3, 3] pixels;
        background: [3]; sh_degree: None or 0..3; near_plane: camera-z cull distance.

    Returns:
        ``rgb`` [H, W, 3], ``alpha`` [H, W], ``depth`` [H, W] (expected z), ``depth_accum``
        [H, W], ``means2d`` [N, 2] pixels (``.grad`` in pixels after backward), ``radii`` [N]
        int32, ``visible`` [N] bool, ``depths`` [N], ``conics`` [N, 3], ``colors`` None
        (gsplat does not return the evaluated colours).
    """
    dt = means.dtype
    view = torch.eye(4, device=means.device, dtype=dt)
    view = torch.cat([cam_from_world[:3].to(dt), view[3:]], dim=0)  # differentiable for pose refinement
    rc, ra, meta = _rasterization()(
        means, quats, scales, opacities, colors, view[None], K.to(dt)[None], width, height,
        near_plane=near_plane, eps2d=EPS2D, sh_degree=sh_degree, packed=False,
        backgrounds=background.to(dt)[None], render_mode="RGB+ED",
    )
    m2d_gs = meta["means2d"]  # [1, N, 2] pixels
    means2d = m2d_gs[0].detach().requires_grad_(m2d_gs.requires_grad)  # [N, 2]
    if m2d_gs.requires_grad:
        def _copy_grad(g: Tensor) -> None:  # accumulate like .retain_grad()
            means2d.grad = g[0].detach().clone() if means2d.grad is None else means2d.grad + g[0].detach()

        m2d_gs.register_hook(_copy_grad)
    radii_axes = meta["radii"][0]  # [N, 2] per axis in gsplat 1.5 ([N] in older versions)
    if radii_axes.dim() == 1:
        radii_axes = radii_axes[:, None]
    radii = radii_axes.amax(dim=-1).to(torch.int32)
    visible = (radii_axes > 0).all(dim=-1)
    alpha = ra[0, ..., 0]
    depth = rc[0, ..., 3]
    return {
        "rgb": rc[0, ..., :3],
        "alpha": alpha,
        "depth": depth,
        "depth_accum": depth * alpha,
        "means2d": means2d,
        "radii": torch.where(visible, radii, torch.zeros_like(radii)),
        "visible": visible,
        "depths": meta["depths"][0],
        "conics": meta["conics"][0],
        "colors": None,
    }
