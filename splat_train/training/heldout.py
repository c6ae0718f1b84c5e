"""Held-out measures along a run: PSNR, SSIM and (optional) LPIPS of the trainer's renders.

The trainer's periodic evaluation (``TrainConfig.eval_every``) renders every test view and
scores the float render, clamped to [0, 1], against the test image, both ``[H, W, 3]`` RGB in
[0, 1] in the view's pixel grid:

* PSNR: :func:`splat_train.losses.psnr` (float64 MSE), dB;
* SSIM: :func:`splat_train.losses.ssim` (the 3DGS definition, the one
  :func:`imgmetrics.psnr_ssim.ssim` also calls), computed in float32;
* LPIPS: LPIPS v0.1 with the AlexNet backbone and the weights ``python -m evaluation images``
  uses (:func:`imgmetrics.lpips.load_lpips`), float32; only with ``TrainConfig.eval_lpips``;
  NaN (null in log.parquet) when it is off or the weights are absent, never 0;
* coverage: the share of the view's pixels the model covers, accumulated opacity (the
  render's ``alpha``, [H, W]) at least :data:`imgmetrics.covered.COVERED_ALPHA`; and the PSNR,
  SSIM and (with LPIPS on) LPIPS over those pixels alone (NaN where none is covered), the definitions of
  :mod:`imgmetrics.covered` that ``python -m evaluation images --alpha-dir`` also uses. From a few views a held-out view also sees what no
  training view saw, where the render is the background: the two tell that part of the error
  (too little covered) from the error where the model is (:func:`coverage_split`).

The means over the test views are the ``test_*`` columns of ``log.parquet``
(:mod:`splat_train.training.runlog`). They differ from the final ``metrics.json`` only by the 8-bit
quantisation of the PNGs that the evaluation stage reads.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from imgmetrics.covered import COVERED_ALPHA, coverage, covered_mask, lpips_covered, psnr_covered, ssim_covered
from imgmetrics.lpips import find_weights, load_lpips, lpips_distance
from splat_train.losses import psnr, ssim

__all__ = ["HeldoutScorer", "LPIPS_NET", "COVERED_ALPHA", "MEASURES", "COVERED_MEASURES", "coverage_split", "unmeasured"]

log = logging.getLogger(__name__)

#: the LPIPS backbone along the run (the evaluation's default network for the study tables)
LPIPS_NET = "alex"
#: the keys of :meth:`HeldoutScorer.means`
MEASURES = ("psnr", "ssim", "lpips", "coverage", "psnr_covered", "ssim_covered", "lpips_covered")
#: the measures over the covered pixels: means over the views that cover any pixel
COVERED_MEASURES = ("psnr_covered", "ssim_covered", "lpips_covered")


def unmeasured() -> dict[str, float]:
    """Every measure NaN: an iteration or run with no held-out score."""
    return {k: math.nan for k in MEASURES}


def coverage_split(rgb: torch.Tensor, target: torch.Tensor, alpha: torch.Tensor) -> tuple[float, float]:
    """(coverage, PSNR over the covered pixels) of one render.

    Args:
        rgb, target: [H, W, 3] in [0, 1].
        alpha: [H, W] accumulated opacity of the render (1 - final transmittance).

    Returns:
        The share of pixels with ``alpha`` >= :data:`COVERED_ALPHA`, and the PSNR (dB, float64
        MSE over those pixels' channels) of ``rgb`` against ``target`` there: NaN when no pixel
        is covered, inf when they match exactly (:mod:`imgmetrics.covered`).
    """
    return coverage(alpha), psnr_covered(rgb.permute(2, 0, 1), target.permute(2, 0, 1), covered_mask(alpha))


class HeldoutScorer:
    """Scores renders against test images and keeps the per-view values of one evaluation.

    Args:
        lpips: compute LPIPS (loads the AlexNet weights once, here).
        lpips_weights: folder or file of the weights (None: the evaluation's search order).
        device: where LPIPS runs (the renders' device).
    """

    def __init__(self, lpips: bool = False, lpips_weights: str | Path | None = None,
                 device: torch.device | str = "cpu") -> None:
        self.model = None
        self.weights: str | None = None
        self.per_view: dict[str, dict[str, float]] = {}
        if lpips:
            t0 = time.perf_counter()
            self.model = load_lpips(LPIPS_NET, lpips_weights, device)  # None (and a warning) if absent
            if self.model is not None:
                self.weights = str(find_weights(LPIPS_NET, lpips_weights))
            log.info("held-out LPIPS-%s along the run: %s (%.2f s to load)", LPIPS_NET,
                     self.weights or "weights absent, test_lpips stays null", time.perf_counter() - t0)

    def reset(self) -> None:
        self.per_view = {}

    @torch.no_grad()
    def __call__(self, name: str, rgb: torch.Tensor, target: torch.Tensor, alpha: torch.Tensor | None = None) -> None:
        """Score one view: ``rgb`` and ``target`` are [H, W, 3] in [0, 1] on one device,
        ``alpha`` [H, W] the render's accumulated opacity (None: coverage and the covered
        measures NaN)."""
        rec = {**unmeasured(), "psnr": psnr(rgb, target), "ssim": float(ssim(rgb, target))}
        chw, target_chw = rgb.permute(2, 0, 1), target.permute(2, 0, 1)
        mask = None
        if alpha is not None:
            mask = covered_mask(alpha)
            rec["coverage"], rec["psnr_covered"] = coverage_split(rgb, target, alpha)
            rec["ssim_covered"] = ssim_covered(chw, target_chw, mask)
        if self.model is not None:
            try:
                rec["lpips"] = float(lpips_distance(self.model, chw, target_chw)[0])
                if mask is not None:
                    rec["lpips_covered"] = lpips_covered(self.model, chw, target_chw, mask)
            except ValueError as exc:  # smaller than the backbone compares (imgmetrics.lpips.MIN_SIDE)
                log.warning("held-out LPIPS off for the rest of the run: view %s (%d x %d px) cannot be scored "
                            "(%s); test_lpips stays null", name, rgb.shape[1], rgb.shape[0], exc)
                self.model = None
        self.per_view[name] = rec

    def means(self) -> dict[str, float]:
        """Mean of each measure over the views scored since :meth:`reset` (NaN without views);
        the :data:`COVERED_MEASURES` over the views that cover any pixel."""
        if not self.per_view:
            return unmeasured()
        views = self.per_view.values()
        out = {k: float(np.mean([r[k] for r in views])) for k in MEASURES if k not in COVERED_MEASURES}
        for k in COVERED_MEASURES:
            vals = [r[k] for r in views if not math.isnan(r[k])]
            out[k] = float(np.mean(vals)) if vals else math.nan
        return out
