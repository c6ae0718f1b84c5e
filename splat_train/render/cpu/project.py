"""Fused EWA projection + SH colour in C++ (``project.cpp``), forward and backward.

The CPU twin of :func:`splat_train.render.projection.project_gaussians` followed by
:func:`splat_train.render.sh.sh_to_color`, which stay the reference (tests/test_raster_project.py
compares values and gradients in float64). One C pass per Gaussian replaces some hundred torch
ops and their autograd graph: at 100k Gaussians that graph cost ~1.3 us per Gaussian per
iteration (benchmarks/profile_rasterizer.py).

The camera: ``K`` gets no gradient (focal refinement uses the torch path). ``cam_from_world``
gets one only when asked (``camera_grad=True``; the test-pose protocol, :mod:`splat_train.testpose`):
the backward then also sums, per chunk of 1024 Gaussians, dL/dR and dL/dt of the
world -> camera transform through the camera-frame means, the covariance's ``J R`` and the SH
view direction's camera centre, the same chain autograd runs through the torch code (float64
maths; tests/test_train_testpose.py checks it against that code and against finite
differences). Called without it on a camera that requires grad, :func:`project_sh_cpu` raises,
and the caller uses the torch path (training's pose refinement does).

SH coefficients come as one [N, K, 3] tensor or as the pair (DC [N, 3], rest [N, K - 1, 3]),
the trainer's ``sh_dc`` / ``sh_rest``, read in place with their gradients written directly
(no per-iteration concatenation and slice-gradient copy).
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from splat_train.render.cpu.build import KERNEL_REGISTRY as _KERNELS
from splat_train.render.cpu.build import Kernel as _Kernel
from splat_train.render.cpu.build import ptr as _ptr
from splat_train.render.cpu.build import run_threaded as _run_threaded
from splat_train.render.cpu.build import suffix as _suffix
from splat_train.render.projection import TILE_SIZE, Projected
from splat_train.render.sh import num_sh_bases

__all__ = ["available", "project_sh_cpu"]


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    sh = [i64, vp, i64, vp, i64, i64]  # sh_deg, dc, dc_stride, rest, rest_stride, rest_k
    for dt in ("f32", "f64"):
        f = getattr(lib, f"splat_project_forward_{dt}")
        f.argtypes = [i64, vp, vp, vp, vp] + sh + [i64] + [vp] * 8
        f.restype = None
        b = getattr(lib, f"splat_project_backward_{dt}")
        b.argtypes = [i64, vp, vp, vp, vp] + sh + [vp, i64] * 3 + [vp] * 7
        b.restype = None
        c = getattr(lib, f"splat_project_camgrad_{dt}")
        c.argtypes = [i64, vp, vp, vp, vp, vp] + sh + [vp, i64] * 3 + [vp] * 2
        c.restype = None
    return lib


_KERNELS.setdefault("project", _Kernel("project", "project.cpp", 4, True, "splat_project_abi_version", _declare))
_CHUNK = 1024  # Gaussians per work item of the kernel (CHUNK in project.cpp): one camera-gradient row each


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


def _sh_layout(dc: Tensor, rest: Tensor | None) -> tuple[Tensor, int, Tensor, int, int]:
    """(dc, dc_stride, rest, rest_stride, rest_k) for the kernel's SH arguments: ``rest`` None
    means ``dc`` is one [N, K, 3] tensor (DC at column 0, the rest after it)."""
    if rest is None:
        k = dc.shape[1]
        return dc, 3 * k, dc, 3 * k, k - 1
    return dc, 3, rest, 3 * rest.shape[1], rest.shape[1]


def _sh_ptrs(dc: Tensor, rest: Tensor | None) -> list:
    dc, dcs, rest_t, rs, rk = _sh_layout(dc, rest)
    elt = dc.element_size()
    # one [N, K, 3] tensor: the rest starts 3 values after its DC term
    rp = _ptr(rest_t) + (3 * elt if rest is None else 0) if rk > 0 else None
    return [_ptr(dc), dcs, rp, rs, rk]


def _rows(v: Tensor | None, dt: torch.dtype, n: int, width: int) -> tuple[Tensor, int]:
    """A cotangent [n, width] as (tensor, row stride in elements) for the kernel: read in place
    when its rows are dense (e.g. the columns of the blend backward's [N, 6 + F] gradient),
    else a contiguous copy; zeros for None."""
    if v is None:
        return torch.zeros(n, width, dtype=dt), width
    if v.dtype != dt or v.shape != (n, width) or v.stride(1) != 1:
        v = v.to(dt).contiguous()
    return v, v.stride(0)


class _ProjectSH(torch.autograd.Function):
    """``sh_dc``: [N, K, 3] coefficients with ``sh_rest`` None, or [N, 3] DC terms with
    ``sh_rest`` [N, K - 1, 3] the other coefficients (gradients then land in two contiguous
    tensors of those shapes: no concatenation, no copy of a slice's gradient).

    Outputs means2d [N, 2], conics [N, 3], feat [N, 4] = (r, g, b, depth) (colour 0 without
    SH; the blend's feature rows as they are, no concatenation), then the non-differentiable
    cov2d, radii, rect, visible.

    ``cam_from_world``: the [4, 4] / [3, 4] tensor ``cam`` was made from, or None; given, it
    receives dL/d(cam_from_world) (rows 0-2; a [4, 4]'s last row gets zeros)."""

    @staticmethod
    def forward(ctx, means, quats, scales, sh_dc, sh_rest, cam, sh_degree, width, height, cam_from_world=None):
        lib = _KERNELS["project"].load()
        dt = means.dtype
        sfx = _suffix(dt)
        m, q, s = (t.detach().to(dt).contiguous() for t in (means, quats, scales))
        n = m.shape[0]
        deg = -1 if sh_degree is None else int(sh_degree)
        dc = sh_dc.detach().to(dt).contiguous() if deg >= 0 else m.new_zeros(0)
        rest = sh_rest.detach().to(dt).contiguous() if deg >= 0 and sh_rest is not None else None
        shp = _sh_ptrs(dc, rest) if deg >= 0 else [None, 0, None, 0, 0]
        means2d, conics, cov2d, feat = m.new_empty(n, 2), m.new_empty(n, 3), m.new_empty(n, 3), m.new_empty(n, 4)
        radii = torch.empty(n, dtype=torch.int32)
        rect = torch.empty(n, 4, dtype=torch.int64)
        visible = torch.empty(n, dtype=torch.bool)
        _run_threaded(getattr(lib, f"splat_project_forward_{sfx}"), n, _ptr(cam), _ptr(m), _ptr(q), _ptr(s), deg,
                      *shp, TILE_SIZE, _ptr(means2d), _ptr(conics), _ptr(cov2d), _ptr(feat),
                      _ptr(radii), _ptr(rect), _ptr(visible))
        ctx.save_for_backward(m, q, s, dc, rest, cam)
        ctx.deg = deg
        ctx.cw_meta = None if cam_from_world is None else (cam_from_world.shape, cam_from_world.dtype)
        ctx.set_materialize_grads(False)  # no zero tensors for unused outputs (None handled)
        ctx.mark_non_differentiable(cov2d, radii, rect, visible)
        return means2d, conics, feat, cov2d, radii, rect, visible

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_feat, *_):
        m, q, s, dc, rest, cam = ctx.saved_tensors
        lib = _KERNELS["project"].load()
        dt, n, deg = m.dtype, m.shape[0], ctx.deg
        cots = [_rows(v, dt, n, w) for v, w in ((v_means2d, 2), (v_conics, 3), (v_feat, 4))]
        gauss = any(ctx.needs_input_grad[:5])
        want_cam = ctx.cw_meta is not None and ctx.needs_input_grad[9]
        shp = _sh_ptrs(dc, rest) if deg >= 0 else [None, 0, None, 0, 0]
        cot_ptrs = [x for t, st in cots for x in (_ptr(t), st)]
        sfx = _suffix(dt)
        v_m = v_q = v_s = v_dc = v_rest = v_cam = None
        if gauss:
            v_m, v_q, v_s, v_dc = (torch.empty(t.shape, dtype=t.dtype) for t in (m, q, s, dc))
            v_rest = torch.empty(rest.shape, dtype=rest.dtype) if rest is not None else None
            vsh = [None, None]
            if deg >= 0:
                vshp = _sh_ptrs(v_dc, v_rest)
                vsh = [vshp[0], vshp[2]]  # same layout as the coefficients
            if want_cam:
                v_cam = torch.zeros(max(1, (n + _CHUNK - 1) // _CHUNK), 12, dtype=torch.float64)
            _run_threaded(getattr(lib, f"splat_project_backward_{sfx}"), n, _ptr(cam), _ptr(m), _ptr(q),
                          _ptr(s), deg, *shp, *cot_ptrs, _ptr(v_m), _ptr(v_q), _ptr(v_s), *vsh,
                          None if v_cam is None else _ptr(v_cam))
        elif want_cam:
            # the Gaussians frozen: the camera's gradient alone, over the Gaussians whose
            # cotangent rows are not all zero (the blend gives zero rows to every Gaussian it did
            # not reach: about half of them, culled or behind the last contributor; a zero row
            # adds exactly nothing to the sum)
            live = cots[0][0].ne(0).any(1) | cots[1][0].ne(0).any(1) | cots[2][0].ne(0).any(1)
            idx = live.nonzero().view(-1)
            k = idx.numel()
            v_cam = torch.zeros(max(1, (k + _CHUNK - 1) // _CHUNK), 12, dtype=torch.float64)
            _run_threaded(getattr(lib, f"splat_project_camgrad_{sfx}"), k, _ptr(idx), _ptr(cam), _ptr(m), _ptr(q),
                          _ptr(s), deg, *shp, *cot_ptrs, _ptr(v_cam))
        v_cw = None
        if v_cam is not None:
            shape, cw_dt = ctx.cw_meta
            g = v_cam.sum(0)  # chunk rows in order (one serial sum: no thread dependence)
            v_cw = torch.zeros(shape, dtype=torch.float64)
            v_cw[:3, :3] = g[:9].view(3, 3)
            v_cw[:3, 3] = g[9:]
            v_cw = v_cw.to(cw_dt)
        if deg < 0:
            v_dc = v_rest = None
        return v_m, v_q, v_s, v_dc, v_rest, None, None, None, None, v_cw


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
    camera_grad: bool = False,
) -> tuple[Projected, Tensor, Tensor]:
    """Projection and per-Gaussian colour in one C pass (CPU tensors, float32 or float64).

    Args:
        means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3]: world-frame Gaussians.
        colors: [N, 3] RGB when ``sh_degree`` is None (returned as is), else [N, K, 3] SH
            coefficients (K >= (sh_degree + 1) ** 2) or the pair (DC [N, 3], rest [N, K - 1, 3]),
            e.g. the trainer's ``sh_dc`` and ``sh_rest`` parameters: read in place and given
            their gradients directly, with no [N, K, 3] concatenation per call.
        cam_from_world: [4, 4] or [3, 4] world -> OpenCV camera.
        K: [3, 3] intrinsics (no gradient); width, height: image size; near, eps2d as in
            :func:`splat_train.render.projection.project_gaussians`.
        camera_grad: differentiate ``cam_from_world`` too (when it requires grad; module doc).
            False refuses a camera that requires grad.

    Returns:
        (:class:`splat_train.render.projection.Projected`, colours [N, 3], feat [N, 4]): the values of
        ``project_gaussians`` and ``sh_to_color`` (float64 maths) with their gradients; feat
        is (colour, depth) per row, the blend's features with no concatenation (colour 0 when
        ``sh_degree`` is None); ``Projected.depths`` and the SH colours are its columns.
    """
    if K.requires_grad or (cam_from_world.requires_grad and not camera_grad):
        raise ValueError("project_sh_cpu differentiates the pose only with camera_grad=True and never K; "
                         "use project_gaussians for pose refinement or focal refinement")
    cam = _camera_block(cam_from_world, K, width, height, near, eps2d)
    sh_dc = sh_rest = None
    if sh_degree is not None:
        sh_dc, sh_rest = colors if isinstance(colors, (tuple, list)) else (colors, None)
        k = sh_dc.shape[1] if sh_rest is None else 1 + sh_rest.shape[1]
        if k < num_sh_bases(sh_degree):
            raise ValueError(f"sh_degree={sh_degree} needs {num_sh_bases(sh_degree)} SH coefficients, got {k}")
    cw = cam_from_world if camera_grad and cam_from_world.requires_grad else None
    means2d, conics, feat, cov2d, radii, rect, visible = _ProjectSH.apply(
        means, quats, scales, sh_dc, sh_rest, cam, sh_degree, int(width), int(height), cw)
    proj = Projected(means2d=means2d, conics=conics, cov2d=cov2d, depths=feat[:, 3], radii=radii, rect=rect,
                     visible=visible, width=int(width), height=int(height), tile_size=TILE_SIZE)
    return proj, (colors if sh_degree is None else feat[:, :3]), feat
