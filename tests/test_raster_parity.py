"""Fast rasterizer paths against the dense pure-PyTorch reference (gsplat test_basic pattern).

Forward outputs with ``torch.testing.assert_close``; gradients with ``torch.autograd.grad`` fed
the same random cotangents. Float64 parity is tight (1e-9 relative: only summation order
differs); float32 uses 1e-4 relative to the largest gradient (the backward divides T by
(1 - alpha) and sums per pixel in a different order).
"""

from __future__ import annotations

import pytest
import torch

from splat_train import rasterize
from splat_train.render.cpu.raster import available as kernel_available
from splat_train.render._tiles import tile_pairs
from splat_train.render.projection import project_gaussians

FAST = ["torch"] + (["cpu"] if kernel_available() else [])


def make_scene(kind: str, seed: int, dtype=torch.float64, sh_degree=None):
    """Random Gaussians in front of an identity camera looking down +z.

    Returns (params dict of leaf tensors requiring grad, cam_from_world [4,4], K [3,3], W, H).
    """
    g = torch.Generator().manual_seed(seed)
    W, H = 53, 41  # not multiples of 16: partial edge tiles
    n = {"sparse": 60, "overlap": 250, "borders": 80, "stop": 120, "sh": 90}[kind]
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.7, 0.5, 0.4], dtype=dtype)
    means[:, 2] += 3.0
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.12 + 0.01
    opac = torch.rand(n, generator=g, dtype=dtype)
    if kind == "overlap":  # many Gaussians in one or two tiles
        means[:, :2] *= 0.08
        scales *= 0.6
    if kind == "borders":  # centres near tile borders (x, y multiples of 16 pixels)
        f = 45.0
        u = (torch.randint(1, 4, (n,), generator=g) * 16).to(dtype) + torch.randn(n, generator=g, dtype=dtype) * 0.3
        v = (torch.randint(1, 3, (n,), generator=g) * 16).to(dtype) + torch.randn(n, generator=g, dtype=dtype) * 0.3
        means[:, 0] = (u - W / 2) / f * means[:, 2]
        means[:, 1] = (v - H / 2) / f * means[:, 2]
    if kind == "stop":  # stacked near-opaque layers: transmittance falls below 1e-4
        means[:, :2] *= 0.3
        scales = scales * 3.0
        opac = 0.6 + 0.4 * opac
        opac[:10] = 1.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=dtype)
    else:
        colors = torch.randn(n, 16, 3, generator=g, dtype=dtype) * 0.3
    R = torch.linalg.qr(torch.eye(3, dtype=dtype) + 0.05 * torch.randn(3, 3, generator=g, dtype=dtype)).Q
    R = R * torch.sign(torch.det(R))
    cw = torch.eye(4, dtype=dtype)
    cw[:3, :3] = R
    cw[:3, 3] = torch.randn(3, generator=g, dtype=dtype) * 0.05
    K = torch.tensor([[45.0, 0, W / 2], [0, 47.0, H / 2], [0, 0, 1]], dtype=dtype)
    params = {
        "means": means, "quats": quats, "scales": scales, "opacities": opac, "colors": colors,
        "background": torch.rand(3, generator=g, dtype=dtype),
    }
    for t in params.values():
        t.requires_grad_(True)
    return params, cw, K, W, H


def render(params, cw, K, W, H, backend, sh_degree=None):
    return rasterize(
        params["means"], params["quats"], params["scales"], params["opacities"], params["colors"],
        cw, K, W, H, params["background"], sh_degree=sh_degree, backend=backend,
    )


def grads_with_cotangents(out, params, seed, keys=("rgb", "alpha", "depth")):
    g = torch.Generator().manual_seed(seed)
    loss = 0.0
    for key in keys:
        loss = loss + (out[key] * torch.randn(out[key].shape, generator=g, dtype=out[key].dtype)).sum()
    inputs = list(params.values()) + [out["means2d"]]
    return torch.autograd.grad(loss, inputs, allow_unused=True)


CASES = [("sparse", None), ("overlap", None), ("borders", None), ("stop", None),
         ("sh", 0), ("sh", 1), ("sh", 2), ("sh", 3)]


@pytest.mark.parametrize("backend", FAST)
@pytest.mark.parametrize("kind,sh_degree", CASES)
def test_fast_matches_reference_float64(backend, kind, sh_degree):
    params, cw, K, W, H = make_scene(kind, seed=sum(map(ord, kind)) + (sh_degree or 0), sh_degree=sh_degree)
    ref = render(params, cw, K, W, H, "reference", sh_degree)
    out = render(params, cw, K, W, H, backend, sh_degree)
    for key in ("rgb", "alpha", "depth", "depth_accum", "means2d", "radii", "visible"):
        torch.testing.assert_close(out[key], ref[key], rtol=1e-9, atol=1e-10, msg=key)
    assert ref["alpha"].max() > 0.5, "scene renders almost nothing: the test would be vacuous"
    g_ref = grads_with_cotangents(ref, params, seed=7)
    g_out = grads_with_cotangents(out, params, seed=7)
    names = list(params) + ["means2d"]
    for name, a, b in zip(names, g_out, g_ref):
        assert b is not None and torch.isfinite(b).all(), name
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9 * (1 + b.abs().max().item()), msg=name)


