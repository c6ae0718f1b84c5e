"""The ``mcmc`` recipe (splat_train.strategy.mcmc, 3DGS as MCMC): the relocation formula, relocation and
growth with their Adam moments, the noise, the regularisers, the recipe's values, a capped run
through the CLI, exact resume, and the gsplat backend path."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _train_scene import kill_at_loss_call, write_scene
from camio.ply import GaussianCloud, read_gaussian_ply, write_gaussian_ply
from splat_train.training.checkpoint import list_checkpoints, load_checkpoint
from splat_train.config import TrainConfig
from splat_train.strategy.densify import quat_to_rotmat
from splat_train.export import render_params
from splat_train.gaussians import make_optimizer
from splat_train.losses import gaussian_regularisers, photometric_loss
from splat_train.tree import OptimConfig
from splat_train.strategy.mcmc import (MAX_COPIES, MCMCStrategy, growth_target, inject_noise, refine_steps, relocate,
                              relocation_opacity_scale)
from splat_train.recipes import RECIPES
from splat_train.training.trainer import train

REPO = Path(__file__).resolve().parents[1]
D = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def scene(tmp_path_factory, one_thread):
    return write_scene(tmp_path_factory.mktemp("scene"), n_views=4, n_test=2)


# ---------------------------------------------------------------- the relocation formula
def _eq9_scale_factor(o: float, o_new: float, n: int) -> float:
    """The paper's Eq. 9 as written (the double loop of gsplat's kernel): o / sum_i sum_k ..."""
    denom = sum(math.comb(i - 1, k) * (-1) ** k / math.sqrt(k + 1) * o_new ** (k + 1)
                for i in range(1, n + 1) for k in range(i))
    return o / denom


def test_relocation_keeps_the_composited_opacity_and_matches_eq9_float64():
    g = torch.Generator().manual_seed(0)
    o = torch.rand(150, generator=g, dtype=D) * 0.98 + 0.01
    n = torch.randint(1, MAX_COPIES + 1, (150,), generator=g)
    s = torch.rand(150, 3, generator=g, dtype=D) + 0.1
    o_new, s_new = relocation_opacity_scale(o, s, n, min_opacity=0.0)
    assert o_new.dtype == s_new.dtype == D
    # n copies of the new Gaussian composited over one pixel give back the old opacity
    torch.testing.assert_close(1 - (1 - o_new) ** n, o, rtol=1e-12, atol=1e-12)
    ref = torch.tensor([_eq9_scale_factor(float(a), float(b), int(k)) for a, b, k in zip(o, o_new, n)], dtype=D)
    torch.testing.assert_close(s_new, ref[:, None] * s, rtol=1e-9, atol=1e-12)
    # one copy changes nothing; more copies are each fainter and smaller than the source
    o1, s1 = relocation_opacity_scale(o, s, torch.ones_like(n))
    torch.testing.assert_close(o1, o, rtol=0, atol=1e-15)
    torch.testing.assert_close(s1, s, rtol=1e-14, atol=0)
    many = n > 1
    assert (o_new[many] < o[many]).all() and (s_new[many] < s[many]).all()


def test_relocation_clamps_copies_and_opacity_as_gsplat():
    o = torch.tensor([0.5, 0.5, 0.004, 0.9999999], dtype=torch.float32)
    s = torch.ones(4, 3)
    o_new, s_new = relocation_opacity_scale(o, s, torch.tensor([MAX_COPIES, 10 * MAX_COPIES, 3, 1]), 0.005)
    assert o_new[0] == o_new[1] and torch.equal(s_new[0], s_new[1])  # beyond MAX_COPIES: as MAX_COPIES
    assert o_new[2] == pytest.approx(0.005)  # never below the dead threshold
    assert o_new[3] <= 1 - torch.finfo(torch.float32).eps
    assert o_new.dtype == torch.float32 and torch.isfinite(s_new).all()


# ---------------------------------------------------------------- relocation, growth, noise
def _params(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.randn(n, 3, generator=g), "sh_dc": torch.rand(n, 3, generator=g),
        "sh_rest": torch.zeros(n, 15, 3), "opacity": torch.logit(torch.rand(n, generator=g) * 0.8 + 0.1),
        "scales": torch.log(torch.rand(n, 3, generator=g) * 0.1 + 0.01), "quats": torch.randn(n, 4, generator=g),
    }
    params = {k: torch.nn.Parameter(v) for k, v in params.items()}
    opt = make_optimizer(params, TrainConfig(device="cpu"), 1.0)
    # one Adam step so that every row has non-zero moments
    loss = sum((p ** 2).sum() for p in params.values())
    loss.backward()
    opt.step()
    opt.zero_grad(set_to_none=True)
    return params, opt


def _moments(opt, params, name):
    st = opt.state[params[name]]
    return st["exp_avg"], st["exp_avg_sq"]


def test_dead_gaussians_are_relocated_onto_live_ones_with_zero_moments():
    params, opt = _params()
    dead = torch.zeros(40, dtype=torch.bool)
    dead[[3, 7, 20, 21, 39]] = True
    with torch.no_grad():
        params["opacity"][dead] = torch.logit(torch.tensor(0.001))
    before = {k: p.detach().clone() for k, p in params.items()}
    o_before = torch.sigmoid(before["opacity"]).double()
    m_before = {k: _moments(opt, params, k)[0].clone() for k in params}
    n = relocate(params, opt, dead, 0.005, torch.Generator().manual_seed(1))
    assert n == 5 and params["means"].shape[0] == 40
    o = torch.sigmoid(params["opacity"].detach())
    assert (o >= 0.005).all()  # no dead Gaussian left
    # each relocated row is a copy of a live source; the source's stack keeps its opacity
    changed = (params["opacity"].detach() != before["opacity"]) & ~dead
    sources = changed.nonzero().squeeze(1)
    assert 1 <= len(sources) <= 5
    for src in sources:
        copies = [int(d) for d in dead.nonzero().squeeze(1)
                  if torch.equal(params["means"][d], params["means"][src])]
        stack = [int(src), *copies]
        assert len(copies) >= 1
        for k in params:
            for d in copies:
                assert torch.equal(params[k][d], params[k][src]), k
        assert 1 - torch.prod(1 - o[stack].double()) == pytest.approx(float(o_before[src]), rel=1e-5)
    touched = dead | changed
    for k in params:
        m, v = _moments(opt, params, k)
        assert (m[touched] == 0).all() and (v[touched] == 0).all(), k
        assert torch.equal(m[~touched], m_before[k][~touched]), k  # the others keep theirs
        assert torch.equal(params[k].detach()[~touched], before[k][~touched]), k


def test_a_refine_step_relocates_then_grows_5_percent_to_the_cap():
    params, opt = _params(n=40)
    with torch.no_grad():
        params["opacity"][:6] = -9.0  # sigmoid < 0.005: dead
    strat = MCMCStrategy(refine_from=0, refine_until=100, refine_every=10, cap=43, min_opacity=0.005, noise_lr=5e5)
    state = strat.init_state(40)
    gen = torch.Generator().manual_seed(0)
    assert strat.step(params, opt, state, 5, 1.0, gen) == {"relocated": 0, "added": 0}  # not a refine step
    assert (torch.sigmoid(params["opacity"].detach()) < 0.005).sum() == 6
    out = strat.step(params, opt, state, 10, 1.0, gen)
    assert out == {"relocated": 6, "added": 2}  # int(1.05 * 40) = 42
    assert (torch.sigmoid(params["opacity"].detach()) < 0.005).sum() == 0
    assert all(p.shape[0] == 42 for p in params.values())
    for k in params:
        m, v = _moments(opt, params, k)
        assert m.shape[0] == 42 and (m[40:] == 0).all() and (v[40:] == 0).all()
    strat.step(params, opt, state, 20, 1.0, gen)
    assert params["means"].shape[0] == 43  # the cap, not int(1.05 * 42) = 44
    strat.step(params, opt, state, 30, 1.0, gen)
    assert params["means"].shape[0] == 43
    assert int(state["relocated"]) == 6 and int(state["added"]) == 3
    assert all(torch.isfinite(p).all() for p in params.values())


def test_refine_steps_count_the_refine_iterations_of_the_window():
    its = [it for it in range(1, 3001) if 50 < it < 2500 and it % 20 == 0]  # the step() test
    assert refine_steps(50, 2500, 20, 3000) == len(its) == 122
    for it in (1, 50, 60, 61, 1000, 2499, 2500, 2999):
        assert refine_steps(50, 2500, 20, it) == sum(1 for i in its if i <= it), it
    assert refine_steps(100, 100, 20, 500) == 0


def test_growth_is_gsplats_5_percent_unless_the_seed_cannot_reach_the_cap():
    # a seed that 5 % per step takes to the cap: gsplat's int(1.05 N) exactly, whatever the seed
    for n in (40, 1000, 5000):
        assert growth_target(n, 3, 100, 1000, 100_000) == int(1.05 * n)
        assert growth_target(n, 3, 100, None, 100_000) == int(1.05 * n)
    # a 13-Gaussian seed: gsplat's rule never grows it (int(1.05 x 13) = 13) ...
    assert growth_target(13, 1, 122, None, 37_000) == 13
    # ... the path to the cap does, at least as fast as 5 %, and ends on the cap at the last step
    n, counts = 13, []
    for step in range(1, 123):
        nxt = growth_target(n, step, 122, 13, 37_000)
        assert int(1.05 * n) <= nxt <= 37_000 and nxt > n
        n = nxt
        counts.append(n)
    assert counts[-1] == 37_000 and counts[0] == 14
    rate = (37_000 / 13) ** (1 / 122)  # the geometric path: the middle step is at sqrt(13 x cap)
    assert abs(counts[60] / (13 * rate ** 61) - 1) < 1e-3
    # a seed at or over the cap, or past the cap already: nothing added
    assert growth_target(50_000, 5, 122, 50_000, 37_000) == 50_000
    assert growth_target(37_000, 5, 122, 13, 37_000) == 37_000


def test_noise_is_covariance_shaped_and_gated_to_transparent_gaussians():
    n = 3
    params = {"means": torch.zeros(n, 3, dtype=D), "opacity": torch.logit(torch.tensor([0.001, 0.5, 0.99], dtype=D)),
              "scales": torch.log(torch.tensor([[0.1, 0.2, 0.3]] * n, dtype=D)),
              "quats": torch.tensor([[0.9, 0.1, -0.3, 0.2]] * n, dtype=D)}
    inject_noise(params, 2.0, torch.Generator().manual_seed(3))
    eps = torch.randn((n, 3), generator=torch.Generator().manual_seed(3), dtype=D)
    R = quat_to_rotmat(params["quats"])
    cov = R @ torch.diag_embed(torch.exp(params["scales"]) ** 2) @ R.transpose(1, 2)
    gate = torch.sigmoid(-100 * (torch.sigmoid(params["opacity"]) - 0.005))
    torch.testing.assert_close(params["means"], torch.einsum("nij,nj->ni", cov, eps) * (2.0 * gate)[:, None],
                               rtol=1e-12, atol=1e-15)
    step = params["means"].norm(dim=1)
    assert step[0] > 1e3 * step[2] and step[2] < 1e-30  # the opaque Gaussian stays put


def test_regularisers_add_their_gradient_through_the_rasterizer(scene):
    """opacity_reg mean(sigmoid(o)) + scale_reg mean(exp(s)): the loss and the gradient of the
    trained parameters are the photometric ones plus the analytic terms (the CPU backend writes
    some gradients directly; these must still add)."""
    from splat_train.data import load_views
    from splat_train.export import camera_tensors
    from splat_train.gaussians import params_from_cloud

    view = load_views(scene["cameras"], scene["images"])[0]
    cw, K = camera_tensors(view.camera, "cpu")
    grads = {}
    for w in (0.0, 0.5):
        params = params_from_cloud(read_gaussian_ply(scene["seed"]), 0)
        out = render_params(params, 0, cw, K, view.camera.width, view.camera.height, torch.zeros(3))
        loss = photometric_loss(out["rgb"], torch.as_tensor(view.image), OptimConfig.lambda_dssim)[0]
        reg = gaussian_regularisers(params["opacity"], params["scales"], w, 2 * w)
        assert (reg is None) == (w == 0)
        (loss if reg is None else loss + reg).backward()
        grads[w] = {k: params[k].grad.clone() for k in ("opacity", "scales")}
    o, s = params["opacity"].detach(), params["scales"].detach()
    sig = torch.sigmoid(o)
    torch.testing.assert_close(grads[0.5]["opacity"] - grads[0.0]["opacity"], 0.5 * sig * (1 - sig) / len(o),
                               rtol=1e-4, atol=1e-9)
    torch.testing.assert_close(grads[0.5]["scales"] - grads[0.0]["scales"], 1.0 * torch.exp(s) / s.numel(),
                               rtol=1e-4, atol=1e-9)


# ---------------------------------------------------------------- the recipe
def test_mcmc_recipe_values_are_gsplats_preset_scaled_to_the_run():
    r = RECIPES["mcmc"].to_flat()
    assert r["strategy"] == "mcmc" and r["opacity_reg"] == r["scale_reg"] == 0.01
    shares = RECIPES["mcmc"].shares
    assert shares.densify_every == 100 / 30000 and shares.opacity_reset_every is None
    assert r["dropout_rate"] == r["depth_weight"] == 0.0 and r["gaussians_per_pixel"] == 0.175
    assert r["mcmc_growth"] == "reach_cap" and TrainConfig(recipe="sparse").mcmc_growth == "gsplat"
    cfg = TrainConfig(recipe="mcmc", iterations=30000)
    s = cfg.schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == (
        500, 25000, 100, 0, 1000)
    assert cfg.max_gaussians_for(3 * 504 * 378) == 100018  # LLFF 3 views at 1/8: ~100k
    assert (cfg.noise_lr, cfg.prune_opacity) == (5e5, 0.005)
    # a shorter run refines as often relative to its length (never more often than every 20)
    assert TrainConfig(recipe="mcmc", iterations=3000).schedule().densify_every == 20
    assert TrainConfig(recipe="mcmc", iterations=10000).schedule().densify_every == 33
    strat = MCMCStrategy.from_config(cfg, 1000)
    assert (strat.refine_from, strat.refine_until, strat.refine_every, strat.cap, strat.min_opacity) == (
        500, 25000, 100, 1000, 0.005)
    for other in ("paper", "dropgaussian"):
        c = TrainConfig(recipe=other)
        assert c.strategy == "densify" and c.opacity_reg == c.scale_reg == 0.0
    # sparse grows as 3DGS does and borrows only the opacity regulariser
    c = TrainConfig(recipe="sparse")
    assert c.strategy == "densify" and (c.opacity_reg, c.scale_reg) == (0.01, 0.0)
    with pytest.raises(ValueError, match="cap"):
        TrainConfig(recipe="mcmc", gaussians_per_pixel=0)
    with pytest.raises(ValueError, match="strategy"):
        TrainConfig(strategy="relocate")


def test_cli_mcmc_with_a_binding_cap_grows_to_it_and_stays(scene, tmp_path):
    """python -m splat_train --recipe mcmc, 100 iterations, cap 90 on a 60-Gaussian seed: the
    count grows 5 % per refine step, reaches the cap, never falls, and the loss falls."""
    over = {"max_gaussians": 90, "densify_every": 4, "sh_degree": 0, "eval_every": 50, "device": "cpu",
            "checkpoint_every": 1000}
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "splat_train", "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]),
           "--images", str(scene["images"]), "--out", str(out), "--iterations", "100", "--recipe", "mcmc",
           "--test-cameras", str(scene["test_cameras"]), "--test-images", str(scene["test_images"]),
           "--config", json.dumps(over), "-q"]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    df = pq.read_table(out / "log.parquet").to_pandas()
    n = df["num_gaussians"].to_numpy()
    assert (np.diff(n) >= 0).all() and n[0] == 60 and n.max() == 90 and (n[-30:] == 90).all()
    assert np.isfinite(df["loss"]).all() and df["loss"].iloc[-10:].mean() < df["loss"].iloc[:10].mean()
    tj = json.loads((out / "train.json").read_text())
    assert tj["recipe"] == "mcmc" and tj["config"]["strategy"] == "mcmc" and tj["max_gaussians"] == 90
    assert tj["strategy_totals"]["added"] == 30 and tj["num_gaussians"] == 90 and tj["test_psnr"] > 15
    cloud = read_gaussian_ply(out / "model.ply")
    assert len(cloud) == 90 and np.isfinite(cloud.means).all()


@pytest.mark.parametrize("growth", ["reach_cap", "gsplat"])
def test_cli_mcmc_from_a_13_gaussian_seed_reaches_its_cap(scene, tmp_path, growth):
    """python -m splat_train --recipe mcmc on a seed of 13 Gaussians (what three views
    triangulate on some scenes), cap 90: the recipe's growth reaches the cap by the end of the
    refine window and keeps it; gsplat's 5 % never grows the seed (int(1.05 x 13) = 13)."""
    full = read_gaussian_ply(scene["seed"])
    small = tmp_path / "seed13.ply"
    write_gaussian_ply(small, GaussianCloud(full.means[:13], full.sh_dc[:13], full.sh_rest[:13],
                                            full.opacity_logit[:13], full.log_scales[:13], full.quats[:13]))
    over = {"max_gaussians": 90, "densify_every": 4, "sh_degree": 0, "eval_every": 50, "device": "cpu",
            "checkpoint_every": 1000, **({"mcmc_growth": growth} if growth == "gsplat" else {})}
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "splat_train", "--seed-ply", str(small), "--cameras", str(scene["cameras"]),
           "--images", str(scene["images"]), "--out", str(out), "--iterations", "100", "--recipe", "mcmc",
           "--config", json.dumps(over), "-q"]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    n = pq.read_table(out / "log.parquet").to_pandas()["num_gaussians"].to_numpy()
    tj = json.loads((out / "train.json").read_text())
    assert tj["seed_gaussians"] == 13 and tj["config"]["mcmc_growth"] == growth
    assert (np.diff(n) >= 0).all() and n[0] == 13
    if growth == "gsplat":
        assert (n == 13).all() and tj["strategy_totals"]["added"] == 0
    else:  # refine steps at 4, 8, ..., 80 (the window ends at 25000/30000 of the run)
        assert n[79] == 90 and n[78] < 90 and (n[79:] == 90).all()
        assert tj["num_gaussians"] == 90 and tj["strategy_totals"]["added"] == 77
    assert np.isfinite(read_gaussian_ply(out / "model.ply").means).all()


