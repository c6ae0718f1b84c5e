"""splat_train.strategy.densify: clone / split / prune / reset keep parameters and Adam state consistent."""

import math

import numpy as np
import pytest
import torch

from camio.ply import GaussianCloud
from splat_train.config import TrainConfig
from splat_train.strategy.densify import DensifyStrategy, duplicate, quat_to_rotmat, remove, reset_opacity, split
from splat_train.gaussians import PARAM_NAMES, make_optimizer, params_from_cloud


def _strategy(**overrides) -> DensifyStrategy:
    """The paper recipe's thresholds at 10,000 iterations (the config's defaults), with ``overrides``."""
    return DensifyStrategy.from_config(TrainConfig(recipe="paper", iterations=10000), **overrides)



pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

def _setup(n=8, seed=0):
    rng = np.random.default_rng(seed)
    cloud = GaussianCloud.from_points(rng.normal(size=(n, 3)), rng.uniform(0, 1, (n, 3)),
                                      rng.uniform(0.2, 0.9, n), rng.uniform(0.01, 0.3, n))
    params = params_from_cloud(cloud)
    opt = make_optimizer(params, TrainConfig(), extent=1.0)
    # one step so that every group has non-zero Adam moments
    loss = sum((p ** 2).sum() for p in params.values())
    loss.backward()
    opt.step()
    opt.zero_grad(set_to_none=True)
    return params, opt


def _check_consistent(params, opt, n):
    assert len(opt.param_groups) == len(PARAM_NAMES)
    for g in opt.param_groups:
        p = g["params"][0]
        assert p is params[g["name"]], g["name"]
        assert p.shape[0] == n
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    assert len(opt.state) == len(PARAM_NAMES)


def test_duplicate_appends_copies_with_zero_moments():
    params, opt = _setup()
    before = {k: v.detach().clone() for k, v in params.items()}
    avg_before = opt.state[params["means"]]["exp_avg"].clone()
    mask = torch.tensor([True, False, False, True, False, False, False, False])
    assert duplicate(params, opt, mask) == 2
    _check_consistent(params, opt, 10)
    for k in PARAM_NAMES:
        torch.testing.assert_close(params[k][:8], before[k])
        torch.testing.assert_close(params[k][8:], before[k][mask])
    st = opt.state[params["means"]]
    torch.testing.assert_close(st["exp_avg"][:8], avg_before)
    assert (st["exp_avg"][8:] == 0).all() and (st["exp_avg_sq"][8:] == 0).all()


def test_split_replaces_parents_by_two_smaller_children():
    params, opt = _setup()
    before = {k: v.detach().clone() for k, v in params.items()}
    mask = torch.zeros(8, dtype=torch.bool)
    mask[[2, 5]] = True
    gen = torch.Generator().manual_seed(0)
    assert split(params, opt, mask, gen) == 2
    _check_consistent(params, opt, 10)
    torch.testing.assert_close(params["means"][:6], before["means"][~mask])
    # children: scale / 1.6, same colour / opacity / rotation as the parent, order [c0 of all, c1 of all]
    parents = torch.tensor([2, 5, 2, 5])
    torch.testing.assert_close(params["scales"][6:], before["scales"][parents] - math.log(1.6))
    for k in ("sh_dc", "sh_rest", "opacity", "quats"):
        torch.testing.assert_close(params[k][6:], before[k][parents])
    # children lie within a few parent sigmas along the parent's axes
    rot = quat_to_rotmat(before["quats"][parents])
    local = torch.einsum("mji,mj->mi", rot, params["means"][6:] - before["means"][parents])
    assert (local.abs() / torch.exp(before["scales"][parents]) < 6).all()
    assert (opt.state[params["opacity"]]["exp_avg"][6:] == 0).all()
    # an Adam step still runs on the rebuilt groups
    sum((p ** 2).sum() for p in params.values()).backward()
    opt.step()


