"""Image-comparison building blocks shared by training and evaluation.

The SSIM of 3DGS (its Gaussian window and per-pixel map) and the layout conversion that the
metrics and LPIPS use. Both stages import them from here, so neither imports the other:
the training loss (:mod:`splat_train.losses`, and the C++ kernel's loader
:mod:`splat_train.render.cpu.ssim`) and the evaluation metrics (:mod:`imgmetrics.psnr_ssim`,
:mod:`imgmetrics.lpips`).
"""

from __future__ import annotations

import functools
from typing import Union

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["to_bchw", "gaussian_window", "gaussian_window_1d", "ssim_map"]

ArrayLike = Union[torch.Tensor, np.ndarray]


def to_bchw(img: ArrayLike, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Convert an image or batch to a float tensor ``[B, C, H, W]``.

    Args:
        img: numpy ``[H, W, C]`` / ``[B, H, W, C]`` or torch ``[C, H, W]`` / ``[B, C, H, W]``.
            Integer arrays are NOT rescaled: convert 8-bit images to [0, 1] first
            (:func:`camio.images.read_image` does).
        dtype: result dtype; default: the input's float dtype, float32 for non-float input.

    Returns:
        ``[B, C, H, W]`` tensor (a view when no conversion is needed).
    """
    if isinstance(img, np.ndarray):
        if img.ndim not in (3, 4):
            raise ValueError(f"expected a numpy image [H, W, C] or batch [B, H, W, C]; got shape {img.shape}")
        t = torch.from_numpy(np.ascontiguousarray(img))
        t = t.permute(2, 0, 1).unsqueeze(0) if t.ndim == 3 else t.permute(0, 3, 1, 2)
    elif isinstance(img, torch.Tensor):
        if img.ndim not in (3, 4):
            raise ValueError(f"expected a tensor [C, H, W] or batch [B, C, H, W]; got shape {tuple(img.shape)}")
        t = img.unsqueeze(0) if img.ndim == 3 else img
    else:
        raise TypeError(f"expected a torch tensor or numpy array, got {type(img).__name__}")
    if dtype is None:
        dtype = t.dtype if t.is_floating_point() else torch.float32
    return t.to(dtype)


def gaussian_window_1d(size: int = 11, sigma: float = 1.5, dtype=torch.float64, device=None) -> torch.Tensor:
    """Normalised 1D Gaussian window [size]: g[i] = exp(-(i - size // 2)^2 / (2 sigma^2)) / sum,
    computed in float64 and then cast."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 2D Gaussian window [size, size]: the outer product of :func:`gaussian_window_1d`
    with itself (the 3DGS ``create_window``)."""
    g = gaussian_window_1d(size, sigma)
    return torch.outer(g, g).to(dtype=dtype, device=device)


def ssim_map(a: torch.Tensor, b: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
             max_val: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM map of the 3DGS definition (see :func:`ssim`): [B, C, H, W] x2 -> [B, C, H, W].

    The one implementation in the project: the training loss (:mod:`splat_train.losses`) and the
    evaluation metric (:func:`imgmetrics.psnr_ssim.ssim_map`) both call it. C1 = (0.01 max_val)^2,
    C2 = (0.03 max_val)^2.
    The 2D window is an outer product, so each local mean is a row pass then a column pass with
    the 1D window (zero 'same' padding in both): 22 instead of 121 multiply-adds per pixel, the
    same values as the 2D convolution up to rounding (1.8e-14 at most on a random 497x372
    float64 image, whose SSIM took 1.13 s with the 2D convolution and takes 0.14 s). The five
    local means go through the two passes together, stacked on the channel axis, so that a
    training step on a GPU launches 2 convolutions (and 2 in the backward pass), not 10.
    """
    c = a.shape[1]
    w_row, w_col = _separable_windows(window_size, sigma, 5 * c, a.dtype, a.device)
    pad = window_size // 2
    # the five local means (of a, b, a^2, b^2, ab) as one grouped row pass and one column pass
    # over the stacked channels: 2 convolutions instead of 10, the same per-channel arithmetic
    stats = torch.cat((a, b, a * a, b * b, a * b), dim=1)
    stats = F.conv2d(F.conv2d(stats, w_row, padding=(0, pad), groups=5 * c), w_col, padding=(pad, 0), groups=5 * c)
    mu1, mu2, e11, e22, e12 = stats.split(c, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq = e11 - mu1_sq
    sigma2_sq = e22 - mu2_sq
    sigma12 = e12 - mu12
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    return ((2 * mu12 + c1) * (2 * sigma12 + c2)) / ((mu1_sq + mu2_sq + c1) * (sigma1_sq + sigma2_sq + c2))


@functools.lru_cache(maxsize=32)
def _separable_windows(window_size: int, sigma: float, channels: int, dtype: torch.dtype,
                       device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The depthwise row [C, 1, 1, k] and column [C, 1, k, 1] filters of :func:`gaussian_window_1d`
    on ``device``; cached, because building them there is a host-to-device copy that waits for
    the device's queue (once per SSIM call, i.e. per training iteration, otherwise)."""
    g = gaussian_window_1d(window_size, sigma, dtype=dtype, device=device)
    return (g.view(1, 1, 1, window_size).expand(channels, 1, 1, window_size).contiguous(),
            g.view(1, 1, window_size, 1).expand(channels, 1, window_size, 1).contiguous())
