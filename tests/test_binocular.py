"""Binocular stereo consistency (splat_train/parts/binocular.py): the shifted camera, the warp back with
the rendered depth, the loss's minimum at the true depth through the rasterizer, degenerate
input, and the term as a part of a training run."""

from __future__ import annotations

import json
import math

import pytest
import torch

from _train_scene import write_scene
from splat_train import rasterize
from splat_train.parts.binocular import (binocular_consistency_loss, disparity_smoothness, shifted_camera,
                                   warp_from_shifted)
from splat_train.config import TrainConfig
from splat_train.training.trainer import train

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py
F64 = torch.float64


def _random_pose(g: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    q = q * torch.sign(torch.det(q))
    m = torch.eye(4, dtype=F64)
    m[:3, :3], m[:3, 3] = q, torch.randn(3, generator=g, dtype=F64)
    return m


def test_the_shifted_camera_moves_its_centre_along_its_own_x_axis():
    g = torch.Generator().manual_seed(0)
    cw = _random_pose(g)
    out = shifted_camera(cw, 0.37)
    centre = lambda m: -m[:3, :3].T @ m[:3, 3]  # noqa: E731
    torch.testing.assert_close(out[:3, :3], cw[:3, :3], rtol=0, atol=0)
    torch.testing.assert_close(centre(out), centre(cw) + 0.37 * cw[0, :3], rtol=1e-12, atol=1e-12)
    assert torch.equal(cw, _random_pose(torch.Generator().manual_seed(0)))  # the input is untouched


@pytest.mark.parametrize("disparity", [3.0, 2.4])
def test_the_warp_of_a_plane_returns_the_training_image(disparity):
    """A fronto-parallel plane at depth z seen by a camera shifted by s: its image is the
    training image moved by fx s / z pixels; warping it back with depth z gives the training
    image wherever the sample lies inside the shifted image (exactly, for an image linear along
    the rows when the disparity is fractional)."""
    h, w, fx, z = 6, 20, 50.0, 4.0
    shift = disparity * z / fx
    u = torch.arange(w, dtype=F64)
    g = torch.Generator().manual_seed(1)
    slope, offset = torch.rand(3, generator=g, dtype=F64), torch.rand(h, 1, 3, generator=g, dtype=F64)
    image = offset + 0.02 * slope * u[None, :, None]            # [H, W, 3] linear along x
    shifted = offset + 0.02 * slope * (u + disparity)[None, :, None]  # S(u) = I(u + d)
    warped, valid, disp = warp_from_shifted(shifted, torch.full((h, w), z, dtype=F64), fx, shift)
    expect_valid = (u >= disparity).to(F64).expand(h, w)
    torch.testing.assert_close(valid, expect_valid, rtol=0, atol=0)
    torch.testing.assert_close(warped, image * expect_valid[..., None], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(disp, disparity * expect_valid, rtol=1e-12, atol=1e-12)
    loss = binocular_consistency_loss(image, torch.full((h, w), z, dtype=F64), shifted, fx, shift)
    assert float(loss) < 1e-12  # a constant disparity is smooth where valid: both parts vanish
    # counted over the masked map instead, the step to 0 at the warp's edge would be penalised
    assert float(disparity_smoothness(disp, image)) > 0


def _plane_of_gaussians(dtype=F64, n_side=14):
    """Small textured Gaussians tiling the plane z = 3 in front of an identity camera."""
    g = torch.Generator().manual_seed(2)
    xs = torch.linspace(-1.2, 1.2, n_side, dtype=dtype)
    gx, gy = torch.meshgrid(xs, xs, indexing="xy")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((n_side * n_side,), 3.0, dtype=dtype)], 1)
    n = means.shape[0]
    quats = torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(n, 4).clone()
    scales = torch.full((n, 3), 0.12, dtype=dtype)
    scales[:, 2] = 0.01
    return dict(means=means, quats=quats, scales=scales, opacities=torch.full((n,), 0.95, dtype=dtype),
                colors=torch.rand(n, 3, generator=g, dtype=dtype))