def test_remove_and_reset_opacity():
    params, opt = _setup()
    before = {k: v.detach().clone() for k, v in params.items()}
    sq = opt.state[params["scales"]]["exp_avg_sq"].clone()
    mask = torch.zeros(8, dtype=torch.bool)
    mask[[0, 7]] = True
    assert remove(params, opt, mask) == 2
    _check_consistent(params, opt, 6)
    torch.testing.assert_close(params["means"], before["means"][1:7])
    torch.testing.assert_close(opt.state[params["scales"]]["exp_avg_sq"], sq[1:7])
    step_before = float(opt.state[params["means"]]["step"])
    reset_opacity(params, opt, 0.01)
    _check_consistent(params, opt, 6)
    assert float(torch.sigmoid(params["opacity"].detach()).max()) <= 0.01 + 1e-6
    assert (opt.state[params["opacity"]]["exp_avg"] == 0).all()
    assert float(opt.state[params["means"]]["step"]) == step_before


def test_strategy_clones_small_splits_large_prunes_transparent():
    params, opt = _setup(n=6)
    with torch.no_grad():
        params["scales"][:] = math.log(0.001)          # small (< 0.01 * extent)
        params["scales"][3:5] = math.log(0.5)          # large
        params["opacity"][:] = 2.0
        params["opacity"][5] = -8.0                    # alpha 3e-4 < 0.005: pruned
    strat = _strategy(densify_from=0, densify_until=100, densify_every=10, opacity_reset_every=1000)
    state = strat.init_state(6)
    g = torch.zeros(6, 2)
    g[[0, 3], 0] = 1e-3  # pixel gradient; NDC = 1e-3 * W / 2 = 0.016 >> 2e-4
    strat.update_state(state, g, torch.full((6,), 3), torch.ones(6, dtype=torch.bool), 32, 24, iteration=5)
    assert float(state["count"].sum()) == 6
    assert float(state["grad2d"][0]) == pytest.approx(1e-3 * 16)
    out = strat.step(params, opt, state, iteration=10, extent=1.0, generator=torch.Generator().manual_seed(0))
    assert out == {"cloned": 1, "split": 1, "pruned": 1, "reset": 0}
    # 6 + 1 clone + 1 net split - 1 pruned
    _check_consistent(params, opt, 7)
    assert state["grad2d"].shape == (7,) and float(state["count"].sum()) == 0
    # no densification outside the window; reset on its period
    assert strat.step(params, opt, state, iteration=11, extent=1.0)["cloned"] == 0


def test_update_state_skips_non_finite_gradients():
    """A Gaussian whose view-space gradient has an inf or NaN component (or a norm that
    overflows) adds nothing to the statistics; the others add their NDC norm."""
    strat = _strategy(densify_from=0, densify_until=100)
    state = strat.init_state(5)
    g = torch.tensor([[3e-3, 4e-3], [float("nan"), 0.0], [0.0, float("inf")], [3e38, 3e38], [0.0, 0.0]])
    strat.update_state(state, g, torch.full((5,), 2), torch.ones(5, dtype=torch.bool), 2, 2, iteration=1)
    assert state["count"].tolist() == [1, 0, 0, 0, 1]
    assert float(state["grad2d"][0]) == pytest.approx(5e-3) and bool(torch.isfinite(state["grad2d"]).all())


def test_update_state_c_path_equals_torch_path():
    """The CPU float32 accumulation in C (splat_train.render.cpu.optim, taken for the rasterizer's
    int32 radii and a [N, 2] view of its gradient buffer) gives the statistics of the torch
    code (taken for int64 radii): hidden, NaN, inf and overflowing rows skipped, counts and
    radii exact, norms to float32 rounding; three views accumulated."""
    from splat_train.render.cpu import optim as cpu_optim

    if not cpu_optim.available():
        pytest.skip("no C++ compiler for the CPU kernels")
    strat = _strategy(densify_from=0, densify_until=100)
    n = 50_000
    gen = torch.Generator().manual_seed(3)
    states = [strat.init_state(n), strat.init_state(n), strat.init_state(n)]
    for view in range(3):
        buf = torch.randn(n, 10, generator=gen) * 1e-3  # as the blend backward's [N, 10] rows
        buf[::97, 0] = float("nan")
        buf[5::89, 1] = float("inf")
        buf[7::83, :2] = 3e38
        radii = torch.randint(0, 40, (n,), generator=gen, dtype=torch.int32)
        visible = torch.rand(n, generator=gen) < 0.8
        g = buf[:, 0:2]
        assert cpu_optim.densify_stats(states[0], g, radii, visible, 497, 372)  # the C path
        strat.update_state(states[1], g, radii.long(), visible, 497, 372, iteration=view)  # torch
        strat.update_state(states[2], g, radii, visible, 497, 372, iteration=view)  # dispatches to C
    c_state, t_state = states[0], states[1]
    assert all(torch.equal(states[2][k], c_state[k]) for k in c_state)
    assert torch.equal(c_state["count"], t_state["count"]) and float(c_state["count"].sum()) > 0
    assert torch.equal(c_state["max_radii"], t_state["max_radii"])
    torch.testing.assert_close(c_state["grad2d"], t_state["grad2d"], rtol=1e-6, atol=0.0)
    assert bool(torch.isfinite(c_state["grad2d"]).all())


