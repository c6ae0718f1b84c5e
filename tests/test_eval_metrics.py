"""PSNR and SSIM (imgmetrics.psnr_ssim) against float64 direct implementations.

Tolerances: float64 vs float64 references 1e-10 (same maths, different summation order);
float32 vs float64 1e-5 for SSIM (float32 rounding of local variances) and 1e-4 dB for PSNR;
agreement with the trainer's SSIM (splat_train.losses) 1e-6 as agreed between the two owners.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from imgmetrics.psnr_ssim import (
    PSNR_CAP_DB,
    capped_psnr,
    gaussian_window,
    mse,
    psnr,
    ssim,
    ssim_map,
    to_bchw,
)

pytestmark = pytest.mark.usefixtures("core_threads")


def _rand_pair(seed: int, h: int = 24, w: int = 31, noise: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gt = rng.random((h, w, 3))
    pred = np.clip(gt + noise * rng.standard_normal((h, w, 3)), 0.0, 1.0)
    return pred, gt


def _psnr_ref(a: np.ndarray, b: np.ndarray) -> float:
    m = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if m == 0 else 10.0 * math.log10(1.0 / m)


def _ssim_ref(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM with scipy's correlate, zero padding ('constant'), float64, [H, W, C] images."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    x = np.arange(11) - 5
    g = np.exp(-(x ** 2) / (2 * 1.5 ** 2))
    g /= g.sum()
    win = np.outer(g, g)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    vals = []
    for c in range(a.shape[2]):
        f = lambda t: ndimage.correlate(t, win, mode="constant", cval=0.0)  # noqa: E731
        ma, mb = f(a[..., c]), f(b[..., c])
        va = f(a[..., c] ** 2) - ma ** 2
        vb = f(b[..., c] ** 2) - mb ** 2
        cov = f(a[..., c] * b[..., c]) - ma * mb
        vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


class TestPSNR:
    def test_matches_float64_reference(self):
        for seed in range(3):
            pred, gt = _rand_pair(seed)
            assert float(psnr(pred, gt)[0]) == pytest.approx(_psnr_ref(pred, gt), abs=1e-10)

    def test_known_value(self):
        gt = np.full((8, 9, 3), 0.5)
        assert float(psnr(gt + 0.1, gt)[0]) == pytest.approx(20.0, abs=1e-9)  # MSE = 0.01

    def test_float32_close_to_float64(self):
        pred, gt = _rand_pair(5, 64, 80)
        p32 = float(psnr(pred.astype(np.float32), gt.astype(np.float32))[0])
        assert p32 == pytest.approx(_psnr_ref(pred, gt), abs=1e-4)

    def test_identical_is_inf_and_capped(self):
        img = np.random.default_rng(0).random((10, 12, 3))
        v = float(psnr(img, img)[0])
        assert math.isinf(v) and v > 0
        assert capped_psnr(v) == PSNR_CAP_DB
        assert capped_psnr(31.5) == 31.5

    def test_layouts_and_batches_agree(self):
        pred, gt = _rand_pair(1)
        ref = _psnr_ref(pred, gt)
        chw = float(psnr(torch.from_numpy(pred).permute(2, 0, 1), torch.from_numpy(gt).permute(2, 0, 1))[0])
        batch = psnr(np.stack([pred, gt]), np.stack([gt, gt]))
        assert chw == pytest.approx(ref, abs=1e-10)
        assert float(batch[0]) == pytest.approx(ref, abs=1e-10) and math.isinf(float(batch[1]))
        assert float(mse(pred, gt)[0]) == pytest.approx(np.mean((pred - gt) ** 2), abs=1e-14)

    def test_shape_mismatch_is_an_error(self):
        with pytest.raises(ValueError, match="shapes differ"):
            psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
        with pytest.raises(ValueError, match="expected"):
            psnr(np.zeros((4, 4)), np.zeros((4, 4)))


class TestSSIM:
    def test_window(self):
        w = gaussian_window(11, 1.5, dtype=torch.float64)
        assert w.shape == (11, 11)
        assert float(w.sum()) == pytest.approx(1.0, abs=1e-14)
        assert torch.equal(w, w.T) and int(w.argmax()) == 5 * 11 + 5
        # ratio of neighbouring 1D weights is exp(-(2i+1)/(2 sigma^2))
        g = w[5] / w[5].sum()
        assert float(g[6] / g[5]) == pytest.approx(math.exp(-1 / (2 * 1.5 ** 2)), rel=1e-12)

    def test_matches_scipy_reference(self):
        for seed, noise in [(0, 0.05), (1, 0.3), (2, 0.0)]:
            pred, gt = _rand_pair(seed, noise=noise)
            assert float(ssim(pred, gt)[0]) == pytest.approx(_ssim_ref(pred, gt), abs=1e-10)

    def test_identical_is_one(self):
        img = np.random.default_rng(3).random((20, 17, 3))
        assert float(ssim(img, img)[0]) == pytest.approx(1.0, abs=1e-12)
        m = ssim_map(img, img)
        assert m.shape == (1, 3, 20, 17) and torch.allclose(m, torch.ones_like(m), atol=1e-12)

    def test_float32_close_to_float64(self):
        pred, gt = _rand_pair(4, 48, 64)
        s32 = float(ssim(pred.astype(np.float32), gt.astype(np.float32))[0])
        assert s32 == pytest.approx(_ssim_ref(pred, gt), abs=1e-5)

    def test_structure_destroyed_lowers_ssim(self):
        rng = np.random.default_rng(7)
        gt = rng.random((32, 32, 3))
        assert float(ssim(rng.random((32, 32, 3)), gt)[0]) < 0.2  # ~0.11: zero-padded borders share means
        assert float(ssim(np.clip(gt + 0.01, 0, 1), gt)[0]) > 0.95

    def test_differentiable(self):
        pred, gt = _rand_pair(8, 7, 6)  # small: gradcheck costs one forward per input value
        x = torch.from_numpy(pred[..., :1]).permute(2, 0, 1).clone().requires_grad_(True)
        y = torch.from_numpy(gt[..., :1]).permute(2, 0, 1)
        assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,), eps=1e-6, atol=1e-6)

    def test_agrees_with_trainer_ssim(self):
        losses = pytest.importorskip("splat_train.losses", reason="splat_train.losses (trainer's SSIM) not present")
        for dtype in (torch.float32, torch.float64):
            pred, gt = _rand_pair(9, 40, 52, noise=0.2)
            a = torch.from_numpy(pred).to(dtype)
            b = torch.from_numpy(gt).to(dtype)
            theirs = float(losses.ssim(a, b))  # [H, W, 3] layout in the trainer
            ours = float(ssim(a.permute(2, 0, 1), b.permute(2, 0, 1))[0])
            assert ours == pytest.approx(theirs, abs=1e-6)


class TestLayouts:
    def test_to_bchw(self):
        hwc = np.zeros((5, 7, 3), np.float32)
        assert to_bchw(hwc).shape == (1, 3, 5, 7)
        assert to_bchw(np.zeros((2, 5, 7, 3))).shape == (2, 3, 5, 7)
        assert to_bchw(torch.zeros(3, 5, 7)).shape == (1, 3, 5, 7)
        assert to_bchw(np.zeros((5, 7, 3), np.uint8)).dtype == torch.float32
        with pytest.raises(TypeError):
            to_bchw([[0.0]])


_img = st.integers(0, 2 ** 31 - 1).map(lambda s: _rand_pair(s, 13, 15, noise=0.2))


@settings(max_examples=15, deadline=None)
@given(_img)
def test_property_symmetry(pair):
    pred, gt = pair
    assert float(psnr(pred, gt)[0]) == pytest.approx(float(psnr(gt, pred)[0]), abs=1e-12)
    assert float(ssim(pred, gt)[0]) == pytest.approx(float(ssim(gt, pred)[0]), abs=1e-12)


@settings(max_examples=15, deadline=None)
@given(_img, st.floats(0.0, 1.0))
def test_property_bounds(pair, t):
    pred, gt = pair
    s = float(ssim(pred, gt)[0])
    assert -1.0 <= s <= 1.0 + 1e-12
    # moving the prediction towards the ground truth never lowers PSNR
    closer = gt + (1.0 - t) * (pred - gt)
    assert float(psnr(closer, gt)[0]) >= float(psnr(pred, gt)[0]) - 1e-9
