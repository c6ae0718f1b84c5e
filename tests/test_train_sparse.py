"""The sparse-view recipe and its parts: recipes and schedules, Gaussian dropout, the depth
prior (Bridge file, Pearson loss, rendered depth through every backend), the growth cap."""

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

from _train_scene import write_scene
from camio.depth_prior import DEPTH_PRIOR_FILE, DepthSamples, read_depth_prior, write_depth_prior
from splat_train import rasterize
from splat_train.render.cpu.raster import available as kernel_available
from splat_train.recipes import RECIPE_NAMES
from splat_train.config import TrainConfig
from splat_train.strategy.densify import cap_candidates
from splat_train.parts.depth_prior import load_depth_prior, pearson_depth_loss
from splat_train.parts.dropout import dropout_rate_at, gaussian_dropout
from splat_train.export import render_params
from splat_train.training.trainer import Trainer, train

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ---------------------------------------------------------------- recipes and schedules
@pytest.mark.parametrize("iterations,expected", [
    (30000, (500, 15000, 100, 3000, 1000)),  # the 3DGS release's counts at its own length
    (10000, (167, 5000, 100, 1000, 333)),  # the same fractions; the period stays 100
    (1000, (17, 500, 100, 300, 33)),  # reset period kept >= 3 densification periods
    (300, (5, 150, 100, 300, 10)),
])
def test_paper_recipe_is_the_release_schedule_in_proportion(iterations, expected):
    s = TrainConfig(recipe="paper", iterations=iterations).schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == expected
    cfg = TrainConfig(recipe="paper", iterations=iterations)
    assert (cfg.dropout_rate, cfg.depth_weight, cfg.max_gaussians_for(10**6)) == (0.0, 0.0, None)


@pytest.mark.parametrize("iterations, expected", [
    (10000, (500, 10000, 100, 0)),  # to the end, as Binocular3DGS while its opacity decay acts
    (3000, (150, 3000, 100, 0)),
    (1000, (50, 1000, 100, 0)),  # the field's period at any length, never 1 % of the run
    (300, (15, 300, 100, 0)),
])
def test_sparse_recipe_grows_every_100_to_the_end_of_the_run_under_its_cap(iterations, expected):
    cfg = TrainConfig(recipe="sparse", iterations=iterations)
    s = cfg.schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every) == expected
    # a value the user sets is used as written, floor or not
    assert TrainConfig(recipe="sparse", iterations=iterations, densify_until=100).schedule().densify_until == 100
    assert s.source["opacity_reset_every"] == "recipe sparse: never"
    assert cfg.opacity_decay == 0.995 and TrainConfig(recipe="paper").opacity_decay == 1.0
    assert cfg.max_gaussians_for(571_000) == 57_100  # 0.1 per training pixel
    assert TrainConfig(recipe="sparse", iterations=10000, max_gaussians=1000).max_gaussians_for(571_000) == 1000
    assert TrainConfig(recipe="sparse", iterations=10000, gaussians_per_pixel=0).max_gaussians_for(571_000) is None
    # a period that is a fraction of the run (mcmc's 100/30000) never falls below MIN_DENSIFY_EVERY
    assert TrainConfig(recipe="mcmc", iterations=300).schedule().densify_every == 20


def test_a_schedule_value_means_what_it_says():
    """A value the user sets is iterations of this run: 3,000 iterations with densify_until
    1500 stop growth at 1500 (it used to be rescaled to 450); the source is recorded."""
    s = TrainConfig(recipe="paper", iterations=3000, densify_until=1500).schedule()
    assert s.densify_until == 1500 and s.source["densify_until"] == "set"
    assert s.densify_from == 50 and s.source["densify_from"].startswith("recipe paper")


@pytest.mark.parametrize("bad", [{"recipe": "fast"}, {"dropout_rate": 1.0}, {"depth_weight": -1},
                                 {"gaussians_per_pixel": -0.1}, {"densify_every": 0}, {"max_gaussians": 0}])
def test_bad_recipe_values_are_refused(bad):
    with pytest.raises(ValueError):
        TrainConfig(iterations=10, **bad)


