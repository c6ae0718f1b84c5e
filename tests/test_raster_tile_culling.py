"""The "cpu" kernel's tight tile lists: a Gaussian is binned only into the tiles of
its 3-sigma rectangle that its alpha >= 1/255 ellipse can reach (opacity-aware extent, ellipse
against each tile row). The rule must be exact: the dropped pairs would blend no pixel, so
images and gradients equal those of the full-rectangle lists bit for bit, and the dense
reference at the parity tolerances.
"""

from __future__ import annotations

import math

import pytest
import torch

from splat_train import rasterize
from splat_train.render.cpu.raster import available as kernel_available
from splat_train.render.projection import project_gaussians

pytestmark = pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")


def _quat_z(angle: float, n: int, dtype) -> torch.Tensor:
    q = torch.zeros(n, 4, dtype=dtype)
    q[:, 0] = math.cos(angle / 2)
    q[:, 3] = math.sin(angle / 2)
    return q


def _scene(n: int, seed: int, dtype, W: int, H: int):
    """Elongated, rotated Gaussians of every opacity from just above 1/255 to 1, centres all
    over the image (many near tile borders), in front of an identity camera."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * W
    z = 3.0 + torch.rand(n, generator=g, dtype=dtype)
    u = torch.rand(n, generator=g, dtype=dtype) * (W + 20) - 10
    v = torch.rand(n, generator=g, dtype=dtype) * (H + 20) - 10
    snap = torch.rand(n, generator=g) < 0.4  # centres within a pixel of a tile corner
    u = torch.where(snap, torch.round(u / 16) * 16 + torch.randn(n, generator=g, dtype=dtype) * 0.5, u)
    v = torch.where(snap, torch.round(v / 16) * 16 + torch.randn(n, generator=g, dtype=dtype) * 0.5, v)
    means = torch.stack([(u - W / 2) / f * z, (v - H / 2) / f * z, z], 1)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * 3.0 - 4.5)  # 0.011 .. 0.22
    scales[:, 2] = 0.01
    opac = torch.exp(torch.rand(n, generator=g, dtype=dtype) * math.log(250.0)) / 250.0 * 0.999 + 1.0 / 254.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    return means, quats, scales, opac, K


def _bins_pair(proj, opac, W, H):
    from splat_train.render.cpu.raster import bin_cpu

    full = bin_cpu(proj.depths, proj.rect, proj.visible, W, H, "cpu")
    tight = bin_cpu(proj.depths, proj.rect, proj.visible, W, H, "cpu", proj.means2d, proj.conics, opac)
    return full, tight


def _blend(proj, feats, opac, bins, W, H):
    """(accum, T, per-pixel count, gradients) of the kernel's forward and backward with ``bins``
    (the same seeded output cotangents for every call)."""
    from splat_train.render.cpu.raster import backward_raw, forward_raw

    accum, t_final, last, count = forward_raw(proj.means2d, proj.conics, feats, opac, bins, W, H)
    v_acc = torch.randn(accum.shape, generator=torch.Generator().manual_seed(1), dtype=accum.dtype)
    v_t = torch.randn(t_final.shape, generator=torch.Generator().manual_seed(2), dtype=t_final.dtype)
    grads = backward_raw(proj.means2d, proj.conics, feats, opac, bins, W, H, t_final, last, v_acc, v_t)
    return accum, t_final, count, grads


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tight_tile_lists_change_no_pixel_and_no_gradient(dtype, seed):
    """Forward (image, transmittance, per-pixel counts) and per-Gaussian gradients from the
    tight lists are bit-identical to those of the full 3-sigma rectangles, while the lists are
    much shorter; any pair dropped where alpha reaches 1/255 would change a pixel."""
    W, H = 100, 84  # partial edge tiles
    means, quats, scales, opac, K = _scene(600, seed, dtype, W, H)
    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, torch.eye(4, dtype=dtype), K, W, H)
    g = torch.Generator().manual_seed(seed + 100)
    feats = torch.rand(means.shape[0], 4, generator=g, dtype=dtype)
    full, tight = _bins_pair(proj, opac, W, H)
    assert tight.gauss.numel() < 0.85 * full.gauss.numel(), "the tight test drops too little to be exercised"
    outs = [_blend(proj, feats, opac, bins, W, H) for bins in (full, tight)]
    assert outs[0][2].sum() > W * H  # Gaussians overlap: the blend order matters
    for name, a, b in zip(("accum", "T", "count", "grads"), outs[0], outs[1]):
        assert torch.equal(a, b), name


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_tall_gaussians_spans_computed_on_the_fly(dtype):
    """Boxes taller than the 14 tile rows whose spans the footprint pass stores take the other
    branch of for_tiles (spans computed while binning): still bit-identical to the rectangle
    lists."""
    W, H = 120, 400  # 25 tile rows
    means, quats, scales, opac, K = _scene(80, 7, dtype, W, H)
    scales[:20, 0] = 2.5  # long (sigma ~70 px), rotated by the random quaternions, opaque
    scales[:20, 1] = 0.05
    opac[:20] = 0.9
    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, torch.eye(4, dtype=dtype), K, W, H)
    r = proj.rect
    assert ((r[:, 3] - r[:, 2]) > 14).sum() >= 3, "no box is tall enough to exercise the branch"
    feats = torch.rand(means.shape[0], 4, generator=torch.Generator().manual_seed(3), dtype=dtype)
    full, tight = _bins_pair(proj, opac, W, H)
    assert tight.gauss.numel() < full.gauss.numel()
    outs = [_blend(proj, feats, opac, bins, W, H) for bins in (full, tight)]
    for name, a, b in zip(("accum", "T", "count", "grads"), outs[0], outs[1]):
        assert torch.equal(a, b), name


def test_low_opacity_gaussian_matches_reference():
    """A faint wide Gaussian (opacity 0.02: alpha < 1/255 beyond ~2.0 sigma, so most of its
    3-sigma rectangle's tiles are dropped) and a thin diagonal one (its rectangle's corner
    tiles are dropped) over a few ordinary ones: the "cpu" backend matches the dense reference
    (float64 values 1e-9, gradients 1e-9 of the largest), and the lists really are shorter."""
    dtype = torch.float64
    W, H = 96, 80
    f = 80.0
    pix = torch.tensor([[48.0, 40.0], [40.0, 36.0], [20.0, 20.0], [70.0, 60.0], [52.0, 20.0]], dtype=dtype)
    z = torch.tensor([4.0, 3.0, 3.5, 3.2, 2.5], dtype=dtype)
    means = torch.cat([(pix - torch.tensor([W / 2, H / 2], dtype=dtype)) / f * z[:, None], z[:, None]], 1)
    scales = torch.tensor([[0.9, 0.7, 0.01], [1.2, 0.02, 0.01], [0.08, 0.05, 0.01], [0.1, 0.1, 0.01],
                           [0.06, 0.09, 0.01]], dtype=dtype)
    quats = torch.cat([_quat_z(0.3, 1, dtype), _quat_z(math.pi / 4, 1, dtype), _quat_z(0.0, 3, dtype)])
    opac = torch.tensor([0.02, 0.6, 0.8, 0.5, 0.9], dtype=dtype)
    colors = torch.rand(5, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    cw, K = torch.eye(4, dtype=dtype), torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, cw, K, W, H)
    full, tight = _bins_pair(proj, opac, W, H)
    per_g = lambda b: torch.bincount(b.gauss, minlength=5)  # noqa: E731
    assert per_g(tight)[0] < per_g(full)[0] and per_g(tight)[1] < per_g(full)[1]

    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    res = {}
    for backend in ("reference", "cpu"):
        out = rasterize(*params, cw, K, W, H, bg, backend=backend)
        gen = torch.Generator().manual_seed(4)
        loss = sum((out[k] * torch.randn(out[k].shape, generator=gen, dtype=dtype)).sum() for k in ("rgb", "alpha", "depth"))
        res[backend] = (out, torch.autograd.grad(loss, params))
    ref, cpu = res["reference"], res["cpu"]
    assert ref[0]["alpha"][40, 25] > 0  # the faint Gaussian reaches 23 pixels from its centre
    for key in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(cpu[0][key], ref[0][key], rtol=1e-9, atol=1e-10, msg=key)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), cpu[1], ref[1]):
        assert b.abs().max() > 0, name
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9 * (1 + b.abs().max().item()), msg=name)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_vector_footprint_pass_matches_scalar(dtype):
    """The footprint pass runs 8 Gaussians per vector; its records (footprints and binning
    spans) must equal the scalar footprint() bit for bit, padding lanes of a partial last
    block and the special cases included (opacity below 1/255, not positive definite,
    enormous, thin and rotated, and tall boxes whose spans are not stored)."""
    from splat_train.render.cpu.build import ptr
    from splat_train.render.cpu.raster import _footprints, load_library

    W, H = 200, 330
    n = 1003  # not a multiple of 8
    means, quats, scales, opac, K = _scene(n, 11, dtype, W, H)
    g = torch.Generator().manual_seed(5)
    scales[:40, 0] = 2.5  # tall and wide
    scales[40:80] *= torch.exp(3 * torch.randn(40, 3, generator=g, dtype=dtype))
    opac[80:100] = torch.rand(20, generator=g, dtype=dtype) * (1.0 / 255.0)
    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, torch.eye(4, dtype=dtype), K, W, H)
    mu, co, op = proj.means2d.contiguous(), proj.conics.clone(), opac.contiguous()
    co[100:104] = torch.tensor([1.0, 2.0, 1.0], dtype=dtype)  # not positive definite
    co[104:106] = torch.tensor([1e-30, 0.0, 1e-30], dtype=dtype)  # huge footprint
    rect = proj.rect.to(torch.int64).contiguous()
    assert ((rect[:, 3] - rect[:, 2]) > 14).any()
    lib = load_library("cpu")
    sfx = "f32" if dtype == torch.float32 else "f64"
    outs = []
    for vector in (True, False):
        sp = torch.full((n, 32), -7, dtype=torch.int16)
        if vector:
            fp = _footprints(lib, mu, co, op, sfx, rect, sp)
        else:
            fp = torch.empty(n, 8, dtype=torch.float64)
            getattr(lib, f"splat2_footprint_scalar_{sfx}")(n, ptr(co), ptr(op), ptr(mu), ptr(rect), ptr(fp), ptr(sp))
        outs.append((fp, sp))
    assert torch.equal(outs[0][0], outs[1][0])
    assert torch.equal(outs[0][1], outs[1][1])
