"""Opacity decay (splat_train/parts/opacity_decay.py): the logit update against a float64 reference,
finite on extreme logits, the part's start, the config's bounds, and the decay as a part of a
training run (it fades and prunes what the views do not hold up)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from camio.ply import GaussianCloud, read_gaussian_ply, write_gaussian_ply
from _train_scene import write_scene
from splat_train.config import TrainConfig
from splat_train.data import load_views
from splat_train.parts.opacity_decay import OpacityDecay, opacity_decay
from splat_train.parts.compose import recipe_parts
from splat_train.training.trainer import train

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py
F64 = torch.float64


@pytest.mark.parametrize("factor", [0.995, 0.5, 1e-3])
def test_the_decay_multiplies_the_opacity_by_the_factor(factor):
    x = torch.linspace(-12.0, 12.0, 97, dtype=F64)
    out = opacity_decay(x, factor)
    torch.testing.assert_close(torch.sigmoid(out), factor * torch.sigmoid(x), rtol=1e-12, atol=0)
    # float32 against the float64 reference, within float32's logit precision
    out32 = opacity_decay(x.float(), factor)
    torch.testing.assert_close(out32.double(), out, rtol=1e-6, atol=2e-5)


def test_extreme_logits_stay_finite_and_a_factor_of_one_changes_nothing():
    x = torch.tensor([-1e4, -80.0, -20.0, 0.0, 20.0, 80.0, 1e4])
    out = opacity_decay(x, 0.995)
    assert torch.isfinite(out).all()
    # nearly transparent: the logit moves by log(factor); nearly opaque: it ends at logit(factor)
    assert out[0].item() == pytest.approx(-1e4 + torch.log(torch.tensor(0.995)).item(), abs=1e-2)
    assert out[-1].item() == pytest.approx(torch.logit(torch.tensor(0.995, dtype=F64)).item(), rel=1e-4)
    assert torch.all(out <= x)  # never more opaque
    assert torch.equal(opacity_decay(x, 1.0), x)


def test_the_part_acts_after_its_start_in_place():
    params = {"opacity": torch.zeros(5, requires_grad=True)}
    part = OpacityDecay(0.9, start=3, iterations=10)
    tensor = params["opacity"]
    for it in (1, 2, 3):
        part.after_step(it, params)
    assert torch.equal(params["opacity"].detach(), torch.zeros(5))
    part.after_step(4, params)
    assert params["opacity"] is tensor  # in place: the optimizer's parameter itself
    torch.testing.assert_close(torch.sigmoid(params["opacity"].detach()), torch.full((5,), 0.45))
    assert part.summary() == {"opacity_decay": {"factor": 0.9, "from_iteration": 4, "iterations": 7}}


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5])
def test_bad_factors_are_refused(bad):
    with pytest.raises(ValueError, match="opacity_decay"):
        TrainConfig(opacity_decay=bad)
    with pytest.raises(ValueError, match="factor"):
        OpacityDecay(bad, 0, 10)


def test_sparse_decays_at_the_release_factor_and_the_field_recipes_do_not(tmp_path):
    sc = write_scene(tmp_path / "s", n_views=2)
    views = load_views(sc["cameras"], sc["images"])
    cams = [torch.eye(4) for _ in views]
    names = lambda cfg: [type(p).__name__ for p in recipe_parts(cfg, views, cams, torch.Generator())]  # noqa: E731
    for recipe in ("paper", "dropgaussian", "sparse", "mcmc"):
        listed = "OpacityDecay" in names(TrainConfig(recipe=recipe, binocular_weight=0.0))
        assert listed == (recipe == "sparse"), recipe
    assert "OpacityDecay" not in names(TrainConfig(recipe="sparse", binocular_weight=0.0, opacity_decay=1.0))
    cfg = TrainConfig(recipe="paper", opacity_decay=0.995, iterations=1000)
    parts = [p for p in recipe_parts(cfg, views, cams, torch.Generator()) if isinstance(p, OpacityDecay)]
    assert len(parts) == 1 and parts[0].start == cfg.schedule().densify_from == 17


def test_a_run_with_the_decay_prunes_what_no_view_holds_up(tmp_path):
    """Through the trainer: ten Gaussians behind every camera (no gradient ever reaches them)
    keep their opacity without the decay; with it they fade below the prune threshold and are
    removed, while the Gaussians the views see survive; the run stays finite and train.json
    says when the decay acted."""
    sc = write_scene(tmp_path / "s", n_views=3)
    seed, k = read_gaussian_ply(sc["seed"]), 10
    hidden = np.random.default_rng(0).uniform(-1.0, 1.0, (k, 3)) + np.array([0.0, 0.0, -20.0])
    more = lambda a: np.concatenate([a, a[:k]])  # noqa: E731
    write_gaussian_ply(sc["seed"], GaussianCloud(
        means=np.concatenate([seed.means, hidden]), sh_dc=more(seed.sh_dc), sh_rest=more(seed.sh_rest),
        opacity_logit=more(seed.opacity_logit), log_scales=more(seed.log_scales), quats=more(seed.quats)))
    base = dict(recipe="paper", iterations=60, eval_every=0, checkpoint_every=10**6, device="cpu",
                densify_from=5, densify_until=61, densify_every=10, opacity_reset_every=0)
    train(sc["seed"], sc["cameras"], sc["images"], tmp_path / "on", TrainConfig(opacity_decay=0.9, **base))
    train(sc["seed"], sc["cameras"], sc["images"], tmp_path / "off", TrainConfig(**base))
    on, off = (json.loads((tmp_path / d / "train.json").read_text()) for d in ("on", "off"))
    assert on["opacity_decay"] == {"factor": 0.9, "from_iteration": 6, "iterations": 55}
    assert "opacity_decay" not in off
    m_on, m_off = (read_gaussian_ply(tmp_path / d / "model.ply") for d in ("on", "off"))
    behind = lambda m: int((m.means[:, 2] < -10.0).sum())  # noqa: E731
    assert behind(m_off) == k and behind(m_on) == 0
    assert len(m_on) > len(seed)  # the seen ones survive (and grew)
    for m in (m_on, m_off):
        assert np.isfinite(m.opacity_logit).all() and np.isfinite(m.means).all()
