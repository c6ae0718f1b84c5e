"""The recipes: each one's published values, and ``paper`` densifying as gsplat's own loop does.

``paper`` stands for 3DGS as its code runs; gsplat's ``DefaultStrategy`` is the field's
reference implementation of that code. The pin test feeds both strategies the same Gaussians
and the same per-view statistics, lets each densify at the same iterations (before and after
the first opacity reset), and checks that they clone, split and prune the same Gaussians.
gsplat's strategy is pure PyTorch and runs on the CPU (gsplat is a dev dependency).
"""

import numpy as np
import pytest
import torch

from splat_train.config import TrainConfig
from splat_train.strategy.densify import DensifyStrategy
from splat_train.gaussians import make_optimizer, params_from_cloud
from splat_train.recipes import RECIPE_NAMES, RECIPES, VALUE_KEYS, recipe_defaults
from camio.ply import GaussianCloud

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

W, H = 160, 120


def test_every_recipe_gives_every_value_key_and_the_config_takes_it():
    for name in RECIPE_NAMES:
        preset = recipe_defaults(name)
        cfg = TrainConfig(recipe=name, iterations=1000)
        for key in VALUE_KEYS:
            assert key in preset, (name, key)
            assert cfg.flat(key) == preset[key]
    # a value the user sets wins over the recipe's
    assert TrainConfig(recipe="dropgaussian", densify_grad_threshold=1e-4).densify_grad_threshold == 1e-4


def test_a_seed_within_the_cap_trains_the_same_under_every_seed_over_cap_rule():
    """The ``seed_over_cap`` rules (docs/reference.md section 3a) change a run only where the
    seed is larger than the cap: within it, the cap and the strategy are sparse's."""
    pixels = 3 * 200 * 200  # the cap: 0.1 x 120,000 = 12,000
    for seed in (0, 1, 11_999, 12_000):
        runs = {rule: TrainConfig(recipe="sparse", iterations=3000, seed_over_cap=rule)
                for rule in ("cap", "keep", "relocate")}
        assert {(c.max_gaussians_for(pixels, seed), c.strategy_for(pixels, seed)) for c in runs.values()} \
            == {(12_000, "densify")}, seed


def test_a_seed_over_the_cap_is_held_kept_or_relocated():
    pixels, seed = 3 * 200 * 200, 30_000  # 3DGS's random seed of 0.25 per pixel, over sparse's 0.1
    cfg = TrainConfig(recipe="sparse", iterations=3000)
    assert cfg.seed_over_cap == "cap"
    assert (cfg.max_gaussians_for(pixels, seed), cfg.strategy_for(pixels, seed)) == (12_000, "densify")
    keep = cfg.replace(seed_over_cap="keep")
    assert (keep.max_gaussians_for(pixels, seed), keep.strategy_for(pixels, seed)) == (seed, "densify")
    reloc = cfg.replace(seed_over_cap="relocate")
    assert (reloc.max_gaussians_for(pixels, seed), reloc.strategy_for(pixels, seed)) == (seed, "mcmc")
    # no cap at all: nothing to raise
    paper = TrainConfig(recipe="paper", iterations=3000, seed_over_cap="keep")
    assert paper.max_gaussians_for(pixels, seed) is None and paper.strategy_for(pixels, seed) == "densify"
    # mcmc never removes, and grows from a seed that fills its cap (CAP_OVER_SEED x the seed)
    assert TrainConfig(recipe="mcmc", iterations=3000).max_gaussians_for(pixels, 30_000) == 45_000
    assert TrainConfig(recipe="mcmc-keep", iterations=3000).max_gaussians_for(pixels, 30_000) == 30_000
    grow = cfg.replace(seed_over_cap="grow")
    assert (grow.max_gaussians_for(pixels, seed), grow.strategy_for(pixels, seed)) == (45_000, "densify")
    assert grow.max_gaussians_for(pixels, 100) == 12_000  # a small seed: the cap as set
    with pytest.raises(ValueError, match="seed_over_cap must be one of"):
        TrainConfig(recipe="sparse", seed_over_cap="expand")


