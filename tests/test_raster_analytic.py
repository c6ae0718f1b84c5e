"""Outside anchors for the rasterizer: closed-form cases, an independent per-pixel 3DGS loop,
an autograd-Jacobian EWA check and (when its source can be found) gsplat's pure-PyTorch helpers.

gsplat needs CUDA to build, so it is never installed here. If ``gsplat`` is installed, or
``$GSPLAT_TORCH_IMPL`` points at a copy of ``gsplat/cuda/_torch_impl.py`` (e.g. unpacked from
``pip download gsplat --no-deps``), that file is imported standalone (it only needs torch) and
used as an anchor for projection and SH; otherwise those tests skip.
"""

from __future__ import annotations

import importlib.util
import math
import os
from pathlib import Path

import pytest
import torch

from splat_train import rasterize
from splat_train.render.cpu.raster import available as kernel_available
from splat_train.render.projection import covariance_3d, project_gaussians
from splat_train.render.sh import SH_C0, eval_sh, rgb_to_sh

BACKENDS = ["reference", "torch"] + (["cpu"] if kernel_available() else [])
D = torch.float64


def one_gaussian(opacity=0.7, s=0.05, z=2.0, f=100.0, size=33, color=(0.2, 0.5, 0.9)):
    means = torch.tensor([[0.0, 0.0, z]], dtype=D)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D)
    scales = torch.full((1, 3), s, dtype=D)
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=D)
    return means, quats, scales, torch.tensor([opacity], dtype=D), torch.tensor([color], dtype=D), K


@pytest.mark.parametrize("backend", BACKENDS)
def test_isotropic_gaussian_centre_and_falloff(backend):
    """Centre pixel alpha = opacity; alpha(r) = opacity exp(-r^2 / (2 (sigma_2d^2 + 0.3)))."""
    opacity, s, z, f, size = 0.7, 0.05, 2.0, 100.0, 33
    means, quats, scales, op, col, K = one_gaussian(opacity, s, z, f, size)
    bg = torch.tensor([0.1, 0.1, 0.1], dtype=D)
    out = rasterize(means, quats, scales, op, col, torch.eye(4, dtype=D), K, size, size, bg, backend=backend)
    c = size // 2  # pixel (16, 16) has centre (16.5, 16.5) = principal point
    alpha = out["alpha"]
    assert alpha[c, c].item() == pytest.approx(opacity, rel=1e-12)
    var = (f * s / z) ** 2 + 0.3
    for dr, dc in [(0, 1), (1, 0), (2, 2), (-3, 1), (0, -6)]:
        r2 = dr * dr + dc * dc
        expect = opacity * math.exp(-r2 / (2 * var))
        if expect >= 1 / 255:
            assert alpha[c + dr, c + dc].item() == pytest.approx(expect, rel=1e-10)
    expect_rgb = opacity * col[0] + (1 - opacity) * bg
    torch.testing.assert_close(out["rgb"][c, c], expect_rgb, rtol=1e-12, atol=1e-12)
    assert out["depth"][c, c].item() == pytest.approx(z, rel=1e-12)
    assert out["radii"][0].item() == math.ceil(3 * math.sqrt(var))


@pytest.mark.parametrize("backend", BACKENDS)
def test_alpha_clamp_and_threshold(backend):
    """Opacity 1 clamps to 0.99 at the centre; alpha below 1/255 is not drawn."""
    means, quats, scales, _, col, K = one_gaussian()
    out = rasterize(means, quats, scales, torch.ones(1, dtype=D), col, torch.eye(4, dtype=D), K, 33, 33, backend=backend)
    assert out["alpha"].max().item() == pytest.approx(0.99, rel=1e-12)
    a = out["alpha"][out["alpha"] > 0]
    assert a.min().item() >= 1 / 255