def test_through_the_rasterizer_the_loss_is_least_at_the_rendered_depth():
    """The training render's own depth explains its shifted render: scaling the depth by 0.8 or
    1.25 (colour placed at the wrong depth) raises the loss, in float64 through the torch
    backend."""
    p = _plane_of_gaussians()
    w, h = 40, 32
    K = torch.tensor([[36.0, 0, w / 2], [0, 36.0, h / 2], [0, 0, 1]], dtype=F64)
    cw = torch.eye(4, dtype=F64)
    out = rasterize(*p.values(), cw, K, w, h, sh_degree=None, backend="torch")
    shift = 0.12  # 1.4 px at depth 3
    shifted = rasterize(*p.values(), shifted_camera(cw, shift), K, w, h, sh_degree=None, backend="torch")["rgb"]
    target, depth = out["rgb"], out["depth"]
    losses = {s: float(binocular_consistency_loss(target, depth * s, shifted, K[0, 0], shift))
              for s in (0.8, 1.0, 1.25)}
    assert losses[1.0] < 0.5 * min(losses[0.8], losses[1.25]), losses


def test_gradients_reach_the_depth_and_the_shifted_render_and_stay_finite_on_empty_renders():
    g = torch.Generator().manual_seed(3)
    h, w = 9, 13
    target = torch.rand(h, w, 3, generator=g, dtype=F64)
    depth = (2.0 + torch.rand(h, w, generator=g, dtype=F64)).requires_grad_(True)
    shifted = torch.rand(h, w, 3, generator=g, dtype=F64).requires_grad_(True)
    loss = binocular_consistency_loss(target, depth, shifted, 20.0, 0.2)
    gd, gs = torch.autograd.grad(loss, [depth, shifted])
    assert gd.abs().sum() > 0 and gs.abs().sum() > 0
    # nothing rendered: depth 0 everywhere (the rasterizer's value), and a negative shift
    empty = torch.zeros(h, w, dtype=F64, requires_grad=True)
    loss = binocular_consistency_loss(target, empty, shifted, 20.0, -0.2)
    gd, gs = torch.autograd.grad(loss, [empty, shifted])
    assert float(loss.detach()) == 0.0 and torch.isfinite(gd).all() and torch.isfinite(gs).all()
    assert float(disparity_smoothness(torch.zeros(h, w, dtype=F64), target)) == 0.0


@pytest.mark.parametrize("bad", [{"binocular_weight": -1.0}, {"binocular_from_fraction": 1.5},
                                 {"binocular_shift": 0.0}])
def test_bad_binocular_values_are_refused(bad):
    with pytest.raises(ValueError, match="binocular"):
        TrainConfig(**bad)


def test_sparse_has_the_term_from_its_densification_start_and_the_field_recipes_do_not():
    for recipe in ("paper", "dropgaussian", "sparse", "mcmc"):
        cfg = TrainConfig(recipe=recipe, iterations=3000)
        assert cfg.binocular_weight == (1.0 if recipe == "sparse" else 0.0), recipe
        start = round(cfg.binocular_from_fraction * cfg.iterations)
        assert start == (cfg.schedule().densify_from if recipe == "sparse" else 2000), recipe


def test_a_run_with_the_term_adds_it_from_its_start(tmp_path):
    """Through the trainer: the term acts from the iteration after its start, the run stays
    finite, train.json says how often it was added, and the term changes the model (the same
    run without it ends elsewhere)."""
    sc = write_scene(tmp_path / "s", n_views=3)
    base = dict(recipe="sparse", iterations=24, binocular_from_fraction=0.5, eval_every=0,
                checkpoint_every=10**6, device="cpu")
    train(sc["seed"], sc["cameras"], sc["images"], tmp_path / "on", TrainConfig(binocular_weight=1.0, **base))
    train(sc["seed"], sc["cameras"], sc["images"], tmp_path / "off", TrainConfig(binocular_weight=0.0, **base))
    on, off = (json.loads((tmp_path / d / "train.json").read_text()) for d in ("on", "off"))
    assert on["binocular"]["from_iteration"] == 13 and on["binocular"]["terms"] == 12
    assert "binocular" not in off
    assert math.isfinite(on["train_psnr"]) and on["train_psnr"] != off["train_psnr"]
