"""PSNR, SSIM and LPIPS over the pixels a model covers (accumulated opacity >= :data:`COVERED_ALPHA`).

From a few views a held-out view also sees what no training view saw; there the render is the
background colour. The share of covered pixels (:func:`coverage`) and the figures over those
pixels alone tell that part of the error (too little covered) from the error where the model is.

Convention: one image per call; layouts as :mod:`imgmetrics.psnr_ssim` (numpy ``[H, W, C]``,
torch ``[C, H, W]``), RGB in [0, 1]; ``mask`` a boolean ``[H, W]`` (numpy or torch) in the same
pixel grid, from :func:`covered_mask`. Every function returns a Python float, NaN when the mask
holds no pixel (nothing covered: no figure, never 0).

* PSNR covered: ``10 log10(1 / MSE)``, the MSE in float64 over the covered pixels' channels;
  inf where they match exactly (cap it as the full-image PSNR is, :func:`imgmetrics.psnr_ssim.capped_psnr`).
* SSIM covered: the full-image SSIM map (:func:`imgmetrics.psnr_ssim.ssim_map`, the same window,
  sigma and zero padding, in the input's dtype) averaged over channels, then over the covered pixels.
* LPIPS covered: the LPIPS spatial map (:func:`imgmetrics.lpips.lpips_map`) averaged over the
  covered pixels.

With every pixel covered each equals its full-image figure (LPIPS: see :func:`imgmetrics.lpips.lpips_map`).
An uncovered pixel never enters the PSNR; SSIM and LPIPS are averaged over covered pixels only,
but each of those pixels' values sees its neighbourhood (the 11 x 11 SSIM window, the network's
receptive field), as in the full-image figures.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from imgmetrics.lpips import LPIPS, lpips_map
from imgmetrics.psnr_ssim import ssim_map
from imgmetrics.ssim import ArrayLike, to_bchw

__all__ = ["COVERED_ALPHA", "covered_mask", "coverage", "psnr_covered", "ssim_covered", "lpips_covered"]

#: a pixel counts as covered by the model where its accumulated opacity reaches this
COVERED_ALPHA = 0.5


def covered_mask(alpha: ArrayLike) -> torch.Tensor:
    """Boolean [H, W] tensor: ``alpha`` [H, W] (accumulated opacity) >= :data:`COVERED_ALPHA`."""
    a = torch.as_tensor(alpha) if isinstance(alpha, np.ndarray) else alpha
    if a.ndim != 2:
        raise ValueError(f"expected an [H, W] opacity, got shape {tuple(a.shape)}")
    return a.detach() >= COVERED_ALPHA


def coverage(alpha: ArrayLike) -> float:
    """The share of pixels of ``alpha`` [H, W] that are covered (:func:`covered_mask`), in [0, 1]."""
    return float(covered_mask(alpha).double().mean())


def _masked(values: torch.Tensor, mask: ArrayLike) -> torch.Tensor | None:
    """``values`` [B=1, C, H, W] at the pixels of ``mask`` [H, W]: [C, K], or None when K = 0."""
    m = torch.as_tensor(mask) if isinstance(mask, np.ndarray) else mask
    if values.shape[0] != 1:
        raise ValueError(f"one image per call; got a batch of {values.shape[0]}")
    if tuple(m.shape) != tuple(values.shape[-2:]):
        raise ValueError(f"mask is {tuple(m.shape)}, the image {tuple(values.shape[-2:])} (as [H, W])")
    m = m.to(device=values.device, dtype=torch.bool)
    if not bool(m.any()):
        return None
    return values[0][:, m]


def psnr_covered(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike) -> float:
    """PSNR in dB over the covered pixels (float64 MSE); NaN without any, inf where they match."""
    x, y = to_bchw(pred, torch.float64), to_bchw(gt, torch.float64)
    if x.shape != y.shape:
        raise ValueError(f"image shapes differ: {tuple(x.shape)} vs {tuple(y.shape)} (as [B, C, H, W])")
    d = _masked((x - y) ** 2, mask)
    if d is None:
        return math.nan
    mse = float(d.mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim_covered(pred: ArrayLike, gt: ArrayLike, mask: ArrayLike) -> float:
    """SSIM over the covered pixels: the SSIM map's channel mean averaged there; NaN without any."""
    per_pixel = ssim_map(pred, gt).mean(dim=1, keepdim=True)  # [1, 1, H, W]
    v = _masked(per_pixel, mask)
    return math.nan if v is None else float(v.mean())


def lpips_covered(model: LPIPS, pred: ArrayLike, gt: ArrayLike, mask: ArrayLike,
                  dtype: torch.dtype = torch.float32) -> float:
    """LPIPS over the covered pixels: the spatial map averaged there (computed in ``dtype``);
    NaN without any."""
    m = torch.as_tensor(mask) if isinstance(mask, np.ndarray) else mask
    if not bool(m.any()):  # no network pass for nothing
        return math.nan
    v = _masked(lpips_map(model, pred, gt, dtype)[:, None], m)
    return float(v.mean())
