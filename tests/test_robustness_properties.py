"""Property tests (Hypothesis) that complement the stage engineers' own (see docs/robustness.md):

* Sim(3) from *cameras* (``fit_sim3_cameras``, what evaluation uses) recovers random
  similarities over 14 decades of scale and 1e4 translations (Umeyama on points is in
  test_eval_align.py);
* the whole Bridge (``build_seed``, not only Eq. 2) keeps every opacity in
  [alpha_min, alpha_max] for random confidence maps with NaN/Inf and extreme spans, and its
  seed is invariant to a random global scaling of the input world;
* rasterizer gradients stay finite through the *trainer's* parameterisation (log-scales,
  opacity logits, raw quaternions, SH up to degree 3; ``splat_train.export.render_params``)
  for random near-degenerate values (the raw rasterizer property is in test_raster_stability);
* PSNR / SSIM / LPIPS reach their limits on identical images, including the stiff constant
  images (zero variance: SSIM's C1/C2 terms alone), and are symmetric.

Tolerances: float64 where the code allows it; the documented float32 ones otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from camio.cameras import Camera, look_at, qvec_to_rotmat

finite = dict(allow_nan=False, allow_infinity=False)


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ----------------------------------------------------------------------------- Sim(3) from cameras

@settings(max_examples=25, deadline=None)
@given(q=st.tuples(*[st.floats(-1, 1, **finite)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1),
       log10_s=st.floats(-5, 5, **finite), t=st.tuples(*[st.floats(-1e3, 1e3, **finite)] * 3),
       seed=st.integers(0, 2**16), n=st.integers(3, 10))
def test_fit_sim3_cameras_recovers_random_similarity(q, log10_s, t, seed, n):
    """Tolerance: float64 rounding grows with how far the (scaled) rig sits from the origin
    relative to its size, cond = 1 + |t| / s; the bound is 1e-9 + 1e-13 * cond."""
    from evaluation.metrics.align import Sim3, collinearity_ratio, fit_sim3_cameras, transform_cam_from_world

    rng = np.random.default_rng(seed)
    ref = {}
    for i in range(n):
        eye = rng.normal(size=3) * 3
        ref[f"{i}.png"] = look_at(eye, rng.normal(size=3) * 0.3)[:3]
    centres = np.array([-c[:, :3].T @ c[:, 3] for c in ref.values()])
    assume(collinearity_ratio(centres) > 0.05)
    sim = Sim3(10.0 ** log10_s, qvec_to_rotmat(np.array(q) / np.linalg.norm(q)), np.array(t))
    pred = {k: transform_cam_from_world(v, sim) for k, v in ref.items()}
    al = fit_sim3_cameras(pred, ref, use_orientations="never")
    inv = sim.inverse()
    tol = 1e-9 + 1e-13 * (1 + np.abs(t).max() / sim.s)
    assert al.sim.s == pytest.approx(inv.s, rel=tol)
    np.testing.assert_allclose(al.sim.R, inv.R, atol=tol)
    assert al.rmse <= tol * al.ref_radius


# ----------------------------------------------------------------------------- the Bridge

def _inp(points, conf, colors, cams):
    from bridge.inputs import BridgeInput

    return BridgeInput("vggt", Path("p.npz"), points, conf, colors, cams)


def _cams(scale=1.0):
    out = []
    for i, a in enumerate(np.linspace(-0.4, 0.4, 3)):
        eye = scale * np.array([3 * np.sin(a), 0.2, -3 * np.cos(a)])
        cw = look_at(eye, np.zeros(3))[:3]
        out.append(Camera(f"{i}.png", 40, 30, np.array([[30.0, 0, 20], [0, 30, 15], [0, 0, 1]]), cw))
    return out


_conf = st.one_of(st.floats(1.0, 1e6, **finite), st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1.0]))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), conf=st.lists(_conf, min_size=200, max_size=200),
       a_min=st.floats(1e-6, 0.5, **finite), width=st.floats(0.0, 0.49, **finite),
       mode=st.sampled_from(["gated", "filtered"]))
def test_bridge_opacities_stay_in_range(seed, conf, a_min, width, mode):
    """Eq. 2 modes (``uniform`` is a constant, tested in test_bridge_pipeline.py)."""
    from bridge.core import BridgeConfig, build_seed

    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(200, 3))
    conf = np.asarray(conf)
    assume(np.isfinite(conf).sum() >= 20)
    a_max = a_min + width
    res = build_seed(_inp(pts, conf, rng.integers(0, 255, (200, 3), dtype=np.uint8), _cams()),
                     BridgeConfig(mode=mode, stride=1, alpha_min=a_min, alpha_max=a_max))
    alpha = res.cloud.opacity
    assert len(alpha) > 0 and np.isfinite(alpha).all()
    # the PLY stores logit(alpha) in float32: allow its rounding at the range ends
    assert (alpha >= a_min - 1e-6).all() and (alpha <= a_max + 1e-6).all(), (alpha.min(), alpha.max())
    assert np.isfinite(res.cloud.opacity_logit).all() and np.isfinite(res.cloud.log_scales).all()


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), log10_k=st.floats(-4, 4, **finite))
def test_bridge_seed_invariant_to_global_scaling(seed, log10_k):
    from bridge.core import BridgeConfig, build_seed

    k = 10.0 ** log10_k
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(150, 3)) * rng.uniform(0.5, 2.0, 3)
    conf = 1 + rng.exponential(3.0, 150)
    col = rng.integers(0, 255, (150, 3), dtype=np.uint8)
    cams_k = [Camera(c.name, c.width, c.height, c.K, np.c_[c.R, k * c.t]) for c in _cams()]
    cfg = BridgeConfig(stride=1)
    a = build_seed(_inp(pts, conf, col, _cams()), cfg)
    b = build_seed(_inp(pts * k, conf, col, cams_k), cfg)
    assert b.report["s"] == pytest.approx(a.report["s"] / k, rel=1e-9)
    np.testing.assert_allclose(b.points, a.points, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b.cloud.log_scales, a.cloud.log_scales, atol=1e-5)  # float32 in the cloud
    np.testing.assert_array_equal(b.cloud.opacity_logit, a.cloud.opacity_logit)
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_allclose(cb.cam_from_world, ca.cam_from_world, rtol=1e-9, atol=1e-9)


# ----------------------------------------------------------------------------- trainer parameterisation

@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16),
       log_scale=st.one_of(st.sampled_from([-40.0, -20.0, 15.0]), st.floats(-12, 6, **finite)),
       logit=st.one_of(st.sampled_from([-60.0, 60.0]), st.floats(-20, 20, **finite)),
       quat=st.lists(st.one_of(st.just(0.0), st.just(1e-30), st.floats(-1, 1, **finite)), min_size=4, max_size=4),
       z=st.one_of(st.sampled_from([-1.0, 0.0, 0.01, 1e4]), st.floats(0.02, 100, **finite)),
       sh=st.floats(-50, 50, **finite), degree=st.integers(0, 3))
def test_trainer_render_gradients_finite(seed, log_scale, logit, quat, z, sh, degree):
    from splat_train.export import render_params

    g = torch.Generator().manual_seed(seed)
    n, W, H = 6, 24, 16
    params = {
        "means": torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 2.0]),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.full((n, 3), -3.0) + 0.3 * torch.randn(n, 3, generator=g),
        "opacity": torch.randn(n, generator=g),
        "sh_dc": torch.randn(n, 3, generator=g),
        "sh_rest": 0.1 * torch.randn(n, 15, 3, generator=g),
    }
    params["means"][0] = torch.tensor([0.05, -0.02, z])
    params["scales"][0] = torch.tensor([log_scale, log_scale - 3.0, log_scale + 1.0])
    params["opacity"][0] = logit
    params["quats"][0] = torch.tensor(quat)
    params["sh_rest"][0] = sh
    leaves = {k: v.requires_grad_(True) for k, v in params.items()}
    K = torch.tensor([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    out = render_params(leaves, degree, torch.eye(4), K, W, H, torch.tensor([0.1, 0.2, 0.3]))
    assert torch.isfinite(out["rgb"]).all()
    loss = ((out["rgb"] - 0.5) ** 2).mean()
    loss.backward()
    for k, p in leaves.items():
        assert p.grad is None or torch.isfinite(p.grad).all(), f"non-finite gradient for {k}"


# ----------------------------------------------------------------------------- metrics limits

def _image(kind: str, seed: int, h: int = 17, w: int = 19) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "random":
        return rng.uniform(0, 1, (h, w, 3))
    if kind == "black":
        return np.zeros((h, w, 3))
    if kind == "white":
        return np.ones((h, w, 3))
    if kind == "constant":
        return np.broadcast_to(rng.uniform(0, 1, 3), (h, w, 3)).copy()
    return (rng.uniform(0, 1, (h, w, 3)) > 0.5).astype(np.float64)  # binary: extreme contrast


_kinds = st.sampled_from(["random", "black", "white", "constant", "binary"])


@settings(max_examples=12, deadline=None)
@given(kind=_kinds, seed=st.integers(0, 2**16))
def test_psnr_ssim_limits_on_identical_images(kind, seed):
    from imgmetrics.psnr_ssim import PSNR_CAP_DB, capped_psnr, psnr, ssim

    x = _image(kind, seed)
    p = float(psnr(x, x.copy())[0])
    assert p == float("inf") and capped_psnr(p) == PSNR_CAP_DB
    assert float(ssim(x, x.copy())[0]) == pytest.approx(1.0, abs=1e-12)
    x32 = x.astype(np.float32)
    assert float(ssim(x32, x32.copy())[0]) == pytest.approx(1.0, abs=1e-6)


@settings(max_examples=15, deadline=None)
@given(a=_kinds, b=_kinds, sa=st.integers(0, 2**16), sb=st.integers(0, 2**16))
def test_psnr_ssim_symmetric_and_bounded_on_stiff_pairs(a, b, sa, sb):
    from imgmetrics.psnr_ssim import psnr, ssim

    x, y = _image(a, sa), _image(b, sb)
    assume(not np.array_equal(x, y))
    pxy, pyx = float(psnr(x, y)[0]), float(psnr(y, x)[0])
    assert np.isfinite(pxy) and pxy == pytest.approx(pyx, abs=1e-12) and pxy >= 0.0  # MSE <= 1
    sxy, syx = float(ssim(x, y)[0]), float(ssim(y, x)[0])
    assert np.isfinite(sxy) and sxy == pytest.approx(syx, abs=1e-12) and -1.0 <= sxy < 1.0


_LPIPS = {}


def _lpips():
    if "alex" not in _LPIPS:
        from imgmetrics.lpips import LPIPS

        g = torch.Generator().manual_seed(5)
        m = LPIPS("alex").double()
        with torch.no_grad():
            for name, p in m.named_parameters():
                p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64) * (0.1 if "weight" in name else 0.01))
                if name.startswith("lins."):
                    p.abs_()
        _LPIPS["alex"] = m.requires_grad_(False)
    return _LPIPS["alex"]


@settings(max_examples=8, deadline=None)
@given(a=_kinds, b=_kinds, sa=st.integers(0, 2**16), sb=st.integers(0, 2**16))
def test_lpips_limits_and_symmetry_on_stiff_images(a, b, sa, sb):
    """Random-weight AlexNet LPIPS (float64): identical -> exactly 0 even for constant images
    (zero features: the normalisation's epsilon keeps it finite); symmetric; non-negative."""
    m = _lpips()
    t = lambda img: torch.from_numpy(img).permute(2, 0, 1)[None].contiguous()  # noqa: E731
    x, y = t(_image(a, sa, 32, 32)), t(_image(b, sb, 32, 32))
    assert float(m(x, x.clone())) == 0.0
    dxy, dyx = float(m(x, y)), float(m(y, x))
    assert np.isfinite(dxy) and dxy >= 0.0 and dxy == pytest.approx(dyx, abs=1e-14)
