"""Full-reference image metrics: PSNR and SSIM (the 3DGS definitions).

Convention: images are RGB in [0, 1]. Layout follows the container type:

* numpy arrays are channel-last, the project's image layout (:mod:`camio.images`):
  ``[H, W, C]`` or a batch ``[B, H, W, C]``;
* torch tensors are channel-first: ``[C, H, W]`` or ``[B, C, H, W]``.

Functions compute in the input's floating dtype (float32 input stays float32; pass float64 for
reference values). Batched inputs give one value per image.

PSNR
    ``10 log10(max_val^2 / MSE)`` with the MSE over all pixels and channels of one image.
    Identical images have MSE = 0 and PSNR = +inf; :func:`psnr` returns inf (the true
    value). Means cannot average inf, so the evaluation uses :func:`capped_psnr`, which clips
    at :data:`PSNR_CAP_DB` = 100 dB, and lists every image that reached the cap (choice: cap,
    not skip; skipping would drop the best images from the mean).

SSIM (Wang et al. 2004, as 3DGS ``utils/loss_utils.py`` computes it)
    11x11 Gaussian window, sigma 1.5 (normalised to sum 1), applied per channel by a
    depthwise 2D convolution with zero 'same' padding (5 pixels), C1 = 0.01^2, C2 = 0.03^2
    (``max_val`` = 1), and the SSIM map averaged over channels, rows and columns. Border
    pixels therefore see zero padding, exactly as in 3DGS (this is not skimage's 'valid'
    cropping; values differ slightly from skimage).
"""

from __future__ import annotations

import numpy as np
import torch

from imgmetrics.ssim import ArrayLike, gaussian_window, to_bchw
from imgmetrics.ssim import ssim_map as _ssim_map

__all__ = [
    "PSNR_CAP_DB",
    "SSIM_WINDOW_SIZE",
    "SSIM_SIGMA",
    "SSIM_C1",
    "SSIM_C2",
    "to_bchw",
    "mse",
    "psnr",
    "capped_psnr",
    "gaussian_window",
    "ssim",
    "ssim_map",
]

#: PSNR cap in dB for means and JSON. For scale: 8-bit images that differ by one code value
#: in one channel of one pixel have PSNR = 48.13 + 10 log10(3 H W) dB, i.e. 100 dB at about
#: 5 * 10^4 pixels and 107 dB at 620 x 410; so the cap only ever touches (near-)identical pairs.
PSNR_CAP_DB = 100.0
SSIM_WINDOW_SIZE = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _pair(a: ArrayLike, b: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    x, y = to_bchw(a), to_bchw(b)
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {tuple(x.shape)} vs {tuple(y.shape)} (as [B, C, H, W]); "
                         "render at the ground-truth resolution or resize one of them first")
    dtype = torch.promote_types(x.dtype, y.dtype)
    return x.to(dtype), y.to(dtype)


def mse(pred: ArrayLike, gt: ArrayLike) -> torch.Tensor:
    """Mean squared error per image: ``[B]`` (``B = 1`` for a single image)."""
    x, y = _pair(pred, gt)
    return ((x - y) ** 2).flatten(1).mean(dim=1)


def psnr(pred: ArrayLike, gt: ArrayLike, max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image, ``10 log10(max_val^2 / MSE)``.

    Args:
        pred, gt: images in [0, ``max_val``], same shape (see module docstring for layouts).

    Returns:
        ``[B]`` tensor; ``+inf`` where the images are identical (MSE = 0).
    """
    m = mse(pred, gt)
    return 10.0 * torch.log10(max_val ** 2 / m)  # 1/0 = inf -> +inf dB, no warning in torch


def capped_psnr(value: float, cap: float = PSNR_CAP_DB) -> float:
    """``min(value, cap)``: the PSNR used in means and JSON (inf cannot be averaged)."""
    return float(min(float(value), cap))


def ssim_map(pred: ArrayLike, gt: ArrayLike, window_size: int = SSIM_WINDOW_SIZE,
             sigma: float = SSIM_SIGMA, max_val: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM map ``[B, C, H, W]`` (3DGS definition; see module docstring).

    Differentiable; works on any device. ``C1 = (0.01 max_val)^2``, ``C2 = (0.03 max_val)^2``.
    """
    x, y = _pair(pred, gt)
    return _ssim_map(x, y, window_size, sigma, max_val)


def ssim(pred: ArrayLike, gt: ArrayLike, window_size: int = SSIM_WINDOW_SIZE,
         sigma: float = SSIM_SIGMA, max_val: float = 1.0) -> torch.Tensor:
    """SSIM per image ``[B]``: the mean of :func:`ssim_map` over channels and pixels.

    Identical images give exactly 1 up to rounding (numerator = denominator).
    """
    return ssim_map(pred, gt, window_size, sigma, max_val).flatten(1).mean(dim=1)

