"""The SSIM term of the training loss in C++ (``ssim.cpp``): separable filtering, forward
and hand-written backward.

CPU twin of :func:`splat_train.losses.ssim` (mean reduction, gradient for the first image only),
which stays the reference and the evaluation metric. On the CPU five grouped 11 x 11
``conv2d`` calls and their backward dominate a training iteration with few Gaussians; here the
separable filter runs row then column, the row pass vectorised across x (zero-padded rows,
taps outer), work items are (channel, band of rows) so that every core is busy on 3 channels,
each filter output is summed in registers over the taps, and the map's and L1's sums run in
eight double lanes. Timings: ``python -m benchmarks`` (benchmarks/README.md).
tests/test_train_losses.py compares value and gradient with the reference in float64.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from imgmetrics.ssim import gaussian_window_1d
from splat_train.render.cpu.build import KERNEL_REGISTRY as _KERNELS
from splat_train.render.cpu.build import Kernel as _Kernel
from splat_train.render.cpu.build import ptr as _ptr
from splat_train.render.cpu.build import run_threaded as _run_threaded
from splat_train.render.cpu.build import suffix as _suffix

__all__ = ["available", "ssim_cpu", "l1_ssim_cpu"]


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    for dt in ("f32", "f64"):
        getattr(lib, f"splat_ssim_forward_{dt}").argtypes = [i64] * 5 + [vp] * 3 + [i64] * 3 + [vp] * 4
        getattr(lib, f"splat_ssim_forward_{dt}").restype = None
        getattr(lib, f"splat_ssim_backward_{dt}").argtypes = [i64] * 5 + [vp] * 3 + [i64] * 3 + [vp, f64, f64, vp, vp]
        getattr(lib, f"splat_ssim_backward_{dt}").restype = None
    return lib


_KERNELS.setdefault("ssim", _Kernel("ssim", "ssim.cpp", 3, True, "splat_ssim_abi_version", _declare))


# Rows per work item (items are channel x band): 64 keeps the row pass's halo (the 2 x 5 rows
# above and below a band that its column pass reads) at ~16 % extra while a 3-channel 372-row
# image still gives 18 items to share between the cores.
BAND_ROWS = 64


def available() -> bool:
    """True when the SSIM kernel is built and loaded."""
    return _KERNELS["ssim"].load() is not None


def _planes(img: Tensor, layout: str) -> tuple[Tensor, int, int, int, tuple[int, int, int]]:
    """(contiguous image, planes, H, W, element strides (plane, row, column)) of a [B, C, H, W]
    ("bchw") or [H, W, C] ("hwc") image."""
    img = img.contiguous()
    if layout == "hwc":
        H, W, C = img.shape
        return img, C, H, W, (1, W * C, C)
    B, C, H, W = img.shape
    return img, B * C, H, W, (H * W, W, 1)


class _SSIML1CPU(torch.autograd.Function):
    """(mean |a - b|, mean SSIM(a, b)) of two images of one layout, gradients for ``a`` only."""

    @staticmethod
    def forward(ctx, a, b, layout, window_size, sigma):
        lib = _KERNELS["ssim"].load()
        dt = a.dtype
        a_, nc, H, W, st = _planes(a.detach(), layout)
        b_ = _planes(b.detach().to(dt), layout)[0]
        g = gaussian_window_1d(window_size, sigma, dtype=dt).contiguous()
        m = torch.empty(nc, 5, H, W, dtype=dt)
        items = nc * -(-H // BAND_ROWS)
        sums = torch.empty(2, items, dtype=torch.float64)  # per item: SSIM map sum, |a - b| sum
        _run_threaded(getattr(lib, f"splat_ssim_forward_{_suffix(dt)}"), nc, H, W, window_size, BAND_ROWS, _ptr(g),
                      _ptr(a_), _ptr(b_), *st, _ptr(m), _ptr(sums[0]), _ptr(sums[1]))
        ctx.save_for_backward(a_, b_, m, g)
        ctx.dims = (nc, H, W, window_size, st)
        ctx.set_materialize_grads(False)
        total = sums.sum(1) / (nc * H * W)
        return total[1].to(dt), total[0].to(dt)

    @staticmethod
    def backward(ctx, v_l1, v_s):
        a_, b_, m, g = ctx.saved_tensors
        nc, H, W, ws, st = ctx.dims
        n = nc * H * W
        lib = _KERNELS["ssim"].load()
        da = torch.empty_like(a_)
        w = 0.0 if v_s is None else float(v_s) / n
        wl1 = 0.0 if v_l1 is None else float(v_l1) / n
        _run_threaded(getattr(lib, f"splat_ssim_backward_{_suffix(a_.dtype)}"), nc, H, W, ws, BAND_ROWS, _ptr(g),
                      _ptr(a_), _ptr(b_), *st, _ptr(m), w, wl1, _ptr(da))
        return da, None, None, None, None


def _check(img1: Tensor, img2: Tensor, dims: int, window_size: int) -> None:
    if img1.shape != img2.shape or img1.dim() != dims:
        want = "[B, C, H, W]" if dims == 4 else "[H, W, C]"
        raise ValueError(f"need two {want} images of one shape, got {tuple(img1.shape)} and {tuple(img2.shape)}")
    if img2.requires_grad:
        raise ValueError("the CPU SSIM differentiates img1 only; img2 must not require grad")
    if window_size % 2 != 1:
        raise ValueError(f"window_size must be odd, got {window_size}")


def ssim_cpu(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of :func:`splat_train.losses.ssim` with a C++ forward and backward.

    Args:
        img1: [B, C, H, W] CPU float32/float64 image (gets the gradient).
        img2: [B, C, H, W] the other image (no gradient: a target).

    Returns:
        Scalar tensor (dtype of img1).
    """
    _check(img1, img2, 4, window_size)
    return _SSIML1CPU.apply(img1, img2, "bchw", int(window_size), float(sigma))[1]


def l1_ssim_cpu(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> tuple[Tensor, Tensor]:
    """(mean |img1 - img2|, mean SSIM) of two [H, W, C] images (the rasterizer's layout, no
    transposed copies) in one C++ pass, forward and backward: the two terms of the 3DGS loss
    (:func:`splat_train.losses.photometric_loss`).

    Args:
        img1: [H, W, C] CPU float32/float64 image (gets the gradient of both terms).
        img2: [H, W, C] the target (no gradient).

    Returns:
        (l1, ssim) scalar tensors (dtype of img1), both differentiable in img1.
    """
    _check(img1, img2, 3, window_size)
    return _SSIML1CPU.apply(img1, img2, "hwc", int(window_size), float(sigma))