@pytest.mark.parametrize("backend", FAST)
def test_fast_matches_reference_without_depth_loss(backend):
    """A photometric loss leaves the depth channel's cotangent zero, which the "cpu" kernel's
    backward skips: gradients still equal the reference (float64)."""
    params, cw, K, W, H = make_scene("overlap", seed=21, sh_degree=3)
    ref = render(params, cw, K, W, H, "reference", 3)
    out = render(params, cw, K, W, H, backend, 3)
    g_ref = grads_with_cotangents(ref, params, 3, keys=("rgb", "alpha"))
    g_out = grads_with_cotangents(out, params, 3, keys=("rgb", "alpha"))
    for name, a, b in zip(list(params) + ["means2d"], g_out, g_ref):
        assert b is not None and b.abs().max() > 0, name
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9 * (1 + b.abs().max().item()), msg=name)


@pytest.mark.parametrize("backend", FAST)
def test_fast_matches_reference_float32(backend):
    params64, cw, K, W, H = make_scene("overlap", seed=3, sh_degree=2)
    params = {k: v.detach().float().requires_grad_(True) for k, v in params64.items()}
    ref = render(params, cw.float(), K.float(), W, H, "reference", 2)
    out = render(params, cw.float(), K.float(), W, H, backend, 2)
    for key in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(out[key], ref[key], rtol=1e-4, atol=1e-4, msg=key)
    for name, a, b in zip(list(params) + ["means2d"], grads_with_cotangents(out, params, 1), grads_with_cotangents(ref, params, 1)):
        scale = b.abs().max().item()
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * scale + 1e-6, msg=name)


def test_early_stop_happens_and_matches():
    """The 'stop' scene really drives transmittance to the 1e-4 floor (the stop rule is exercised)."""
    params, cw, K, W, H = make_scene("stop", seed=11)
    out = render(params, cw, K, W, H, "reference")
    t_final = 1.0 - out["alpha"].detach()
    assert t_final.min() >= 1e-4 * (1 - 1e-12)  # the Gaussian that would cross 1e-4 is dropped
    assert t_final.min() < 1e-2


@pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpu_kernel_deterministic_across_threads(dtype):
    """Bit-identical image and gradients for 1, 2 and 3 kernel threads and on a repeat: tiles
    write disjoint pair rows and each Gaussian's pairs are summed in a fixed order."""
    from splat_train.render.cpu import raster as cpu_raster

    params, cw, K, W, H = make_scene("overlap", seed=5, dtype=dtype, sh_degree=2)
    results = []
    try:
        for nt in (1, 2, 3, 2):
            cpu_raster.set_kernel_threads(nt)
            out = render(params, cw, K, W, H, "cpu", 2)
            results.append([out["rgb"].detach(), *grads_with_cotangents(out, params, 2)])
    finally:
        cpu_raster.set_kernel_threads(None)
    assert results[0][0].abs().sum() > 0
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


def test_tile_pairs_front_to_back_and_complete():
    params, cw, K, W, H = make_scene("borders", seed=2)
    proj = project_gaussians(params["means"], params["quats"], params["scales"], cw, K, W, H)
    offsets, gauss, tx, ty = tile_pairs(proj.depths, proj.rect, proj.visible, W, H)
    assert offsets[-1] == gauss.numel()
    r = proj.rect
    expected = int(((r[:, 1] - r[:, 0]) * (r[:, 3] - r[:, 2]))[proj.visible].sum())
    assert gauss.numel() == expected
    for t in range(tx * ty):
        ids = gauss[offsets[t]:offsets[t + 1]]
        d = proj.depths[ids]
        assert torch.all(d[1:] >= d[:-1])
        x, y = t % tx, t // tx
        assert torch.all((r[ids, 0] <= x) & (x < r[ids, 1]) & (r[ids, 2] <= y) & (y < r[ids, 3]))


@pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")
def test_cpu_binning_matches_torch_binning():
    from splat_train.render.cpu.raster import tile_pairs_cpu

    params, cw, K, W, H = make_scene("overlap", seed=9)
    proj = project_gaussians(params["means"], params["quats"], params["scales"], cw, K, W, H)
    a = tile_pairs(proj.depths, proj.rect, proj.visible, W, H)
    b = tile_pairs_cpu(proj.depths, proj.rect, proj.visible, W, H)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and a[2:] == b[2:]


@pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")
def test_cpu_radix_depth_order_matches_stable_sort():
    """float32 depths (the radix path) with ties, negative and invisible entries: the same
    indices as torch's stable sort (ties by index)."""
    from splat_train.render.cpu.raster import _depth_order, load_library
    from splat_train.render._reference import depth_order

    g = torch.Generator().manual_seed(3)
    d = torch.randint(-50, 50, (5000,), generator=g).float() * 0.37
    d[::7] = 1.0
    d[1] = 0.0
    d[5] = -0.0
    vis = torch.rand(5000, generator=g) > 0.2
    got = _depth_order(load_library("cpu"), d, vis)
    assert torch.equal(got, depth_order(d, vis))
    assert _depth_order(load_library("cpu"), d, torch.zeros(5000, dtype=torch.bool)).numel() == 0


@pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")
@pytest.mark.parametrize("kind", ["overlap", "borders", "stop", "sparse"])
def test_cpu_forward_specialisation_is_the_generic_forward(kind):
    """The rasterizer's float32 forward without per-pixel counts (RGB + depth, four channels)
    runs a specialised kernel on AVX-512 CPUs (mask registers, forward_f4_avx512); with counts
    it runs the generic forward_impl. Both must give the same bits: images, transmittance and
    each pixel's last contributor, on partial edge tiles, early stops and crowded tiles.
    (Without AVX-512 both calls take the generic kernel and the test still holds.)"""
    from splat_train.render.cpu import raster as cpu_raster

    args = _kernel_args(kind, 21, torch.float32)
    bins = args[4]
    with torch.no_grad():
        fast = cpu_raster.forward_raw(*args, with_count=False)
        fast_rows = bins.rows_hit
        generic = cpu_raster.forward_raw(*args, with_count=True)
    assert fast[3] is None and generic[3].sum() > 0
    assert (fast[2] > 0).any()
    for a, b in zip(fast[:3], generic[:3]):
        assert torch.equal(a, b)
    # the rows each pair blended (read by the backward) agree too, over the pairs the
    # forward reached (those behind a tile's last contributor are never read)
    reached = _reached_pairs(bins, fast[2])
    assert torch.equal(fast_rows[reached], bins.rows_hit[reached])
    if kind == "stop":
        assert fast[1].min() < 1e-2  # the stop rule ran


def _kernel_args(kind: str, seed: int, dtype):
    """(means2d, conics, RGB + depth features, opacities, bins, W, H) of a make_scene scene,
    binned for the "cpu" kernel: the arguments of its forward_raw / backward_raw."""
    from splat_train.render.cpu import raster as cpu_raster

    params, cw, K, W, H = make_scene(kind, seed=seed, dtype=dtype)
    with torch.no_grad():
        proj = project_gaussians(params["means"], params["quats"], params["scales"], cw, K, W, H)
        feat = torch.cat([params["colors"], proj.depths[:, None]], dim=1).contiguous()
        op = params["opacities"].detach()
        bins = cpu_raster.bin_cpu(proj.depths, proj.rect, proj.visible, W, H, means2d=proj.means2d,
                                  conics=proj.conics, opacities=op)
    return proj.means2d, proj.conics, feat, op, bins, W, H


def _reached_pairs(bins, last):
    """[P] bool: the pairs of each tile up to its last contributor (the ones the backward reads)."""
    W, H = last.shape[1], last.shape[0]
    tl = torch.nn.functional.pad(last, (0, bins.tiles_x * 16 - W, 0, bins.tiles_y * 16 - H))
    tile_last = tl.reshape(bins.tiles_y, 16, bins.tiles_x, 16).amax(dim=(1, 3)).reshape(-1)
    local = torch.arange(bins.gauss.numel()) - torch.repeat_interleave(bins.offsets[:-1], bins.offsets.diff())
    tile = torch.repeat_interleave(torch.arange(tile_last.numel()), bins.offsets.diff())
    return local < tile_last[tile].long()


@pytest.mark.skipif(not kernel_available(), reason="CPU kernel did not build")
@pytest.mark.parametrize("kind", ["overlap", "borders", "stop", "sparse"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_backward_visits_only_rows_the_forward_blended(kind, dtype):
    """The backward visits, per tile pair, only the rows where the forward blended a pixel
    (bins.rows_hit) and skips pairs with none: the gradients are bit for bit those of a
    backward that visits every row of every reached pair (a mask of all ones), while the
    masks do skip work here (pairs with no row, and rows left out)."""
    from splat_train.render.cpu import raster as cpu_raster

    args = _kernel_args(kind, 22, dtype)
    bins, W, H = args[4:]
    with torch.no_grad():
        _, t_final, last, _ = cpu_raster.forward_raw(*args, with_count=False)
        g = torch.Generator().manual_seed(5)
        v_acc = torch.randn(H, W, 4, generator=g, dtype=dtype)
        v_t = torch.randn(H, W, generator=g, dtype=dtype)
        got = cpu_raster.backward_raw(*args, t_final, last, v_acc, v_t)
        every = torch.full_like(bins.rows_hit, -1)  # all 16 bits
        ref = cpu_raster.backward_raw(*args, t_final, last, v_acc, v_t, rows_hit=every)
    assert torch.equal(got, ref)
    assert got.abs().sum() > 0
    rows = bins.rows_hit[_reached_pairs(bins, last)].to(torch.int32) & 0xFFFF
    assert (rows == 0).any() or kind == "sparse"
    assert (rows != 0xFFFF).any()