def test_sh_degree0_colour():
    """At degree 0 the colour is C0 * dc + 0.5, whatever the view direction."""
    rgb = torch.tensor([[0.25, 0.5, 0.75]], dtype=D)
    coeffs = torch.zeros(1, 16, 3, dtype=D)
    coeffs[:, 0] = rgb_to_sh(rgb)
    coeffs[:, 1:] = 5.0  # higher bands must be ignored at degree 0
    means, quats, scales, op, _, K = one_gaussian(opacity=0.5)
    out = rasterize(means, quats, scales, op, coeffs, torch.eye(4, dtype=D), K, 33, 33, sh_degree=0)
    torch.testing.assert_close(out["colors"], rgb)
    assert eval_sh(0, coeffs, torch.tensor([[0.0, 0.6, 0.8]], dtype=D))[0, 1].item() == pytest.approx(SH_C0 * coeffs[0, 0, 1].item())


def test_pixel_convention_colmap():
    """A mean at (j + 0.5, i + 0.5) peaks exactly at pixel row i, column j."""
    K = torch.tensor([[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]], dtype=D)
    i, j, z = 7, 25, 3.0
    means = torch.tensor([[(j + 0.5 - 20.0) / 50.0 * z, (i + 0.5 - 15.0) / 50.0 * z, z]], dtype=D)
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]], dtype=D), torch.full((1, 3), 0.02, dtype=D),
                    torch.tensor([0.8], dtype=D), torch.ones(1, 3, dtype=D), torch.eye(4, dtype=D), K, 40, 30)
    assert divmod(int(out["alpha"].argmax()), 40) == (i, j)
    assert out["alpha"][i, j].item() == pytest.approx(0.8, rel=1e-12)
    torch.testing.assert_close(out["means2d"][0], torch.tensor([j + 0.5, i + 0.5], dtype=D))


