"""Optional gsplat backend (CUDA): maps :func:`splat_train.rasterize` onto ``gsplat.rasterization``.

Used by :func:`splat_train.rasterize` with ``backend="gsplat"``, or ``"auto"`` on CUDA tensors
when gsplat imports (``pip install -e ".[gpu]"`` pins the version this was written against,
:data:`GSPLAT_VERSION`). The mapping (checked on CPU by tests/test_raster_gsplat.py, with
gsplat's own pure-PyTorch projection and SH and our dense compositing standing in for its
CUDA kernels):

* ``viewmats`` [1, 4, 4] = ``cam_from_world`` padded to 4x4 (world -> OpenCV camera, as ours);
  ``Ks`` [1, 3, 3] = ``K`` (both use pixel centres at +0.5, COLMAP);
* ``eps2d`` = :data:`splat_train.render.projection.EPS2D`, ``near_plane`` passed through,
  ``sh_degree`` passed through (None = plain colours), ``packed=False``, ``render_mode="RGB+ED"``;
* returned ``means2d`` is [N, 2] in pixels and its ``.grad`` after ``backward()`` is
  dL/d(means2d) in pixels, the units :meth:`splat_train.strategy.densify.DensifyStrategy.update_state`
  expects (gsplat's own meta["means2d"] is [1, N, 2]; a hook copies its gradient);
* ``visible`` = gsplat's own mask (both per-axis radii > 0); ``radii`` [N] int32 = 3DGS's
  ceil(3 sqrt(lambda_max)) (:func:`splat_train.render.projection.screen_radius`) of the 2D
  covariance recovered from gsplat's conics, 0 where not visible. gsplat's own radii are
  per axis and opacity-aware (``rasterization`` passes the opacities to its projection:
  ceil(min(3.33, sqrt(2 ln(255 opacity))) sqrt(Sigma_axis)), ProjectionEWA3DGSFused.cu), so
  after an opacity reset to 0.01 they are ~2.4x smaller and the densification's screen-size
  prune (radius > 20 px) would almost never fire; the 3DGS radius keeps that prune as the
  paper and the CPU backends have it. In float32 the round trip through the conic can move
  a radius that lies within rounding of an integer by one pixel;
* ``opacities`` are passed clamped at :data:`OPACITY_MAX` = 0.99 (:func:`clamp_opacities`):
  gsplat's kernels clamp each Gaussian's alpha at 0.999, 3DGS and our CPU backends at 0.99
  (:data:`splat_train.render._reference.ALPHA_MAX`), so without it a Gaussian whose opacity passes 0.99
  (a sigmoid near 1 with no opacity reset, or dropout's survivors scaled by 1 / (1 - p)) would
  hide what lies behind it ten times more than in 3DGS. Measured on the CPU kernel built with
  gsplat's 0.999 (``benchmarks/backend_semantics.py``, fern n = 3 grid cell, ``sparse``, 3,000
  iterations): held-out PSNR 0.73 dB lower over 15 seeds, and 0.11 dB lower with this clamp
  (8 seeds), against the CPU kernel as it is. Where a Gaussian's opacity exceeds 0.99, its alpha
  away from the centre is 0.99 G here against min(0.99, opacity G) in 3DGS; at the centre both
  are 0.99.

Known differences from our backends (gsplat's semantics, not mapping errors): gsplat culls a
Gaussian of opacity < 1/255 in its projection (not visible, so not counted in the
densification's visibility count; it blends nothing in either backend; measured, it does not
move the trained model: 15 seeds, -0.04 ± 0.15 dB); its tile footprint is the opacity-aware
one above. The H100 run (benchmarks/README.md) measured the resulting image and gradient
differences.
"""

from __future__ import annotations

import functools
import importlib.metadata

import torch
from torch import Tensor

from splat_train.render._reference import ALPHA_MAX
from splat_train.render.projection import EPS2D, screen_radius

__all__ = ["GSPLAT_VERSION", "OPACITY_MAX", "available", "clamp_opacities", "installed_version", "rasterize_gsplat"]

# The largest opacity passed to gsplat: 3DGS's alpha clamp (module docstring).
OPACITY_MAX = ALPHA_MAX

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