def test_cli_lists_recipe_and_schema_has_it():
    out = subprocess.run([sys.executable, "-m", "splat_train", "--help"], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0 and "--recipe {" + ",".join(RECIPE_NAMES) + "}" in out.stdout
    from splat_train.recipes import RECIPE_SUMMARIES
    assert tuple(RECIPE_SUMMARIES) == RECIPE_NAMES  # every recipe has its one line, and only they
    assert all(f"'{name}':" in " ".join(out.stdout.split()) for name in RECIPE_NAMES)
    assert "--depth-prior" in out.stdout
    sys.path.insert(0, str(REPO / "workflow" / "scripts"))
    import check_config

    train_props = check_config.load_schema()["properties"]["train"]["properties"]
    assert train_props["recipe"]["enum"] == [*RECIPE_NAMES, None]  # every recipe, in order, read from the list
    assert train_props["recipe"]["default"] is None  # null: the trainer's own default recipe


# ---------------------------------------------------------------- dropout
def test_dropout_ramp_and_identity_at_zero():
    assert dropout_rate_at(1, 100, 0.0) == 0.0
    assert dropout_rate_at(50, 100, 0.2) == pytest.approx(0.1) and dropout_rate_at(100, 100, 0.2) == 0.2
    o = torch.rand(10, dtype=torch.float64)
    assert gaussian_dropout(o, 0.0) is o


def test_dropout_ramp_over_a_fraction_of_the_run_then_holds():
    # ramped over the first 30 % of 3,000 iterations: half the rate at 450, the full rate from 900 on
    assert dropout_rate_at(450, 3000, 0.2, 0.3) == pytest.approx(0.1, abs=1e-15)
    assert dropout_rate_at(900, 3000, 0.2, 0.3) == 0.2 and dropout_rate_at(3000, 3000, 0.2, 0.3) == 0.2
    assert dropout_rate_at(1, 3000, 0.2, 0.0) == 0.2  # no ramp: the final rate from the start
    assert dropout_rate_at(450, 3000, 0.2) == dropout_rate_at(450, 3000, 0.2, 1.0)  # DropGaussian's ramp
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="dropout_ramp_fraction"):
            TrainConfig(recipe="sparse", dropout_ramp_fraction=bad, device="cpu")


def test_dropout_compensates_expected_opacity():
    """E[dropped opacity] = opacity: the mean over 4000 draws is within 4.5 binomial standard
    errors of it (fixed generator seed: the outcome is the same on every run)."""
    o = torch.linspace(0.05, 1.0, 20, dtype=torch.float64)
    p, draws = 0.2, 4000
    g = torch.Generator().manual_seed(0)
    mean = torch.stack([gaussian_dropout(o, p, g) for _ in range(draws)]).mean(0)
    se = o * math.sqrt(p / (1 - p) / draws)
    assert ((mean - o).abs() <= 4.5 * se).all()
    one = gaussian_dropout(o, p, torch.Generator().manual_seed(1))
    ratio = one / o
    assert torch.all((ratio == 0) | torch.isclose(ratio, torch.tensor(1 / (1 - p), dtype=torch.float64)))
    assert (ratio == 0).any() and (ratio > 0).any()


def test_dropout_acts_in_training_only(tmp_path):
    """The trainer's step drops Gaussians; the renders that are scored (evaluate) do not: two
    evaluations of the same model agree exactly whatever the dropout rate."""
    sc = write_scene(tmp_path / "s", n_views=3, n_test=1)
    from splat_train.data import load_views

    views = load_views(sc["cameras"], sc["images"])
    tests = load_views(sc["test_cameras"], sc["test_images"])
    tr = Trainer(TrainConfig(iterations=20, recipe="sparse", dropout_rate=0.9, device="cpu", eval_every=0),
                 sc["seed"], views, tmp_path / "o", tests)
    tr.iteration = 19
    seen = []
    import splat_train.training.trainer as tm

    real = tm.render_params

    def spy(*a, **k):
        seen.append(k.get("opacity_fn"))
        return real(*a, **k)

    tm.render_params = spy
    try:
        tr.step()
    finally:
        tm.render_params = real
    assert seen and seen[0] is not None
    opac = torch.sigmoid(tr.params["opacity"].detach())
    dropped = seen[0](opac)
    assert (dropped == 0).any() and torch.allclose(dropped[dropped > 0], opac[dropped > 0] / (1 - 0.9 * 20 / 20))
    a, b = tr.evaluate(tests), tr.evaluate(tests)
    assert a == b and math.isfinite(a)