def _three_step_reference(strat, params, opt, state, iteration, extent, generator):
    """Clone, split, prune as three rewrites (duplicate, split, remove): what the fused
    ``_densify_and_prune`` must equal."""
    n = params["means"].shape[0]
    grads = state["grad2d"] / state["count"].clamp_min(1)
    high = grads >= strat.grad_threshold
    big = torch.exp(params["scales"].detach()).amax(1) > strat.percent_dense * extent
    clone_mask, split_mask = high & ~big, high & big
    n_clone = duplicate(params, opt, clone_mask)
    radii = torch.cat([state["max_radii"], state["max_radii"][clone_mask]])
    split_mask = torch.cat([split_mask, split_mask.new_zeros(n_clone)])
    split(params, opt, split_mask, generator)
    radii = torch.cat([radii[~split_mask], radii.new_zeros(2 * int(split_mask.sum()))])
    prune = torch.sigmoid(params["opacity"].detach()) < strat.prune_opacity
    if iteration > strat.opacity_reset_every:
        if strat.prune_screen_size > 0:
            prune |= radii > strat.prune_screen_size
        prune |= torch.exp(params["scales"].detach()).amax(1) > strat.prune_world_size * extent
    n_pruned = remove(params, opt, prune)
    assert n_pruned == int(prune.sum())
    return {"cloned": n_clone, "split": int(split_mask.sum()), "pruned": n_pruned}


@pytest.mark.parametrize("iteration", [200, 3100])  # before / after the first opacity reset
def test_fused_densify_equals_clone_split_prune_in_three_steps(iteration):
    """One gather per tensor gives exactly the rows, values, Adam moments and random draws of
    duplicate -> split -> remove (all three paths taken, pruning of clones and children too)."""
    n = 400
    runs = []
    for _ in range(2):
        params, opt = _setup(n=n, seed=3)
        g = torch.Generator().manual_seed(5)
        with torch.no_grad():
            params["scales"][:] = torch.log(0.001 + 0.012 * torch.rand(n, 3, generator=g))  # small and big
            params["opacity"][:] = 4 * torch.randn(n, generator=g)  # some below the prune threshold
        strat = _strategy(densify_from=0, densify_until=10000, densify_every=100, opacity_reset_every=3000,
                          prune_world_size=0.0115)
        state = strat.init_state(n)
        state["grad2d"][:] = 4e-4 * torch.rand(n, generator=g)
        state["count"][:] = 1 + torch.randint(0, 3, (n,), generator=g)
        state["max_radii"][:] = 30 * torch.rand(n, generator=g)
        runs.append((params, opt, state, strat))
    p_ref, opt_ref, st_ref, strat_ref = runs[0]
    want = _three_step_reference(strat_ref, p_ref, opt_ref, st_ref, iteration, 1.0, torch.Generator().manual_seed(9))
    p_new, opt_new, st_new, strat_new = runs[1]
    got = strat_new._densify_and_prune(p_new, opt_new, st_new, iteration, 1.0, torch.Generator().manual_seed(9))
    assert got == want and min(want.values()) > 0, (got, want)
    m = p_ref["means"].shape[0]
    _check_consistent(p_new, opt_new, m)
    for k in PARAM_NAMES:
        assert torch.equal(p_new[k], p_ref[k]), k
        s_new, s_ref = opt_new.state[p_new[k]], opt_ref.state[p_ref[k]]
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(s_new[key], s_ref[key]), (k, key)
    assert st_new["grad2d"].shape == (m,) and float(st_new["count"].sum()) == 0