def clamp_opacities(opacities: Tensor) -> Tensor:
    """[N] opacities (after the sigmoid and any training map) -> clamped at :data:`OPACITY_MAX`,
    so that gsplat's alpha (its kernels clamp at 0.999) never passes 3DGS's 0.99; no gradient
    above the clamp, as where 3DGS's alpha clamp binds."""
    return opacities.clamp_max(OPACITY_MAX)


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
    depth: bool = True,
    stats: bool = True,
) -> dict[str, Tensor]:
    """Render with gsplat; arguments, shapes and result keys as :func:`splat_train.rasterize`.

    Args:
        means: [N, 3] world frame; quats: [N, 4] (w, x, y, z); scales: [N, 3] linear;
        opacities: [N]; colors: [N, 3] RGB or [N, K, 3] SH coefficients (``sh_degree`` set);
        cam_from_world: [4, 4] or [3, 4] world -> OpenCV camera; K: [3, 3] pixels;
        background: [3]; sh_degree: None or 0..3; near_plane: camera-z cull distance.
        depth: False renders colour only (``render_mode="RGB"``): ``depth`` and
            ``depth_accum`` are then None.
        stats: False skips the densification statistics: ``radii`` is None, ``visible`` is
            gsplat's own mask, and ``means2d`` gets no gradient.

    Returns:
        ``rgb`` [H, W, 3], ``alpha`` [H, W], ``depth`` [H, W] (expected z), ``depth_accum``
        [H, W], ``means2d`` [N, 2] pixels (``.grad`` in pixels after backward), ``radii`` [N]
        int32 (None without ``stats``), ``visible`` [N] bool, ``depths`` [N], ``conics``
        [N, 3], ``colors`` None (gsplat does not return the evaluated colours).
    """
    dt = means.dtype
    if cam_from_world.shape == (4, 4):  # the trainer's cameras (differentiable with pose refinement)
        view = cam_from_world.to(dt)
    else:
        view = torch.cat([cam_from_world[:3].to(dt), torch.eye(4, device=means.device, dtype=dt)[3:]], dim=0)
    rc, ra, meta = _rasterization()(
        means, quats, scales, clamp_opacities(opacities), colors, view[None], K.to(dt)[None], width, height,
        near_plane=near_plane, eps2d=EPS2D, sh_degree=sh_degree, packed=False,
        backgrounds=background.to(dt)[None], render_mode="RGB+ED" if depth else "RGB",
    )
    m2d_gs = meta["means2d"]  # [1, N, 2] pixels
    want_grad = stats and m2d_gs.requires_grad
    means2d = m2d_gs[0].detach().requires_grad_(want_grad)  # [N, 2]
    if want_grad:
        def _copy_grad(g: Tensor) -> None:  # accumulate like .retain_grad()
            means2d.grad = g[0].detach().clone() if means2d.grad is None else means2d.grad + g[0].detach()

        m2d_gs.register_hook(_copy_grad)
    radii_axes = meta["radii"][0]  # [N, 2] per axis in gsplat 1.5 ([N] in older versions)
    if radii_axes.dim() == 1:
        radii_axes = radii_axes[:, None]
    visible = (radii_axes > 0).all(dim=-1)
    radii = None
    if stats:
        radii, visible = _radii_3dgs(meta["conics"][0], visible)
    alpha = ra[0, ..., 0]
    z = rc[0, ..., 3] if depth else None
    return {
        "rgb": rc[0, ..., :3],
        "alpha": alpha,
        "depth": z,
        "depth_accum": z * alpha if depth else None,
        "means2d": means2d,
        "radii": radii,
        "visible": visible,
        "depths": meta["depths"][0],
        "conics": meta["conics"][0],
        "colors": None,
    }


@torch.no_grad()
def _radii_3dgs(conics: Tensor, visible: Tensor) -> tuple[Tensor, Tensor]:
    """3DGS radii from gsplat's conics.

    Args:
        conics: [N, 3] (A, B, C) of the inverse dilated 2D covariance [[A, B], [B, C]], pixels^-2.
        visible: [N] bool; other rows may hold anything (gsplat leaves them unwritten).

    Returns:
        radii [N] int32: :func:`splat_train.render.projection.screen_radius` of the covariance
        [[C, -B], [-B, A]] / d, d = A C - B^2 (its determinant is 1 / d), computed in float64,
        0 where not visible; visible [N] bool: ``visible`` less the rows whose conic is
        degenerate (d not finite and > 0).
    """
    A, B, C = conics.double().unbind(-1)
    det = A * C - B * B
    ok = visible & (det > 0) & (det < float("inf"))
    inv_det = torch.where(ok, det, 1.0).reciprocal()  # the covariance's determinant
    r = screen_radius(C * inv_det, None, A * inv_det, det=inv_det)
    return torch.where(ok, r, 0.0).clamp(max=2**30).to(torch.int32), ok