# ---------------------------------------------------------------- Pearson depth loss
def test_pearson_loss_values_and_gradcheck():
    g = torch.Generator().manual_seed(0)
    d = torch.rand(50, generator=g, dtype=torch.float64) + 1
    w = torch.rand(50, generator=g, dtype=torch.float64)
    assert float(pearson_depth_loss(3.0 * d + 2.0, d, w)) == pytest.approx(0.0, abs=1e-12)  # scale/shift-invariant
    assert float(pearson_depth_loss(-d, d, w)) == pytest.approx(2.0, abs=1e-12)
    x = torch.rand(50, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r: pearson_depth_loss(r, d, w), (x,))
    # weighted: a sample of weight 0 does not count
    d2, r2 = d.clone(), d.clone()
    r2[0] = 100.0
    w2 = torch.ones(50, dtype=torch.float64)
    w2[0] = 0.0
    assert float(pearson_depth_loss(r2, d2, w2)) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("rendered,weight", [("const", "ones"), ("zero", "ones"), ("rand", "zeros")])
def test_pearson_loss_finite_on_degenerate_input(rendered, weight):
    prior = torch.linspace(1, 2, 30, dtype=torch.float64)
    r = {"const": torch.full((30,), 2.0), "zero": torch.zeros(30),
         "rand": torch.rand(30, generator=torch.Generator().manual_seed(0))}[rendered].double().requires_grad_(True)
    w = torch.ones(30, dtype=torch.float64) if weight == "ones" else torch.zeros(30, dtype=torch.float64)
    loss = pearson_depth_loss(r, prior, w)
    loss.backward()
    assert float(loss.detach()) == 1.0 and torch.isfinite(r.grad).all() and float(r.grad.abs().max()) == 0.0


def _depth_scene(dtype=torch.float64, n=120, seed=5):
    g = torch.Generator().manual_seed(seed)
    W, H = 37, 29
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.6, 0.5, 0.5], dtype=dtype)
    means[:, 2] += 3.0
    leaves = dict(means=means, quats=torch.randn(n, 4, generator=g, dtype=dtype),
                  scales=torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.05,
                  opacities=torch.rand(n, generator=g, dtype=dtype) * 0.6 + 0.2,
                  colors=torch.rand(n, 3, generator=g, dtype=dtype))
    for v in leaves.values():
        v.requires_grad_(True)
    K = torch.tensor([[35.0, 0, W / 2 + 0.7], [0, 36.0, H / 2 - 0.4], [0, 0, 1]], dtype=dtype)
    prior_idx = torch.randperm(W * H, generator=g)[:300]
    prior_z = 2.5 + torch.rand(300, generator=g, dtype=dtype)
    prior_w = torch.rand(300, generator=g, dtype=dtype)
    return leaves, torch.eye(4, dtype=dtype), K, W, H, (prior_idx, prior_z, prior_w)


def _depth_loss_grads(backend: str):
    leaves, cw, K, W, H, (idx, z, w) = _depth_scene()
    out = rasterize(*leaves.values(), cw, K, W, H, sh_degree=None, backend=backend)
    loss = pearson_depth_loss(out["depth"].reshape(-1)[idx], z, w)
    return out["depth"].detach(), torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)


BACKENDS = ["torch"] + (["cpu"] if kernel_available() else [])


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_loss_forward_and_backward_match_dense_reference_float64(backend):
    """The rendered expected depth and the gradient of the Pearson depth loss alone, through the
    fast backends, against the dense reference in float64 (only the summation order differs)."""
    d_ref, g_ref = _depth_loss_grads("reference")
    d, g = _depth_loss_grads(backend)
    torch.testing.assert_close(d, d_ref, rtol=1e-9, atol=1e-10)
    for name, a, b in zip(("means", "quats", "scales", "opacities"), g, g_ref):
        assert b is not None and float(b.abs().max()) > 0, name
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9 * (1 + float(b.abs().max())), msg=name)


