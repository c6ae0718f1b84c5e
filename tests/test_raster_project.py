"""The fused C++ projection + SH (:mod:`splat_train.render.cpu.project`) against the torch code it
replaces on the CPU (:func:`project_gaussians` + :func:`sh_to_color`, autograd).

Float64: values to 1e-12 relative (same double maths, different summation order), gradients
fed the same random cotangents to 1e-9 relative to the largest entry. Float32: the torch
reference computes SH in float32 and the kernel in double, so 1e-5 relative. Scenes include
Gaussians behind the near plane, far outside the view (the Jacobian's 1.3 x fov clamp), a zero
quaternion, and colours clamped at 0.
"""

from __future__ import annotations

import pytest
import torch

from splat_train.render.cpu import project as cpu_project
from splat_train.render.projection import project_gaussians
from splat_train.render.sh import sh_to_color

pytestmark = pytest.mark.skipif(not cpu_project.available(), reason="projection kernel did not build")


def make_scene(seed: int, n: int = 300, dtype=torch.float64):
    """Random Gaussians around a rotated camera; returns (means, quats, scales, sh [N,16,3],
    cam_from_world [4,4], K [3,3], W, H), the first four leaf tensors requiring grad."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.5, 1.2, 1.5], dtype=dtype)
    means[:, 2] += 2.5  # some behind the near plane, some far off to the side
    means[:5, 0] = torch.tensor([40.0, -40.0, 0.0, 0.0, 5.0], dtype=dtype)
    means[:5, 2] = 2.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[7] = 0.0
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.01
    sh = torch.randn(n, 16, 3, generator=g, dtype=dtype) * 0.4
    sh[:20, 0] = -3.0  # colour clamped at 0
    R = torch.linalg.qr(torch.eye(3, dtype=dtype) + 0.2 * torch.randn(3, 3, generator=g, dtype=dtype)).Q
    R = R * torch.sign(torch.det(R))
    cw = torch.eye(4, dtype=dtype)
    cw[:3, :3] = R
    cw[:3, 3] = torch.randn(3, generator=g, dtype=dtype) * 0.1
    W, H = 67, 45
    K = torch.tensor([[60.0, 0, 30.0], [0, 58.0, 24.0], [0, 0, 1]], dtype=dtype)
    return [t.requires_grad_(True) for t in (means, quats, scales, sh)], cw, K, W, H


def run(fast: bool, params, cw, K, W, H, deg):
    means, quats, scales, sh = params
    colors = sh if deg is not None else sh[:, 0].detach().clone().requires_grad_(True)
    if fast:
        proj, rgb, _ = cpu_project.project_sh_cpu(means, quats, scales, colors, deg, cw, K, W, H, 0.01, 0.3)
    else:
        proj = project_gaussians(means, quats, scales, cw, K, W, H)
        if deg is None:
            rgb = colors
        else:
            centre = -cw[:3, :3].T @ cw[:3, 3]
            rgb = sh_to_color(deg, sh, means, centre)
    return proj, rgb


@pytest.mark.parametrize("deg", [None, 0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_project_sh_matches_torch(deg, dtype):
    params, cw, K, W, H = make_scene(4, dtype=dtype)
    ref, ref_rgb = run(False, params, cw, K, W, H, deg)
    got, got_rgb = run(True, params, cw, K, W, H, deg)
    assert not ref.visible.all() and ref.visible.any()
    for name in ("radii", "rect", "visible"):
        assert torch.equal(getattr(got, name), getattr(ref, name)), name
    rtol = 1e-12 if dtype == torch.float64 else 1e-5
    for name in ("means2d", "conics", "cov2d", "depths"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=rtol, atol=rtol, msg=name)
    torch.testing.assert_close(got_rgb, ref_rgb, rtol=rtol, atol=rtol)
    if deg is None:
        return
    grads = []
    for proj, rgb in ((ref, ref_rgb), (got, got_rgb)):
        g = torch.Generator().manual_seed(1)
        loss = sum((t * torch.randn(t.shape, generator=g, dtype=dtype)).sum()
                   for t in (proj.means2d, proj.conics, proj.depths, rgb))
        grads.append(torch.autograd.grad(loss, params))
    gtol = 1e-9 if dtype == torch.float64 else 1e-4
    for name, a, b in zip(("means", "quats", "scales", "sh"), grads[1], grads[0]):
        scale = b.abs().max().item()
        assert scale > 0, name
        torch.testing.assert_close(a, b, rtol=gtol, atol=gtol * scale, msg=name)


def test_project_sh_refuses_a_camera_that_needs_gradients():
    params, cw, K, W, H = make_scene(1, n=10)
    with pytest.raises(ValueError, match="pose refinement"):
        cpu_project.project_sh_cpu(*params[:3], params[3], 3, cw.clone().requires_grad_(True), K, W, H, 0.01, 0.3)


@pytest.mark.parametrize("deg", [0, 1, 3])
def test_sh_pair_matches_one_tensor_and_gradients_accumulate(deg):
    """SH as the (dc, rest) pair gives bit-identical colours and gradients to the [N, 16, 3]
    tensor; a .grad kept across two backward passes accumulates, and one taken away is left
    alone by the next backward."""
    params, cw, K, W, H = make_scene(5, n=6000, dtype=torch.float32)
    means, quats, scales, sh = (t.detach() for t in params)
    dc = sh[:, 0].clone().requires_grad_(True)
    rest = sh[:, 1:].clone().requires_grad_(True)
    whole = sh.clone().requires_grad_(True)
    g = torch.Generator().manual_seed(2)
    cot = [torch.randn(6000, k, generator=g) for k in (2, 3, 3)]

    def once(colors):
        proj, rgb, _ = cpu_project.project_sh_cpu(means, quats, scales, colors, deg, cw, K, W, H, 0.01, 0.3)
        torch.autograd.backward([proj.means2d, proj.conics, rgb], cot)
        return rgb.detach()

    assert torch.equal(once((dc, rest)), once(whole))
    assert torch.equal(dc.grad, whole.grad[:, 0]) and torch.equal(rest.grad, whole.grad[:, 1:])
    first = rest.grad.clone()
    assert first[:, (deg + 1) ** 2 - 1:].eq(0).all() and bool(first.abs().sum() > 0) == (deg > 0)
    once((dc, rest))  # rest.grad is still held: accumulated into, not overwritten
    torch.testing.assert_close(rest.grad, 2 * first)
    kept = rest.grad
    rest.grad = None
    once((dc, rest))
    torch.testing.assert_close(kept, 2 * first)  # a gradient someone still holds is left alone
    assert torch.equal(rest.grad, first)