def test_dropgaussian_is_its_release_llff_setting():
    """DropGaussian's LLFF training: 10k iterations, densify 500-10k every 100 at gradient
    threshold 5e-4, opacity reset every 3,000, dropout ramped to 0.2, pruning by opacity only;
    no cap, no depth term (every value against its source: tests/test_recipes_released.py)."""
    cfg = TrainConfig(recipe="dropgaussian", iterations=10000)
    s = cfg.schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every) == (500, 10000, 100, 3000)
    assert cfg.densify_grad_threshold == 5e-4 and cfg.dropout_rate == 0.2
    assert cfg.depth_weight == 0.0 and cfg.gaussians_per_pixel == 0.0
    assert cfg.prune_screen_size == 0.0 and cfg.prune_world_size == 0.0


def test_paper_is_the_3dgs_release_at_30k():
    cfg = TrainConfig(recipe="paper", iterations=30000)
    s = cfg.schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == \
        (500, 15000, 100, 3000, 1000)
    assert cfg.densify_grad_threshold == 2e-4 and cfg.dropout_rate == 0.0 and cfg.prune_screen_size == 0.0
    assert cfg.prune_world_size == 0.1 and RECIPES["paper"].gaussians_per_pixel == 0.0


def test_the_kept_variants_are_their_recipes_before_the_change():
    """``paper-seedcode`` is the seed code's schedule at 10,000 iterations, ``dropgaussian-wsprune``
    prunes by world size, ``mcmc-keep`` keeps a seed over its cap at its size; each is its
    recipe in every other value, and none is a recipe a user picks."""
    s = TrainConfig(recipe="paper-seedcode", iterations=10000).schedule()
    assert (s.densify_from, s.densify_until, s.densify_every, s.opacity_reset_every, s.sh_increase_every) == \
        (500, 10000, 100, 3000, 1000)
    assert TrainConfig(recipe="dropgaussian-wsprune", iterations=10000).prune_world_size == 0.1
    assert TrainConfig(recipe="mcmc-keep", iterations=10000).seed_over_cap == "keep"
    for variant, recipe, differ in (("paper-seedcode", "paper", set()),
                                    ("dropgaussian-wsprune", "dropgaussian", {"prune_world_size"}),
                                    ("mcmc-keep", "mcmc", {"seed_over_cap"})):
        a, b = recipe_defaults(variant), recipe_defaults(recipe)
        assert {k for k in a if a[k] != b[k]} == differ, variant
        assert variant not in RECIPE_NAMES


def test_dropgaussian_prunes_by_opacity_only():
    """No world-size prune after a reset (the release's size_threshold is None); paper keeps it."""
    n, extent = 40, 1.0
    cloud = GaussianCloud.from_points(np.zeros((n, 3)), np.full((n, 3), 0.5), np.full(n, 0.5),
                                      np.full(n, 0.5))  # every Gaussian 0.5 x the extent: past 3DGS's 0.1
    pruned = {}
    for recipe in ("paper", "dropgaussian", "dropgaussian-wsprune"):
        cfg = TrainConfig(recipe=recipe, iterations=10000)
        strat = DensifyStrategy.from_config(cfg, densify_from=0, opacity_reset_every=100, grad_threshold=1.0)
        params = params_from_cloud(cloud)
        state = strat.init_state(n)
        strat.update_state(state, torch.zeros(n, 2), torch.full((n,), 3), torch.ones(n, dtype=torch.bool), W, H,
                           iteration=199)
        pruned[recipe] = strat.step(params, make_optimizer(params, cfg, extent=extent), state, 200, extent)["pruned"]
    assert pruned == {"paper": n, "dropgaussian": 0, "dropgaussian-wsprune": n}