# ---------------------------------------------------------------- depth-prior file
def test_depth_prior_file_round_trip_and_resampling(tmp_path):
    s = DepthSamples(["a.png", "b.png"], [[40, 30], [40, 30]], [0] * 20 + [1] * 3,
                     np.c_[np.linspace(0.5, 39.5, 23), np.linspace(0.5, 29.5, 23)], np.linspace(1, 2, 23),
                     np.r_[np.ones(22), 0.0], "dense")
    p = write_depth_prior(tmp_path / DEPTH_PRIOR_FILE, s)
    r = read_depth_prior(p)
    assert r.image_names == ["a.png", "b.png"] and r.source == "dense"
    np.testing.assert_array_equal(r.z, s.z)
    prior = load_depth_prior(p, {"a.png": (20, 15), "b.png": (40, 30)}, min_samples=3)
    assert set(prior.views) == {"a.png"}  # b has 2 usable samples (one of weight 0) < 3
    v = prior.views["a.png"]
    xy = s.xy[:20].astype(np.float64)
    np.testing.assert_array_equal(v.index.numpy(), np.floor(xy[:, 1] / 2) * 20 + np.floor(xy[:, 0] / 2))
    with pytest.raises(ValueError, match="not a readable depth prior"):
        np.savez(tmp_path / "bad.npz", z=np.ones(3))
        read_depth_prior(tmp_path / "bad.npz")


def _prior_two_views(tmp_path):
    g = np.random.default_rng(0)
    xy = np.c_[g.uniform(0, 40, 60), g.uniform(0, 30, 60)]
    s = DepthSamples(["a.png", "b.png"], [[40, 30], [40, 30]], [0] * 30 + [1] * 30, xy, g.uniform(1, 3, 60),
                     g.uniform(0.2, 1, 60), "dense")
    return load_depth_prior(write_depth_prior(tmp_path / DEPTH_PRIOR_FILE, s), {"a.png": (40, 30), "b.png": (40, 30)})


def test_depth_term_as_a_graph_per_view_is_the_op_by_op_term(tmp_path, monkeypatch, caplog):
    """On CUDA the depth term runs as one graph per view (splat_train.losses.graphed_checked);
    here torch.cuda.make_graphed_callables is stood in for by a function that records its
    capture and runs the term: built once per view at its first call, the same value and
    gradient as the op-by-op term (float64); a graph that disagrees with the op-by-op term is
    dropped with a warning and that view stays op by op."""
    from splat_train.parts.depth_prior import DepthPriorLoss

    prior = _prior_two_views(tmp_path)
    captured = []

    def make_graphed(fn, sample):
        captured.append(tuple(a.shape for a in sample))
        return lambda *args: fn(*args)

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", make_graphed)
    graphed = DepthPriorLoss(prior, ["a.png", "b.png"], 0.05, 0.1, 100, graphs=True)
    assert not graphed.use_graphs  # a prior on the CPU is never graphed...
    graphed.use_graphs = True  # ...but the same path runs here with the stand-in
    eager = DepthPriorLoss(prior, ["a.png", "b.png"], 0.05, 0.1, 100, graphs=False)
    g = torch.Generator().manual_seed(1)
    for it, view in ((20, 0), (30, 0), (40, 1), (50, 1)):
        depth = 1 + torch.rand(30, 40, generator=g, dtype=torch.float64)
        d1, d2 = depth.clone().requires_grad_(True), depth.clone().requires_grad_(True)
        got = graphed.loss(it, view, {"depth": d1}, {})
        ref = eager.loss(it, view, {"depth": d2}, {})
        got.backward()
        ref.backward()
        assert got.item() == ref.item() and torch.equal(d1.grad, d2.grad)
    assert captured == [((30, 40),), ((30, 40),)]  # one capture per view, at its first call
    monkeypatch.setattr(torch.cuda, "make_graphed_callables", lambda fn, sample: lambda *a: fn(*a) * 1.01)
    wrong = DepthPriorLoss(prior, ["a.png", "b.png"], 0.05, 0.1, 100, graphs=True)
    wrong.use_graphs = True
    depth = 1 + torch.rand(30, 40, generator=g, dtype=torch.float64)
    with caplog.at_level("WARNING"):
        got = wrong.loss(50, 0, {"depth": depth.clone().requires_grad_(True)}, {})
    assert "depth prior term of a.png as a CUDA graph unavailable" in caplog.text
    assert wrong._graphed == {"a.png": None}
    assert got.item() == eager.loss(50, 0, {"depth": depth.clone().requires_grad_(True)}, {}).item()


