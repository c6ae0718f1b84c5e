"""PSNR, SSIM and LPIPS over the covered pixels (imgmetrics.covered) and the LPIPS spatial map:
over every pixel they are the full-image figures; pixels outside the mask never move them; an
empty mask is NaN, never a crash or a zero."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from imgmetrics.covered import (COVERED_ALPHA, coverage, covered_mask, lpips_covered, psnr_covered,
                                ssim_covered)
from imgmetrics.lpips import LPIPS, lpips_distance, lpips_map
from imgmetrics.psnr_ssim import psnr, ssim

pytestmark = pytest.mark.usefixtures("core_threads")


def _pair(h=40, w=36, seed=0):
    """A [H, W, 3] float64 image and a noisy copy (numpy, the project's image layout)."""
    rng = np.random.default_rng(seed)
    gt = rng.random((h, w, 3))
    return np.clip(gt + 0.1 * rng.standard_normal((h, w, 3)), 0, 1), gt


def _random_lpips(net: str, seed: int = 0) -> LPIPS:
    """LPIPS with random weights and non-negative heads (as trained v0.1 heads are), float64."""
    g = torch.Generator().manual_seed(seed)
    m = LPIPS(net).double()
    with torch.no_grad():
        for name, p in m.named_parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64) * (0.1 if "weight" in name else 0.01))
            if name.startswith("lins."):
                p.abs_()
    return m


def test_over_every_pixel_the_covered_figures_are_the_full_image_ones():
    pred, gt = _pair()
    every = np.ones(gt.shape[:2], dtype=bool)
    assert psnr_covered(pred, gt, every) == pytest.approx(float(psnr(pred, gt)[0]), abs=1e-12)
    assert ssim_covered(pred, gt, every) == pytest.approx(float(ssim(pred, gt)[0]), abs=1e-12)
    # torch [C, H, W] input gives the same numbers
    t = (torch.from_numpy(pred).permute(2, 0, 1), torch.from_numpy(gt).permute(2, 0, 1))
    assert psnr_covered(*t, torch.ones(40, 36, dtype=torch.bool)) == psnr_covered(pred, gt, every)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_the_mean_of_the_lpips_map_is_the_lpips(net):
    model = _random_lpips(net)
    # every layer's size divides 64 x 48 for VGG (1, 2, 4, 8, 16): the mean is exact there
    pred, gt = _pair(64, 48)
    d = float(lpips_distance(model, pred, gt, torch.float64)[0])
    m = lpips_map(model, pred, gt, torch.float64)
    assert m.shape == (1, 64, 48)
    assert float(m.mean()) == pytest.approx(d, abs=1e-5)
    if net == "vgg":
        assert float(m.mean()) == pytest.approx(d, abs=1e-14)
    every = np.ones((64, 48), dtype=bool)
    assert lpips_covered(model, pred, gt, every, torch.float64) == pytest.approx(float(m.mean()), abs=1e-15)
    if net == "alex":  # sizes the layers do not divide: bilinear upsampling at a non-integer factor
        pred, gt = _pair(97, 131, seed=1)
        d = float(lpips_distance(model, pred, gt, torch.float64)[0])
        assert float(lpips_map(model, pred, gt, torch.float64).mean()) == pytest.approx(d, abs=1e-5)


def test_the_spatial_form_leaves_the_lpips_value_unchanged():
    model = _random_lpips("alex")
    x, y = (torch.from_numpy(a).permute(2, 0, 1)[None] for a in _pair())
    assert torch.equal(model(x, y), model(x, y, spatial=False))


def test_pixels_outside_the_mask_never_move_the_covered_figures():
    pred, gt = _pair(64, 48)
    mask = np.zeros((64, 48), dtype=bool)
    mask[:, :24] = True
    other = pred.copy()
    other[:, 24:] = 1.0 - other[:, 24:]  # changes only uncovered pixels
    assert psnr_covered(other, gt, mask) == psnr_covered(pred, gt, mask)
    assert ssim_covered(pred, gt, mask) != ssim_covered(pred, gt, ~mask)
    # the SSIM window reaches 5 pixels across the mask's edge: keep the change beyond it
    far = pred.copy()
    far[:, 30:] = 1.0 - far[:, 30:]
    assert ssim_covered(far, gt, mask) == pytest.approx(ssim_covered(pred, gt, mask), abs=1e-15)
    # LPIPS sees a covered pixel's neighbourhood through the network (as the full-image LPIPS
    # does); the map's covered part is what is averaged: the other half gives another figure
    model = _random_lpips("alex")
    full = lpips_map(model, pred, gt, torch.float64)[0]
    assert lpips_covered(model, pred, gt, mask, torch.float64) == pytest.approx(float(full[:, :24].mean()), abs=1e-15)
    assert (lpips_covered(model, pred, gt, mask, torch.float64)
            != lpips_covered(model, pred, gt, ~mask, torch.float64))
    # and a change inside the mask does move them
    inside = pred.copy()
    inside[:, :24] = 1.0 - inside[:, :24]
    assert psnr_covered(inside, gt, mask) < psnr_covered(pred, gt, mask)


def test_an_empty_mask_is_nan_and_identical_pixels_inf():
    pred, gt = _pair()
    none = np.zeros(gt.shape[:2], dtype=bool)
    assert math.isnan(psnr_covered(pred, gt, none))
    assert math.isnan(ssim_covered(pred, gt, none))
    assert math.isnan(lpips_covered(_random_lpips("alex"), pred, gt, none, torch.float64))
    some = none.copy()
    some[3, 4] = True
    same = pred.copy()
    same[3, 4] = gt[3, 4]
    assert psnr_covered(same, gt, some) == math.inf


def test_coverage_counts_pixels_at_the_threshold_as_covered():
    alpha = np.zeros((4, 5))
    alpha[0, :3] = 1.0
    alpha[1, 0] = COVERED_ALPHA
    alpha[1, 1] = np.nextafter(COVERED_ALPHA, 0)
    assert coverage(alpha) == pytest.approx(4 / 20, abs=1e-15)
    assert covered_mask(torch.from_numpy(alpha)).sum() == 4
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        covered_mask(np.zeros((4, 5, 1)))
