"""Public differentiable Gaussian rasterizer: :func:`rasterize`.

Layers (gsplat style): this module checks inputs and runs the steps; projection
(:mod:`splat_train.render.projection`), SH colour (:mod:`splat_train.render.sh`) and the blending backends
(:mod:`splat_train.render.cpu.raster`, :mod:`splat_train.render._tiles`, :mod:`splat_train.render._reference`,
:mod:`splat_train.render._gsplat_backend`) are private building blocks.

Convention: ``cam_from_world`` maps world -> OpenCV camera (x right, y down, z forward); ``K``
maps camera points to pixel coordinates with the top-left pixel centre at (0.5, 0.5) (COLMAP).
Quaternions are (w, x, y, z). Output images are [H, W, ...] with row i = y.

Threads: the CPU kernel uses ``torch.get_num_threads()`` threads. On the shared 2-core
development machine (load ~7) one thread was 2-8x faster than two for the whole
forward+backward (torch's own intra-op threads suffer most); see benchmarks/bench_rasterizer.py.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from splat_train.render import _reference
from splat_train.render.projection import EPS2D, NEAR_PLANE, Projected, project_gaussians
from splat_train.render.sh import num_sh_bases, sh_concat, sh_to_color

__all__ = ["rasterize", "resolve_backend", "BACKENDS", "SKEW_ERROR"]

log = logging.getLogger(__name__)

BACKENDS = ("auto", "cpu", "torch", "reference", "gsplat")
SKEW_ERROR = "K must have zero skew (K[0, 1] == 0); undistort / re-fit the camera first"
_warned_cuda_fallback = False  # resolve_backend warns once per process


def _check(name: str, t: Tensor, shape: tuple) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """The backend that :func:`rasterize` runs for ``backend`` on tensors of ``device``.

    ``"auto"`` resolves to "cpu" on CPU when the C++ kernel builds (else "torch"), "gsplat" on
    CUDA when gsplat imports (else "torch", with a one-time warning: the pure-PyTorch tile
    code is many times slower there), "torch" elsewhere. Any other name is returned as is, but
    "cpu" (C++ kernels that read CPU memory) on another device raises ValueError.
    Callers that record which backend ran (the trainer's ``train.json``) resolve once with
    this function and pass the result to :func:`rasterize`.
    """
    global _warned_cuda_fallback
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    device = torch.device(device)
    if backend == "cpu" and device.type != "cpu":
        raise ValueError(f"backend {backend!r} runs on CPU tensors only, but the device is {device}; "
                         "use 'auto' (gsplat on CUDA), 'gsplat' or 'torch'")
    if backend != "auto":
        return backend
    if device.type == "cpu":
        from splat_train.render.cpu import raster as cpu_raster

        return "cpu" if cpu_raster.available() else "torch"
    if device.type == "cuda":
        from splat_train.render import _gsplat_backend

        if _gsplat_backend.available():
            return "gsplat"
        if not _warned_cuda_fallback:
            _warned_cuda_fallback = True
            log.warning("CUDA device but gsplat is not installed: the rasterizer falls back to the "
                        "pure-PyTorch tile backend ('torch'), many times slower; install it with "
                        "pip install -e '.[gpu]' (gsplat==%s)", _gsplat_backend.GSPLAT_VERSION)
        return "torch"
    return "torch"


def _fused_projection_ok(means: Tensor, cam_from_world: Tensor, K: Tensor, kernel_camera_grad: bool = False) -> bool:
    """Whether the "cpu" backend can use the fused C++ projection + SH: float32/float64 CPU
    tensors (resolve_backend has refused "cpu" on other devices), a K that needs no gradient,
    and a camera that needs none unless ``kernel_camera_grad`` (the kernel then differentiates
    it; training's pose refinement keeps the torch path)."""
    if means.dtype not in (torch.float32, torch.float64) or K.requires_grad:
        return False
    if cam_from_world.requires_grad and not kernel_camera_grad:
        return False
    from splat_train.render.cpu import project as cpu_project

    return cpu_project.available()


def blend(backend: str, proj: Projected, features: Tensor, opacities: Tensor) -> tuple[Tensor, Tensor]:
    """Front-to-back blend projected Gaussians with one backend ("cpu", "torch", "reference").

    Args:
        backend: the blending backend.
        proj: the screen-space Gaussians of one image (pixels, COLMAP convention).
        features: [N, F] per-Gaussian values to blend (colour, then depth).
        opacities: [N] in [0, 1], dtype of ``proj.means2d``.

    Returns:
        As :func:`splat_train.render._reference.blend_dense`: accum [H, W, F] (no background) and
        final transmittance [H, W].
    """
    if backend == "reference":
        return _reference.blend_dense(proj, features, opacities)
    if backend == "torch":
        from splat_train.render import _tiles

        return _tiles.blend_tiles(proj, features, opacities)
    if backend == "cpu":
        from splat_train.render.cpu import raster as cpu_raster

        return cpu_raster.blend_cpu(proj, features, opacities, kernel=backend)
    raise ValueError(f"blend backend must be 'cpu', 'torch' or 'reference', got {backend!r}")


def _check_zero_skew(K: Tensor) -> None:
    """Refuse K [3, 3] with K[0, 1] != 0, where reading it is free: for a CPU tensor. On a GPU
    the read would be a device sync per call; the trainer checks its cameras once, on the host."""
    if K.device.type == "cpu" and float(K[0, 1].detach()) != 0.0:
        raise ValueError(SKEW_ERROR)


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    cam_from_world: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    sh_degree: int | None = None,
    backend: str = "auto",
    near_plane: float = NEAR_PLANE,
    kernel_camera_grad: bool = False,
    depth: bool = True,
    stats: bool = True,
) -> dict[str, Tensor]:
    """Render Gaussians into one camera, differentiably (3DGS semantics, docs/reference.md section 3).

    Args:
        means: [N, 3] world-frame centres.
        quats: [N, 4] (w, x, y, z) rotations; need not be normalised (zero -> identity).
        scales: [N, 3] linear scales (not log).
        opacities: [N] in [0, 1] (already through the sigmoid).
        colors: [N, 3] RGB when ``sh_degree`` is None, else [N, K, 3] SH coefficients with
            K >= (sh_degree + 1) ** 2; colour = max(SH(view dir) + 0.5, 0), view direction
            from the camera centre to the mean. SH may also come as the pair (DC [N, 3],
            rest [N, K - 1, 3]) (the trainer's ``sh_dc`` / ``sh_rest``): the "cpu" backend's
            fused projection then reads both in place and writes their gradients directly
            (no [N, K, 3] concatenation, no copy of a slice's gradient); other paths
            concatenate them.
        cam_from_world: [4, 4] or [3, 4] world -> OpenCV camera.
        K: [3, 3] intrinsics in pixels of this image size (zero skew: checked when K is on the
            CPU; reading a GPU tensor would cost a device sync per call).
        width, height: image size in pixels.
        background: [3] RGB behind everything (default black).
        sh_degree: None for plain colours, else 0..3.
        backend: "auto" (CPU kernel on CPU when it builds, gsplat on CUDA when installed, else
            the vectorised tile code), "cpu" (fused C++ projection + SH when the camera
            needs no gradient, SIMD C++ blending), "torch", "reference" (dense, small scenes
            only) or "gsplat".
        near_plane: Gaussians with camera z below this are culled.
        kernel_camera_grad: with the "cpu" backend and a ``cam_from_world`` that requires grad
            (K must not), keep the fused C++ projection and let its backward give the camera's
            gradient (:mod:`splat_train.render.cpu.project`) instead of running the torch projection
            and SH over every Gaussian: the same gradient (float64 maths in both), an order of
            magnitude faster. The test-pose protocol sets it; training's pose refinement does not.
        depth: False lets a backend skip the depth outputs: gsplat then blends colour only and
            returns ``depth`` and ``depth_accum`` as None (the other backends blend depth with
            the colour at no extra pass and return them anyway).
        stats: False when nothing reads the densification statistics of this render
            (``means2d.grad`` and the 3DGS ``radii``): gsplat then returns ``radii`` as None
            and a ``means2d`` whose ``.grad`` stays None, and skips the ~20 small kernels per
            render that produce them (the other backends produce them with the projection
            at no extra cost and return them anyway).

    Returns:
        dict with
        ``rgb`` [H, W, 3] = sum_i w_i c_i + T_final * background,
        ``alpha`` [H, W] = 1 - T_final,
        ``depth`` [H, W] expected camera z of the rendered surface, normalised by alpha:
        ``depth_accum / max(alpha, 1e-10)`` (0 where nothing is rendered),
        ``depth_accum`` [H, W] = sum_i w_i z_i (not normalised),
        ``means2d`` [N, 2] projected centres in pixels (COLMAP convention); after
        ``backward()`` its ``.grad`` holds dL/d(means2d) in pixel units, [N, 2] for every
        backend (to compare with 3DGS's NDC-based densification threshold, multiply x by W/2
        and y by H/2, as :mod:`splat_train.strategy.densify` does),
        ``radii`` [N] int32 3DGS's 3-sigma screen radius in pixels
        (:func:`splat_train.render.projection.screen_radius`), 0 = culled, for every backend (gsplat's
        own opacity-aware per-axis radii are converted),
        ``visible`` [N] bool (= radii > 0),
        ``depths`` [N] camera z of the means, ``conics`` [N, 3], ``colors`` [N, 3] the
        evaluated per-Gaussian colours (None with gsplat).
    """
    _check("means", means, (None, 3))
    n = means.shape[0]
    _check("quats", quats, (n, 4))
    _check("scales", scales, (n, 3))
    _check("opacities", opacities, (n,))
    if not (isinstance(cam_from_world, Tensor) and cam_from_world.shape in ((4, 4), (3, 4))):
        raise ValueError(f"cam_from_world must be a [4, 4] or [3, 4] tensor, got {getattr(cam_from_world, 'shape', type(cam_from_world))}")
    _check("K", K, (3, 3))
    _check_zero_skew(K)
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    width, height = int(width), int(height)
    sh_pair = isinstance(colors, (tuple, list))
    if sh_degree is None:
        _check("colors", colors, (n, 3))
    else:
        if sh_pair:
            if len(colors) != 2:
                raise ValueError(f"colors as SH (dc, rest) must be a pair, got {len(colors)} tensors")
            _check("colors[0] (SH DC terms)", colors[0], (n, 3))
            _check("colors[1] (SH rest)", colors[1], (n, None, 3))
            k = 1 + colors[1].shape[1]
        else:
            _check("colors (SH coefficients)", colors, (n, None, 3))
            k = colors.shape[1]
        if k < num_sh_bases(sh_degree):
            raise ValueError(
                f"sh_degree={sh_degree} needs >= {num_sh_bases(sh_degree)} SH coefficients per "
                f"Gaussian, got {k}; lower sh_degree or pass [N, 16, 3] coefficients"
            )
    dev, dt = means.device, means.dtype
    if background is None:
        background = torch.zeros(3, device=dev, dtype=dt)
    _check("background", background, (3,))
    which = resolve_backend(backend, dev)
    fused = which == "cpu" and _fused_projection_ok(means, cam_from_world, K, kernel_camera_grad)
    if sh_pair and not fused:  # the fused projection reads the pair in place; the rest want one tensor
        colors = sh_concat(*colors, sh_degree)

    if which == "gsplat":
        from splat_train.render import _gsplat_backend

        return _gsplat_backend.rasterize_gsplat(
            means, quats, scales, opacities, colors, cam_from_world, K, width, height,
            background, sh_degree, near_plane, depth=depth, stats=stats,
        )

    if fused:
        from splat_train.render.cpu import project as cpu_project

        proj, rgb_g, feat = cpu_project.project_sh_cpu(
            means, quats, scales, colors, sh_degree, cam_from_world, K, width, height, near_plane, EPS2D,
            camera_grad=kernel_camera_grad)
        # with SH the kernel's (colour, depth) rows are the blend's features as they are
        features = feat if sh_degree is not None else None
    else:
        features = None
        proj = project_gaussians(means, quats, scales, cam_from_world, K, width, height, near=near_plane, eps2d=EPS2D)
        if sh_degree is None:
            rgb_g = colors
        else:
            cw = cam_from_world.to(dt)
            cam_center = -cw[:3, :3].T @ cw[:3, 3]
            rgb_g = sh_to_color(sh_degree, colors, means, cam_center)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    if features is None:
        features = torch.cat([rgb_g.to(dt), proj.depths[:, None]], dim=1)
    accum, t_final = blend(which, proj, features, opacities.to(dt))
    alpha = 1.0 - t_final
    if background.device.type == "cpu" and not background.requires_grad and not bool(background.any()):
        # black (the trainer's default): the same values as the sum below, in one copy instead
        # of a multiply and an add over the image, and no zero product in t_final's gradient
        rgb = accum[..., :3].contiguous()
    else:
        rgb = accum[..., :3] + t_final[..., None] * background.to(dt)
    depth_accum = accum[..., 3]
    depth = depth_accum / alpha.clamp_min(1e-10)
    return {
        "rgb": rgb,
        "alpha": alpha,
        "depth": depth,
        "depth_accum": depth_accum,
        "means2d": means2d,
        "radii": proj.radii,
        "visible": proj.visible,
        "depths": proj.depths,
        "conics": proj.conics,
        "colors": rgb_g,
    }