def _scene(n: int, seed: int):
    rng = np.random.default_rng(seed)
    # log-uniform sizes around the clone / split border (1 % of the extent 1.0) and past the
    # world-size prune (10 %), opacities spread over the prune threshold
    cloud = GaussianCloud.from_points(rng.normal(size=(n, 3)), rng.uniform(0, 1, (n, 3)),
                                      rng.uniform(0.001, 0.9, n), np.exp(rng.uniform(np.log(1e-3), np.log(0.3), n)))
    return params_from_cloud(cloud)


def _views(n: int, k: int, seed: int):
    """k views' statistics: d loss / d means2d [N, 2] in pixels and screen radii [N] (0: not
    seen; a quarter of the radii exceed 20 px, where a screen-size prune would act)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(k):
        grad = torch.randn(n, 2, generator=g) * 4e-6
        radii = torch.randint(0, 40, (n,), generator=g)
        out.append((grad, radii))
    return out


@pytest.mark.parametrize("iteration", [1100, 3100])  # before and after the first reset (3,000)
def test_paper_densifies_as_gsplat_default_strategy(iteration):
    gsplat_strategy = pytest.importorskip("gsplat.strategy")
    n, extent = 600, 1.0
    cfg = TrainConfig(recipe="paper", iterations=30000)  # the release's length: its first reset at 3,000
    ours = DensifyStrategy.from_config(cfg)
    theirs = gsplat_strategy.DefaultStrategy(
        prune_opa=cfg.prune_opacity, grow_grad2d=cfg.densify_grad_threshold, grow_scale3d=cfg.percent_dense,
        prune_scale3d=cfg.prune_world_size, refine_start_iter=ours.densify_from, refine_stop_iter=ours.densify_until,
        reset_every=ours.opacity_reset_every, refine_every=ours.densify_every)

    p_ours = _scene(n, 7)
    opt = make_optimizer(p_ours, cfg, extent=extent)
    names = {"means": "means", "scales": "scales", "quats": "quats", "opacities": "opacity", "sh0": "sh_dc"}
    p_theirs = torch.nn.ParameterDict({k: torch.nn.Parameter(p_ours[v].detach().clone()) for k, v in names.items()})
    opts = {k: torch.optim.Adam([{"params": [p_theirs[k]], "lr": 1e-3, "name": k}]) for k in p_theirs}
    st_ours = ours.init_state(n)
    st_theirs = theirs.initialize_state(scene_scale=extent)

    for grad, radii in _views(n, 5, seed=iteration):
        ours.update_state(st_ours, grad, radii, radii > 0, W, H, iteration=iteration)
        means2d = torch.zeros(1, n, 2, requires_grad=True)
        means2d.grad = grad[None].clone()
        info = {"width": W, "height": H, "n_cameras": 1, "radii": torch.stack([radii, radii], -1)[None],
                "gaussian_ids": None, "means2d": means2d}
        theirs._update_state(p_theirs, st_theirs, info, packed=False)

    counts = ours.step(p_ours, opt, st_ours, iteration, extent, torch.Generator().manual_seed(0))
    n_dupli, n_split = theirs._grow_gs(p_theirs, opts, st_theirs, iteration)
    n_prune = theirs._prune_gs(p_theirs, opts, st_theirs, iteration)
    assert counts["cloned"] > 0 and counts["split"] > 0 and counts["pruned"] > 0  # every path taken
    assert (counts["cloned"], counts["split"], counts["pruned"]) == (n_dupli, n_split, n_prune)
    assert len(p_ours["means"]) == len(p_theirs["means"])
    # the same Gaussians survive: compare the parameters the split does not redraw, as sets of rows
    def rows(opacity, sh):
        r = torch.cat([opacity.detach().reshape(-1, 1), sh.detach().reshape(len(opacity), -1)], 1)
        return r[torch.argsort(r[:, 0] * 1e3 + r[:, 1])]
    torch.testing.assert_close(rows(p_ours["opacity"], p_ours["sh_dc"]),
                               rows(p_theirs["opacities"], p_theirs["sh0"]), rtol=0, atol=0)