def test_cli_refuses_mcmc_without_a_cap_in_one_line(scene, tmp_path):
    cmd = [sys.executable, "-m", "splat_train", "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]),
           "--images", str(scene["images"]), "--out", str(tmp_path / "o"), "--recipe", "mcmc",
           "--config", '{"gaussians_per_pixel": 0}']
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "mcmc strategy grows to a cap" in r.stderr


# ---------------------------------------------------------------- checkpoint / resume
MCMC_SMALL = dict(iterations=24, recipe="mcmc", densify_from=2, densify_until=24, densify_every=6,
                  max_gaussians=75, sh_increase_every=10, checkpoint_every=8, eval_every=12, device="cpu",
                  keep_checkpoints=5)


def test_resume_of_an_mcmc_run_gives_the_identical_model(scene, tmp_path, monkeypatch):
    """Killed in iteration 19 (checkpoints at 8 and 16, refine steps at 6, 12, 18), resumed to
    24: the model, the log and the strategy totals equal an uninterrupted run's (the generator
    that draws relocations and noise is in the checkpoint)."""
    cfg = TrainConfig(**MCMC_SMALL)

    def run(out):
        return train(scene["seed"], scene["cameras"], scene["images"], out, cfg,
                     test_cameras=scene["test_cameras"], test_images=scene["test_images"])

    full, part = tmp_path / "full", tmp_path / "part"
    run(full)
    restore = kill_at_loss_call(monkeypatch, 19)
    with pytest.raises(KeyboardInterrupt):
        run(part)
    ck = load_checkpoint(list_checkpoints(part)[-1][1])
    assert ck["iteration"] == 16 and set(ck["strategy_state"]) == {"relocated", "added"}
    assert int(ck["strategy_state"]["added"]) > 0
    restore()
    res = run(part)
    assert res.summary["resumed_from"].endswith("ckpt_0000016.pt")
    a, b = read_gaussian_ply(full / "model.ply"), read_gaussian_ply(part / "model.ply")
    assert len(a) == len(b) > 60
    for k in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    la = pq.read_table(full / "log.parquet").to_pandas()
    lb = pq.read_table(part / "log.parquet").to_pandas()
    np.testing.assert_array_equal(la["loss"], lb["loss"])
    np.testing.assert_array_equal(la["num_gaussians"], lb["num_gaussians"])
    sa = json.loads((full / "train.json").read_text())["strategy_totals"]
    assert sa == res.summary["strategy_totals"] and sa["added"] == len(a) - 60


# ---------------------------------------------------------------- gsplat backend
def test_mcmc_trains_through_the_gsplat_adapter(scene, tmp_path, monkeypatch):
    """The same mcmc run through the gsplat adapter (its CPU stand-in tests/_fake_gsplat.py)
    and through the reference rasterizer: same growth, same fit."""
    pytest.importorskip("gsplat", reason="gsplat is in the dev extra: pip install -e '.[dev]'")
    import _fake_gsplat
    from splat_train.render import _gsplat_backend

    monkeypatch.setattr(_gsplat_backend, "_rasterization", lambda: _fake_gsplat.rasterization)
    summaries = {}
    for backend in ("reference", "gsplat"):
        cfg = TrainConfig(**{**MCMC_SMALL, "rasterizer": backend, "checkpoint_every": 1000})
        res = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / backend, cfg)
        summaries[backend] = res.summary
        assert res.summary["rasterizer"] == backend
    got, ref = summaries["gsplat"], summaries["reference"]
    assert got["num_gaussians"] == ref["num_gaussians"] == 60 + got["strategy_totals"]["added"] > 60
    assert abs(got["train_psnr"] - ref["train_psnr"]) < 0.5 and got["train_psnr"] > 15