# ---------------------------------------------------------------- growth cap
def test_cap_keeps_the_best_candidates():
    grads = torch.tensor([0.1, 0.9, 0.5, 0.7, 0.2, 0.8])
    clone = torch.tensor([1, 1, 0, 0, 1, 0], dtype=torch.bool)
    split = torch.tensor([0, 0, 1, 1, 0, 1], dtype=torch.bool)
    c, s = cap_candidates(clone, split, grads, room=3)
    assert c.tolist() == [False, True, False, False, False, False]
    assert s.tolist() == [False, False, False, True, False, True]
    c, s = cap_candidates(clone, split, grads, room=0)
    assert not c.any() and not s.any()
    c, s = cap_candidates(clone, split, grads, room=10)
    assert torch.equal(c, clone) and torch.equal(s, split)


def _capped_run(tmp_path, scene, name):
    cfg = TrainConfig(recipe="paper", iterations=150, densify_from=5, densify_until=150, densify_every=5,
                      opacity_reset_every=10**6, densify_grad_threshold=1e-7, prune_screen_size=4.0,
                      max_gaussians=90, sh_degree=0, eval_every=0, checkpoint_every=10**6, device="cpu")
    res = train(scene["seed"], scene["cameras"], scene["images"], tmp_path / name, cfg)
    return res, pq.read_table(tmp_path / name / "log.parquet").to_pandas()


def test_a_binding_cap_does_not_collapse_the_model(tmp_path):
    """Regression: under a cap that binds while the size prune removes Gaussians, growth used to
    stop altogether (all candidates skipped) and the model shrank and its loss rose. Now the
    room the prune frees is refilled with the best candidates: the count stays at the cap and
    the loss keeps falling."""
    scene = write_scene(tmp_path / "s", n_views=4)
    res, df = _capped_run(tmp_path, scene, "run")
    n = df["num_gaussians"].to_numpy()
    assert n.max() <= 90
    assert n[-40:].min() >= 80, n[-40:]  # refilled after every prune
    assert df["loss"].iloc[-10:].mean() < df["loss"].iloc[:10].mean()
    assert df["loss"].iloc[-10:].mean() <= 1.05 * df["loss"].iloc[40:60].mean()


def test_a_seed_over_the_cap_is_kept_or_relocated_through_the_trainer(tmp_path):
    """A 60-Gaussian seed under a cap of 30 (``seed_over_cap``, docs/reference.md section 3a):
    "cap" trains to the cap of 30, "keep" to a cap of 60, "relocate" to 60 with the mcmc
    strategy, which keeps the seed's count while it moves dead Gaussians."""
    scene = write_scene(tmp_path / "s", n_views=3)
    out = {}
    for rule in ("cap", "keep", "relocate"):
        cfg = TrainConfig(recipe="sparse", iterations=60, densify_from=5, densify_until=60, densify_every=5,
                          densify_grad_threshold=1e-7, max_gaussians=30, seed_over_cap=rule, depth_weight=0.0,
                          sh_degree=0, eval_every=0, checkpoint_every=10**6, device="cpu")
        train(scene["seed"], scene["cameras"], scene["images"], tmp_path / rule, cfg)
        summary = json.loads((tmp_path / rule / "train.json").read_text())
        n = pq.read_table(tmp_path / rule / "log.parquet").to_pandas()["num_gaussians"].to_numpy()
        out[rule] = (summary["max_gaussians"], summary["strategy"], int(n.max()), int(n[-1]))
    assert out["cap"][:2] == (30, "densify")
    assert out["keep"][:2] == (60, "densify") and out["keep"][2] <= 60
    assert out["relocate"][:2] == (60, "mcmc") and out["relocate"][2:] == (60, 60)


