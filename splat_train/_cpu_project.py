"""Fused EWA projection + SH colour in C++ (``_cpu_project.cpp``), forward and backward.

The CPU twin of :func:`splat_train.projection.project_gaussians` followed by
:func:`splat_train.sh.sh_to_color`, which stay the reference (tests/test_raster_project.py
compares values and gradients in float64). One C pass per Gaussian replaces some hundred torch
ops and their autograd graph: at 100k Gaussians that graph cost ~1.3 us per Gaussian per
iteration (benchmarks/profile_rasterizer.py).

Only for leaf-free cameras: when ``cam_from_world`` or ``K`` requires grad (pose refinement)
the caller must use the torch path, which differentiates through the camera.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from splat_train._cpu_build import KERNEL_REGISTRY as _KERNELS
from splat_train._cpu_build import Kernel as _Kernel
from splat_train._cpu_build import ptr as _ptr
from splat_train._cpu_build import run_threaded as _run_threaded
from splat_train._cpu_build import suffix as _suffix
from splat_train.projection import TILE_SIZE, Projected

__all__ = ["available", "project_sh_cpu"]


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    for dt in ("f32", "f64"):
        f = getattr(lib, f"splat_project_forward_{dt}")
        f.argtypes = [i64, vp, vp, vp, vp, i64, i64, vp, i64] + [vp] * 9
        f.restype = None
        b = getattr(lib, f"splat_project_backward_{dt}")
        b.argtypes = [i64, vp, vp, vp, vp, i64, i64] + [vp] * 10
        b.restype = None
    return lib


_KERNELS.setdefault("project", _Kernel("project", "_cpu_project.cpp", 1, True, "splat_project_abi_version", _declare))


def available() -> bool:
    """True when the projection kernel is built and loaded."""
    return _KERNELS["project"].load() is not None


def _camera_block(cam_from_world: Tensor, K: Tensor, width: int, height: int, near: float, eps2d: float) -> Tensor:
    """[23] float64: R (row-major), t, fx, fy, cx, cy, near, eps2d, camera centre, W, H."""
    cw = cam_from_world.detach().to(torch.float64)
    k = K.detach().to(torch.float64)
    R, t = cw[:3, :3], cw[:3, 3]
    centre = -R.T @ t
    return torch.cat([
        R.reshape(-1), t, torch.stack([k[0, 0], k[1, 1], k[0, 2], k[1, 2]]),
        torch.tensor([near, eps2d], dtype=torch.float64), centre,
        torch.tensor([float(width), float(height)], dtype=torch.float64),
    ]).contiguous()


class _ProjectSH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, sh, cam, sh_degree, width, height):
        lib = _KERNELS["project"].load()
        dt = means.dtype
        sfx = _suffix(dt)
        m, q, s = (t.detach().to(dt).contiguous() for t in (means, quats, scales))
        n = m.shape[0]
        deg = -1 if sh_degree is None else int(sh_degree)
        shc = sh.detach().to(dt).contiguous() if deg >= 0 else m.new_zeros(0)
        sh_k = shc.shape[1] if deg >= 0 else 0
        means2d, conics, cov2d = m.new_empty(n, 2), m.new_empty(n, 3), m.new_empty(n, 3)
        depths, colors = m.new_empty(n), (m.new_empty(n, 3) if deg >= 0 else m.new_zeros(n, 3))
        radii = torch.empty(n, dtype=torch.int32)
        rect = torch.empty(n, 4, dtype=torch.int64)
        visible = torch.empty(n, dtype=torch.bool)
        _run_threaded(getattr(lib, f"splat_project_forward_{sfx}"), n, _ptr(cam), _ptr(m), _ptr(q), _ptr(s), deg,
                      sh_k, _ptr(shc), TILE_SIZE, _ptr(means2d), _ptr(conics), _ptr(cov2d), _ptr(depths),
                      _ptr(radii), _ptr(rect), _ptr(visible), _ptr(colors))
        ctx.save_for_backward(m, q, s, shc, cam)
        ctx.deg = deg
        ctx.mark_non_differentiable(cov2d, radii, rect, visible)
        return means2d, conics, depths, colors, cov2d, radii, rect, visible

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_colors, *_):
        m, q, s, shc, cam = ctx.saved_tensors
        lib = _KERNELS["project"].load()
        dt, n = m.dtype, m.shape[0]

        def prep(v, *shape):
            return torch.zeros(*shape, dtype=dt) if v is None else v.to(dt).contiguous()

        v_means2d, v_conics, v_depths, v_colors = (prep(v_means2d, n, 2), prep(v_conics, n, 3),
                                                   prep(v_depths, n), prep(v_colors, n, 3))
        v_m, v_q, v_s = torch.empty_like(m), torch.empty_like(q), torch.empty_like(s)
        v_sh = torch.empty_like(shc)
        _run_threaded(getattr(lib, f"splat_project_backward_{_suffix(dt)}"), n, _ptr(cam), _ptr(m), _ptr(q),
                      _ptr(s), ctx.deg, shc.shape[1] if ctx.deg >= 0 else 0, _ptr(shc), _ptr(v_means2d),
                      _ptr(v_conics), _ptr(v_depths), _ptr(v_colors), _ptr(v_m), _ptr(v_q), _ptr(v_s), _ptr(v_sh))
        return v_m, v_q, v_s, (v_sh if ctx.deg >= 0 else None), None, None, None, None


def project_sh_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    colors: Tensor,
    sh_degree: int | None,
    cam_from_world: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    eps2d: float,
) -> tuple[Projected, Tensor]:
    """Projection and per-Gaussian colour in one C pass (CPU tensors, float32 or float64).

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3]: world-frame Gaussians.
        colors: [N, 3] RGB when ``sh_degree`` is None (returned as is), else [N, K, 3] SH
            coefficients (K >= (sh_degree + 1) ** 2).
        cam_from_world: [4, 4] or [3, 4] world -> OpenCV camera (no gradient: see module doc).
        K: [3, 3] intrinsics; width, height: image size; near, eps2d as in
            :func:`splat_train.projection.project_gaussians`.

    Returns:
        (:class:`splat_train.projection.Projected`, colours [N, 3]), the values of
        ``project_gaussians`` and ``sh_to_color`` (float64 maths) with their gradients.
    """
    if cam_from_world.requires_grad or K.requires_grad:
        raise ValueError("project_sh_cpu does not differentiate the camera; use project_gaussians for pose refinement")
    cam = _camera_block(cam_from_world, K, width, height, near, eps2d)
    sh = colors if sh_degree is not None else None
    means2d, conics, depths, rgb, cov2d, radii, rect, visible = _ProjectSH.apply(
        means, quats, scales, sh, cam, sh_degree, int(width), int(height))
    proj = Projected(means2d=means2d, conics=conics, cov2d=cov2d, depths=depths, radii=radii, rect=rect,
                     visible=visible)
    return proj, (colors if sh_degree is None else rgb)
