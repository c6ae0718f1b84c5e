"""Extreme and bad-input cases of docs/robustness.md that no stage test covered yet."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _train_scene import write_scene
from camio.ply import GaussianCloud, read_gaussian_ply, write_gaussian_ply


def _empty_cloud() -> GaussianCloud:
    z = np.zeros((0, 3))
    return GaussianCloud.from_points(z, z, np.zeros(0), np.zeros(0), sh_degree=3)


def test_empty_gaussian_cloud_round_trips(tmp_path):
    """Zero Gaussians is a valid (if useless) PLY: written and read back with its SH bands."""
    path = write_gaussian_ply(tmp_path / "empty.ply", _empty_cloud())
    cloud = read_gaussian_ply(path)
    assert len(cloud) == 0 and cloud.sh_rest.shape == (0, 15, 3) and cloud.sh_degree == 3


def test_rasterize_zero_gaussians_gives_background():
    from splat_train import rasterize

    bg = torch.tensor([0.2, 0.4, 0.6])
    e = torch.zeros(0, 3)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    out = rasterize(e, torch.zeros(0, 4), e, torch.zeros(0), e, torch.eye(4), K, 16, 12, background=bg)
    torch.testing.assert_close(out["rgb"], bg.expand(12, 16, 3))
    assert torch.equal(out["alpha"], torch.zeros(12, 16))


def test_trainer_refuses_empty_seed(tmp_path):
    """(Found by this suite: it used to train nothing and write an empty model.ply.)"""
    from splat_train.config import TrainConfig
    from splat_train.training.trainer import train

    scene = write_scene(tmp_path / "scene", n_views=3, width=16, height=12)
    seed = write_gaussian_ply(tmp_path / "empty.ply", _empty_cloud())
    n = torch.get_num_threads()
    try:
        with pytest.raises(ValueError, match="empty.ply"):
            train(seed, scene["cameras"], scene["images"], tmp_path / "out",
                  TrainConfig(iterations=3, device="cpu", num_threads=1))
    finally:
        torch.set_num_threads(n)
    assert not (tmp_path / "out" / "model.ply").exists()


def test_colmap_baseline_identical_images_is_a_recorded_failure(tmp_path):
    """Three copies of one image: no baseline, no initial pair. COLMAP's failure is a result
    (status.json, success false, a reason), not an exception, and no model is written."""
    from camio.images import write_image
    from evaluation.initialisers.colmap_baseline import run_colmap

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (48, 64, 3)).astype(np.float32)
    for i in range(3):
        write_image(tmp_path / "images" / f"{i}.png", img)
    status = run_colmap(tmp_path / "images", ["0.png", "1.png", "2.png"], tmp_path / "out")
    assert status["success_paper"] is False and status["registered"] < 3 and status["reason"]
    assert json.loads((tmp_path / "out" / "status.json").read_text())["success_paper"] is False
    assert not (tmp_path / "out" / "sparse").exists()


def test_bridge_constant_confidence_map_from_npz(tmp_path):
    """A predictions.npz whose confidence map is one constant value everywhere (c_max = c_min,
    Eq. 2's 0/0): every opacity is alpha_max, finite logits, through the real reader."""
    from bridge.core import BridgeConfig, build_seed
    from bridge.inputs import load_predictions
    from bridge.synthetic import synthetic_predictions
    from runtime.atomic import save_npz

    d = synthetic_predictions(n_views=3, height=8, width=10)
    d["world_points_conf"] = np.full_like(d["world_points_conf"], 3.7)
    res = build_seed(load_predictions(save_npz(tmp_path / "p.npz", **d)), BridgeConfig(stride=1))
    cfg = BridgeConfig()
    np.testing.assert_allclose(res.cloud.opacity, cfg.alpha_max, rtol=1e-6)
    assert np.isfinite(res.cloud.opacity_logit).all()


def test_bridge_predictions_with_float_colours_and_nan(tmp_path):
    """Colours as float in [0, 1] with NaN (a writer that forgot the uint8 cast) are converted
    with a warning; NaN colour becomes 0 rather than poisoning the SH coefficients."""
    from bridge.inputs import load_predictions
    from bridge.synthetic import synthetic_predictions
    from runtime.atomic import save_npz

    d = synthetic_predictions(n_views=2, height=6, width=8)
    c = d["colors"].astype(np.float32) / 255.0
    c[0, 0, 0] = np.nan
    d["colors"] = c
    inp = load_predictions(save_npz(tmp_path / "p.npz", **d))
    assert inp.colors.dtype == np.uint8 and inp.colors[0].tolist() == [0, 0, 0]