def sequential_pixel(proj, opac, colors, px, py, tile=(0, 0)):
    """The 3DGS per-pixel loop written out in plain Python floats (independent of cumprod)."""
    order = sorted((i for i in range(len(opac)) if proj.visible[i]), key=lambda i: (float(proj.depths[i]), i))
    T, C = 1.0, [0.0, 0.0, 0.0]
    for i in order:
        x0, x1, y0, y1 = proj.rect[i].tolist()
        if not (x0 <= tile[0] < x1 and y0 <= tile[1] < y1):
            continue
        a, b, c = proj.conics[i].tolist()
        dx, dy = float(proj.means2d[i, 0]) - px, float(proj.means2d[i, 1]) - py
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        if power > 0:
            continue
        alpha = min(0.99, float(opac[i]) * math.exp(power))
        if alpha < 1 / 255:
            continue
        test_T = T * (1 - alpha)
        if test_T < 1e-4:
            break
        for k in range(3):
            C[k] += float(colors[i, k]) * alpha * T
        T = test_T
    return C, T


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_sequential_3dgs_loop(backend):
    g = torch.Generator().manual_seed(0)
    n = 60
    means = torch.randn(n, 3, generator=g, dtype=D) * 0.1 + torch.tensor([0, 0, 2.0], dtype=D)
    scales = torch.rand(n, 3, generator=g, dtype=D) * 0.2 + 0.02
    quats = torch.randn(n, 4, generator=g, dtype=D)
    opac = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=D)
    colors = torch.rand(n, 3, generator=g, dtype=D)
    K = torch.tensor([[40.0, 0, 16.0], [0, 40.0, 16.0], [0, 0, 1]], dtype=D)
    cw = torch.eye(4, dtype=D)
    out = rasterize(means, quats, scales, opac, colors, cw, K, 32, 32, backend=backend)
    proj = project_gaussians(means, quats, scales, cw, K, 32, 32)
    stopped = 0
    for (i, j) in [(3, 3), (15, 15), (16, 16), (10, 20), (28, 5), (16, 0)]:
        C, T = sequential_pixel(proj, opac, colors, j + 0.5, i + 0.5, tile=(j // 16, i // 16))
        torch.testing.assert_close(out["rgb"][i, j], torch.tensor(C, dtype=D), rtol=1e-10, atol=1e-12)
        assert out["alpha"][i, j].item() == pytest.approx(1 - T, abs=1e-12)
        stopped += T < 1e-3
    assert stopped > 0, "no sampled pixel reached the early-stop regime"


def test_projection_matches_autograd_jacobian():
    """cov2d = J W Sigma W^T J^T + 0.3 I with J the autograd Jacobian of the pinhole map."""
    g = torch.Generator().manual_seed(1)
    n = 20
    means = torch.randn(n, 3, generator=g, dtype=D) * 0.3 + torch.tensor([0, 0, 3.0], dtype=D)
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = torch.rand(n, 3, generator=g, dtype=D) * 0.1
    cw = torch.eye(4, dtype=D)
    cw[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=D)
    K = torch.tensor([[60.0, 0, 32.0], [0, 55.0, 24.0], [0, 0, 1]], dtype=D)
    proj = project_gaussians(means, quats, scales, cw, K, 64, 48)
    sigma = covariance_3d(quats, scales)
    for i in range(n):
        def pix(p):
            q = cw[:3, :3] @ p + cw[:3, 3]
            return (K @ q)[:2] / q[2]
        J = torch.autograd.functional.jacobian(pix, means[i])
        cov = J @ sigma[i] @ J.T + 0.3 * torch.eye(2, dtype=D)
        torch.testing.assert_close(proj.cov2d[i], torch.stack([cov[0, 0], cov[0, 1], cov[1, 1]]))
        torch.testing.assert_close(proj.means2d[i], pix(means[i]))


def _load_gsplat_torch_impl():
    path = os.environ.get("GSPLAT_TORCH_IMPL")
    if not path:
        spec = importlib.util.find_spec("gsplat")
        if spec is None or spec.origin is None:
            return None
        path = str(Path(spec.origin).parent / "cuda" / "_torch_impl.py")
    if not Path(path).is_file():
        return None
    spec = importlib.util.spec_from_file_location("gsplat_torch_impl_anchor", path)
    mod = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(mod)
    except ImportError:
        return None
    return mod


@pytest.fixture(scope="module")
def gsplat_impl():
    mod = _load_gsplat_torch_impl()
    if mod is None:
        pytest.skip("gsplat's _torch_impl.py not found (install gsplat or set GSPLAT_TORCH_IMPL)")
    return mod


def test_projection_matches_gsplat(gsplat_impl):
    g = torch.Generator().manual_seed(4)
    n = 200
    means = torch.randn(n, 3, generator=g, dtype=D) * torch.tensor([2.0, 2.0, 1.0], dtype=D)
    means[:, 2] += 3.0  # some far off-screen (Jacobian clamp), some behind the camera
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = torch.rand(n, 3, generator=g, dtype=D) * 0.2
    cw = torch.eye(4, dtype=D)
    K = torch.tensor([[60.0, 0, 30.0], [0, 62.0, 26.0], [0, 0, 1]], dtype=D)  # off-centre pp
    W, H = 64, 48
    proj = project_gaussians(means, quats, scales, cw, K, W, H)
    covars = covariance_3d(quats, scales)
    radii, m2d, depths, conics, _ = gsplat_impl._fully_fused_projection(means, covars, cw[None], K[None], W, H, eps2d=0.3)
    ok = depths[0] > 0.01
    torch.testing.assert_close(proj.means2d[ok], m2d[0][ok])
    torch.testing.assert_close(proj.conics[ok], conics[0][ok])
    torch.testing.assert_close(proj.depths[ok], depths[0][ok])
    assert (proj.radii[~ok] == 0).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat(gsplat_impl, degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=D), dim=-1)
    coeffs = torch.randn(50, 16, 3, generator=g, dtype=D)
    torch.testing.assert_close(eval_sh(degree, coeffs, dirs), gsplat_impl._spherical_harmonics(degree, dirs, coeffs))
