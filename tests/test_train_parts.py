"""The training parts (splat_train.parts.base, splat_train.parts.compose): which parts each recipe runs,
and that a run through the parts is the loop written out by hand, bit for bit: Gaussian
dropout, the depth prior, the opacity / scale regularisers and pose (and focal) refinement all
on, against a reference step that calls the functional definitions directly
(dropout_rate_at / gaussian_dropout, depth_weight_at / the Pearson loss, gaussian_regularisers,
PoseCorrections / pose_lr_factor) in the order the trainer documents. Also: a checkpoint
written before the parts (pose state under "pose") still resumes exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _train_scene import make_cloud, write_scene
from camio.colmap import read_model
from camio.depth_prior import DEPTH_PRIOR_FILE, DepthSamples, write_depth_prior
from splat_train.parts.binocular import binocular_consistency_loss, shifted_camera
from splat_train.config import TrainConfig
from splat_train.render.cpu.optim import adam_step
from splat_train.data import load_views
from splat_train.parts.depth_prior import depth_weight_at
from splat_train.parts.dropout import dropout_rate_at, gaussian_dropout
from splat_train.export import render_params
from splat_train.gaussians import position_lr
from splat_train.losses import gaussian_regularisers, photometric_loss
from splat_train.parts.opacity_decay import opacity_decay
from splat_train.parts.compose import recipe_parts
from splat_train.parts.pose import PoseCorrections, camera_spread, pose_lr_factor
from splat_train.training.trainer import Trainer, train

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _part(trainer, name):
    """The trainer's part named ``name`` (the parts are reached by name, never by type)."""
    return next(p for p in trainer.parts if p.name == name)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three 32x24 views of 60 Gaussians, with a depth prior beside the seed: the true camera
    z of every Gaussian centre, affinely changed (the Pearson loss ignores scale and shift),
    with weights from 0.2 to 1."""
    sc = write_scene(tmp_path_factory.mktemp("parts"), n_views=3)
    cams = read_model(sc["cameras"]).cameras
    pts = make_cloud().means
    view, xy, z = [], [], []
    for k, c in enumerate(cams):
        x = pts @ c.cam_from_world[:3, :3].T + c.cam_from_world[:3, 3]
        view += [k] * len(pts)
        xy.append((x @ c.K.T)[:, :2] / x[:, 2:])
        z.append(1.7 * x[:, 2] + 0.3)
    write_depth_prior(sc["seed"].parent / DEPTH_PRIOR_FILE,
                      DepthSamples([c.name for c in cams], [[c.width, c.height] for c in cams], view,
                                   np.concatenate(xy), np.concatenate(z),
                                   np.tile(np.linspace(0.2, 1.0, len(pts)), len(cams)), "dense"))
    return sc


ALL_ON = dict(recipe="sparse", iterations=30, densify_from=4, densify_every=8, densify_until=25,
              densify_grad_threshold=1e-6, dropout_rate=0.3, dropout_ramp_fraction=0.5, depth_weight=0.5,
              depth_ramp_fraction=0.2,
              opacity_reg=0.01, scale_reg=0.01, opacity_decay=0.98, pose_refine=True, pose_refine_focal=True, pose_refine_from=5,
              pose_warmup=5, lr_pose=3e-3, lr_focal=1e-3, random_background=True, eval_every=0,
              checkpoint_every=10**6, device="cpu")


def _names(cfg, scene, prior=True):
    views = load_views(scene["cameras"], scene["images"])
    cams = [torch.eye(4) for _ in views]
    targets = [torch.as_tensor(v.image) for v in views]
    return [p.name for p in recipe_parts(cfg, views, cams, torch.Generator(),
                                         scene["seed"].parent / DEPTH_PRIOR_FILE if prior else None,
                                         targets=targets, renderer=object())]


def test_each_recipe_runs_its_parts(scene):
    """paper is plain 3DGS; dropgaussian drops Gaussians; sparse drops, adds the depth prior
    (when the seed has one), the opacity regulariser, binocular consistency and the opacity
    decay; mcmc adds the
    opacity and scale regularisers; pose refinement is a part of any recipe, run last."""
    assert _names(TrainConfig(recipe="paper"), scene) == []
    assert _names(TrainConfig(recipe="dropgaussian"), scene) == ["dropout"]
    assert _names(TrainConfig(recipe="sparse"), scene) == ["dropout", "depth_prior", "regularisers", "binocular",
                                                           "opacity_decay"]
    assert _names(TrainConfig(recipe="sparse"), scene, prior=False) == ["dropout", "regularisers", "binocular",
                                                                        "opacity_decay"]
    assert _names(TrainConfig(recipe="sparse", opacity_reg=0.0, binocular_weight=0.0, opacity_decay=1.0), scene) == \
        ["dropout", "depth_prior"]
    assert _names(TrainConfig(recipe="mcmc"), scene) == ["regularisers"]
    assert _names(TrainConfig(recipe="paper", pose_refine=True), scene) == ["pose"]
    assert _names(TrainConfig(**ALL_ON), scene) == ["dropout", "depth_prior", "regularisers", "binocular", "opacity_decay",
                                                   "pose"]


def test_depth_term_acts_only_in_views_with_enough_prior_samples(scene):
    """``depth_min_samples``: the prior of each view here has 60 samples; a threshold above that
    leaves every view without a depth term, one at or below it keeps all three; below 2 (where
    a correlation is undefined) the config is refused."""
    views = load_views(scene["cameras"], scene["images"])

    def prior_views(**kw):
        parts = recipe_parts(TrainConfig(recipe="sparse", binocular_weight=0.0, **kw), views,
                             [torch.eye(4) for _ in views], torch.Generator(), scene["seed"].parent / DEPTH_PRIOR_FILE)
        return sorted(next(p for p in parts if p.name == "depth_prior").prior.views)

    assert prior_views() == sorted(v.name for v in views)  # the default, 16
    assert prior_views(depth_min_samples=60) == sorted(v.name for v in views)
    assert prior_views(depth_min_samples=61) == []
    with pytest.raises(ValueError, match="depth_min_samples"):
        TrainConfig(recipe="sparse", depth_min_samples=1)


def _reference_run(cfg, scene, out):
    """The iteration written out by hand (no parts), on a trainer whose parts list is emptied:
    view, random background, pose-corrected camera, dropped opacities, photometric loss + depth term
    + regularisers, backward, statistics, Gaussian Adam, pose Adam with its ramp and gauge,
    then the densification step."""
    tr = Trainer(cfg, scene["seed"], load_views(scene["cameras"], scene["images"]), out,
                 depth_prior=scene["seed"].parent / DEPTH_PRIOR_FILE)
    prior = _part(tr, "depth_prior").prior
    tr.parts = []
    given = [c[0] for c in tr.cams]
    pose = PoseCorrections(len(given), refine_focal=True, trans_scale=camera_spread(given))
    pose_opt = torch.optim.Adam([{"params": [pose.delta], "lr": cfg.lr_pose, "name": "pose"},
                                 {"params": [pose.log_focal], "lr": cfg.lr_focal, "name": "focal"}])
    depth_terms, binocular_terms = [], []
    for it in range(1, cfg.iterations + 1):
        tr.iteration = it
        for g in tr.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = position_lr(cfg, it, tr.extent)
        idx = tr.next_view()
        bg = torch.rand(3, generator=tr.gen)
        cam = tr.train_views[idx].camera
        cw, K = tr.cams[idx]
        if it >= cfg.pose_refine_from:
            cw, K = pose(idx, cw), pose.intrinsics(idx, K)
        rate = dropout_rate_at(it, cfg.iterations, cfg.dropout_rate, cfg.dropout_ramp_fraction)
        out_ = render_params(tr.params, tr.sched.sh_degree_at(it, cfg.sh_degree), cw, K, cam.width, cam.height,
                             bg, tr.backend, opacity_fn=lambda o: gaussian_dropout(o, rate, tr.gen))
        loss = photometric_loss(out_["rgb"], tr.targets[idx], cfg.lambda_dssim)[0]
        depth = depth_weight_at(it, cfg.iterations, cfg.depth_weight, cfg.depth_ramp_fraction) * \
            prior.views[cam.name].loss(out_["depth"])
        depth_terms.append(float(depth.detach()))
        loss = loss + depth
        loss = loss + gaussian_regularisers(tr.params["opacity"], tr.params["scales"], cfg.opacity_reg,
                                            cfg.scale_reg)
        if it > round(cfg.binocular_from_fraction * cfg.iterations):
            surface = out_["depth"].detach()[out_["alpha"].detach() > 0.5]
            shift = (2.0 * torch.rand(1, generator=tr.gen)[0] - 1.0) * cfg.binocular_shift * surface.median()
            shifted = render_params(tr.params, tr.sched.sh_degree_at(it, cfg.sh_degree),
                                    shifted_camera(cw.detach(), shift), K.detach(), cam.width, cam.height, bg,
                                    tr.backend, depth=False, stats=False)["rgb"]
            loss = loss + cfg.binocular_weight * binocular_consistency_loss(tr.targets[idx], out_["depth"], shifted,
                                                                            K[0, 0].detach(), shift)
            binocular_terms.append(it)
        loss.backward()
        tr.strategy.update_state(tr.state, out_["means2d"].grad, out_["radii"], out_["visible"], cam.width,
                                 cam.height, it)
        adam_step(tr.optimizer)
        tr.optimizer.zero_grad(set_to_none=True)
        if it > tr.sched.densify_from:
            with torch.no_grad():
                tr.params["opacity"].copy_(opacity_decay(tr.params["opacity"], cfg.opacity_decay))
        f = pose_lr_factor(it, cfg.pose_refine_from, cfg.pose_warmup)
        for g in pose_opt.param_groups:
            g["lr"] = f * (cfg.lr_pose if g["name"] == "pose" else cfg.lr_focal)
        pose_opt.step()
        pose_opt.zero_grad(set_to_none=True)
        pose.fix_scale_(given)
        tr.strategy.step(tr.params, tr.optimizer, tr.state, it, tr.extent, tr.gen)
    return tr, pose, depth_terms, binocular_terms


def test_a_run_through_the_parts_is_the_hand_written_loop_bit_for_bit(scene, tmp_path):
    """All six parts on (random background too, so that every draw of the shared generator
    is in play): the trainer's run and the hand-written loop end with identical Gaussians,
    pose and focal corrections, and every part acted."""
    cfg = TrainConfig(**ALL_ON)
    ref, ref_pose, depth_terms, binocular_terms = _reference_run(cfg, scene, tmp_path / "ref")
    tr = Trainer(cfg, scene["seed"], load_views(scene["cameras"], scene["images"]), tmp_path / "parts",
                 depth_prior=scene["seed"].parent / DEPTH_PRIOR_FILE)
    assert [p.name for p in tr.parts] == ["dropout", "depth_prior", "regularisers", "binocular", "opacity_decay",
                                                   "pose"]
    res = tr.run()
    # every part acted: the model grew under dropout, the depth term was on, the cameras moved
    assert ref.num_gaussians > 60 and min(depth_terms[6:]) > 0 and binocular_terms
    assert float(ref_pose.delta.detach().abs().max()) > 0 and float(ref_pose.log_focal.detach().abs().max()) > 0
    assert res.summary["num_gaussians"] == ref.num_gaussians
    for key, p in ref.params.items():
        assert torch.equal(tr.params[key], p), key
    pose = _part(tr, "pose").corrections
    assert torch.equal(pose.delta, ref_pose.delta) and torch.equal(pose.log_focal, ref_pose.log_focal)


def test_a_checkpoint_from_before_the_parts_resumes_exactly(scene, tmp_path):
    """Checkpoints written before the training parts held the pose corrections under "pose"
    (no "parts"): such a checkpoint resumes, and ends with the uninterrupted run's model."""
    cfg = TrainConfig(**{**ALL_ON, "iterations": 20, "checkpoint_every": 10})
    full = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "full", cfg)
    ck = torch.load(tmp_path / "full" / "ckpt" / "ckpt_0000010.pt", weights_only=True)
    assert set(ck["parts"]) == {"pose"}  # dropout, depth prior, regularisers, binocular and decay hold no state
    ck["pose"] = ck.pop("parts")["pose"]
    (tmp_path / "old" / "ckpt").mkdir(parents=True)
    torch.save(ck, tmp_path / "old" / "ckpt" / "ckpt_0000010.pt")
    res = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / "old", cfg)
    assert res.summary["resumed_from"].endswith("ckpt_0000010.pt")
    assert res.summary["pose_correction"] == full.summary["pose_correction"]
    from camio.ply import read_gaussian_ply

    a, b = (read_gaussian_ply(tmp_path / d / "model.ply") for d in ("full", "old"))
    for key in ("means", "sh_dc", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