# ---------------------------------------------------------------- the chain: Bridge -> trainer
def test_bridge_writes_prior_and_sparse_recipe_uses_it(tmp_path):
    """Through the CLIs: the Bridge writes depth_prior.npz for a COLMAP-style model with tracks;
    the sparse recipe finds it beside the seed, trains with it and records it in train.json;
    --no-depth-prior writes none and the run says the depth term is off."""
    from camio.colmap import read_model, write_text_model

    scene = write_scene(tmp_path / "s", n_views=3)
    from _train_scene import make_cloud

    cams = read_model(scene["cameras"]).cameras
    pts = make_cloud().means
    obs = {}
    for c in cams:  # every point observed where it projects
        x = pts @ c.cam_from_world[:3, :3].T + c.cam_from_world[:3, 3]
        uv = (x @ c.K.T)[:, :2] / x[:, 2:]
        obs[c.name] = (uv, np.arange(len(pts)))
    model = tmp_path / "model"
    write_text_model(model, cams, pts, np.full((len(pts), 3), 128, np.uint8), observations=obs)
    for flag, name in (([], "b"), (["--no-depth-prior"], "b_off")):
        rc = subprocess.run([sys.executable, "-m", "bridge", "--colmap", str(model), "--out", str(tmp_path / name),
                             *flag], cwd=REPO, capture_output=True, text=True)
        assert rc.returncode == 0, rc.stderr
    prior = read_depth_prior(tmp_path / "b" / DEPTH_PRIOR_FILE)
    assert prior.source == "sparse" and len(prior.z) > 0 and (prior.weight == 1).all()
    assert not (tmp_path / "b_off" / DEPTH_PRIOR_FILE).exists()
    bj = json.loads((tmp_path / "b" / "bridge.json").read_text())
    assert bj["depth_prior"]["samples"] == len(prior.z)
    for name in ("b", "b_off"):
        rc = subprocess.run([sys.executable, "-m", "splat_train", "--seed-ply", str(tmp_path / name / "seed.ply"),
                             "--cameras", str(tmp_path / name), "--images", str(scene["images"]), "--out",
                             str(tmp_path / f"t_{name}"), "--iterations", "12", "--recipe", "sparse",
                             "--eval-every", "0", "--config", '{"device": "cpu"}'],
                            cwd=REPO, capture_output=True, text=True)
        assert rc.returncode == 0, rc.stderr[-2000:]
    tj = json.loads((tmp_path / "t_b" / "train.json").read_text())
    assert tj["recipe"] == "sparse" and tj["depth_prior"]["samples"] > 0
    assert json.loads((tmp_path / "t_b_off" / "train.json").read_text())["depth_prior"] is None
    assert "depth term off" in rc.stderr


def test_no_opacity_reset_means_no_reset_and_no_size_prune():
    """opacity_reset_every 0 (the sparse recipe): the schedule never resets opacity, and the
    size prunes that 3DGS runs only after a reset stay off."""
    from splat_train.strategy.densify import DensifyStrategy
    from splat_train.gaussians import make_optimizer, params_from_cloud
    from _train_scene import make_cloud

    cfg = TrainConfig(recipe="sparse", iterations=1000, device="cpu")
    strat = DensifyStrategy.from_config(cfg, densify_from=0, densify_until=1000, densify_every=10,
                                        prune_world_size=1e-6, prune_screen_size=0.0)
    assert strat.opacity_reset_every == 0
    params = params_from_cloud(make_cloud(), 0, "cpu")
    opt = make_optimizer(params, cfg, 1.0)
    state = strat.init_state(len(params["means"]))
    n0 = len(params["means"])
    for it in (10, 20, 300, 600, 900):
        out = strat.step(params, opt, state, it, 1.0)
        assert out["reset"] == 0 and out["pruned"] == 0
    assert len(params["means"]) == n0
