"""The Gaussian window of SSIM (the 3DGS ``create_window``), shared by the torch reference
(:mod:`splat_train.losses`) and the C++ kernel's loader (:mod:`splat_train.cpu.ssim`).

Its own module so that both import it and neither imports the other for it: ``losses`` calls
the kernel, so the kernel must not import ``losses``.
"""

from __future__ import annotations

import torch

__all__ = ["gaussian_window", "gaussian_window_1d"]


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
