"""The SSIM term of the training loss in C++ (``_cpu_ssim.cpp``): separable filtering, forward
and hand-written backward.

CPU twin of :func:`splat_train.losses.ssim` (mean reduction, gradient for the first image only),
which stays the reference and the evaluation metric. Five grouped 11 x 11 ``conv2d`` calls and
their backward took ~100 ms of a ~126 ms training iteration at 497x372 on one torch thread
(fern cell, few Gaussians); the row-then-column filter in C took 9.4 + 6.0 ms (forward +
backward, 2 kernel threads) with a scalar row pass and one channel per work item, and takes
4.2 + 2.2 ms with the row pass vectorised across x (zero-padded rows, taps outer) and
(channel, band of rows) work items that keep both cores busy on 3 channels.
tests/test_train_losses.py compares value and gradient with the reference in float64.
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

__all__ = ["available", "ssim_cpu"]


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    i64, vp, f64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    for dt in ("f32", "f64"):
        getattr(lib, f"splat_ssim_forward_{dt}").argtypes = [i64] * 5 + [vp] * 6
        getattr(lib, f"splat_ssim_forward_{dt}").restype = None
        getattr(lib, f"splat_ssim_backward_{dt}").argtypes = [i64] * 5 + [vp] * 4 + [f64, vp, vp]
        getattr(lib, f"splat_ssim_backward_{dt}").restype = None
    return lib


_KERNELS.setdefault("ssim", _Kernel("ssim", "_cpu_ssim.cpp", 2, True, "splat_ssim_abi_version", _declare))


# Rows per work item (items are channel x band): 64 keeps the row pass's halo (the 2 x 5 rows
# above and below a band that its column pass reads) at ~16 % extra while a 3-channel 372-row
# image still gives 18 items to share between the cores.
BAND_ROWS = 64


def available() -> bool:
    """True when the SSIM kernel is built and loaded."""
    return _KERNELS["ssim"].load() is not None


def _window_1d(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    """The 1D factor of :func:`splat_train.losses.gaussian_window` (same float64 maths)."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return (g / g.sum()).to(dtype).contiguous()


class _SSIMCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, window_size, sigma):
        lib = _KERNELS["ssim"].load()
        dt = a.dtype
        a_, b_ = a.detach().contiguous(), b.detach().to(dt).contiguous()
        nc = a_.shape[0] * a_.shape[1]
        H, W = a_.shape[2], a_.shape[3]
        g = _window_1d(window_size, sigma, dt)
        m = torch.empty(nc, 5, H, W, dtype=dt)
        sums = torch.empty(nc * -(-H // BAND_ROWS), dtype=torch.float64)  # one partial sum per item
        _run_threaded(getattr(lib, f"splat_ssim_forward_{_suffix(dt)}"), nc, H, W, window_size, BAND_ROWS, _ptr(g),
                      _ptr(a_), _ptr(b_), _ptr(m), _ptr(sums))
        ctx.save_for_backward(a_, b_, m, g)
        ctx.dims = (nc, H, W, window_size)
        return (sums.sum() / (nc * H * W)).to(dt)

    @staticmethod
    def backward(ctx, v):
        a_, b_, m, g = ctx.saved_tensors
        nc, H, W, ws = ctx.dims
        lib = _KERNELS["ssim"].load()
        da = torch.empty_like(a_)
        _run_threaded(getattr(lib, f"splat_ssim_backward_{_suffix(a_.dtype)}"), nc, H, W, ws, BAND_ROWS, _ptr(g),
                      _ptr(a_), _ptr(b_), _ptr(m), float(v) / (nc * H * W), _ptr(da))
        return da, None, None, None


def ssim_cpu(img1: Tensor, img2: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of :func:`splat_train.losses.ssim` with a C++ forward and backward.

    Args:
        img1: [B, C, H, W] CPU float32/float64 image (gets the gradient).
        img2: [B, C, H, W] the other image (no gradient: a target).

    Returns:
        Scalar tensor (dtype of img1).
    """
    if img1.shape != img2.shape or img1.dim() != 4:
        raise ValueError(f"ssim_cpu needs two [B, C, H, W] images of one shape, got {tuple(img1.shape)} "
                         f"and {tuple(img2.shape)}")
    if img2.requires_grad:
        raise ValueError("ssim_cpu differentiates img1 only; img2 must not require grad")
    if window_size % 2 != 1:
        raise ValueError(f"window_size must be odd, got {window_size}")
    return _SSIMCPU.apply(img1, img2, int(window_size), float(sigma))
