"""The training recipes, ``paper``, ``dropgaussian``, ``sparse`` and ``mcmc``: the one place for their
defaults.

A recipe is a training config tree (:class:`splat_train.tree.ConfigTree`) that states only its
differences from the base (the configs' defaults, 3DGS as its code trains): ``PAPER`` is the base,
``DROPGAUSSIAN`` is ``PAPER`` with dropout and a higher gradient threshold, ``SPARSE`` and ``MCMC``
set their own parts and strategy. A run's config is the recipe's with the flat keys the user
sets over it (a key the user sets keeps its value, and means what it says: schedule keys are
iterations of this run, never rescaled). The recipe's own schedule values are shares of the run
(:class:`splat_train.config.RecipeSchedule`), resolved to iterations once per run
(:meth:`splat_train.tree.ConfigTree.schedule`, printed by the trainer).

``paper``
    3DGS as its release trains (graphdeco-inria/gaussian-splatting, ``train.py`` and
    ``arguments/__init__.py``; docs/reference.md section 7 lists every value with its source):
    the release's schedule as fractions of its own 30,000 iterations, as gsplat's
    ``steps_scaler`` scales it: densify from 500/30000 of the run to half of it (15000/30000)
    every 100 iterations, reset opacity every 3000/30000, raise the SH degree every
    1000/30000; no cap on growth, no dropout, no depth term. The densification *period* stays
    100 at every run length, as the release's own code keeps it whatever ``--iterations`` says
    (a 5x shorter period in a 5x shorter run grew 4000 seeds to 120k Gaussians by iteration 400
    on the 256 px synthetic scene). The seed code of the paper ran this code for 10,000
    iterations with its absolute counts (densify to the end, reset every 3,000, SH every 1,000);
    at 10,000 iterations this recipe densifies to 5,000, resets every 1,000 and raises the SH
    degree every 333, as the release's 30,000-iteration run does in proportion (the variant
    ``paper-seedcode`` keeps the seed code's schedule, see below).
    Pruning is what the official code does, not what its source appears to do: the code
    computes a screen-size prune (2D radius above 20 px after the first reset), but zeroes the
    radii it reads before the prune reads them (graphdeco-inria/gaussian-splatting issue 123),
    so it never prunes by screen size; gsplat's ``DefaultStrategy`` leaves it off by default for
    the same reason. This recipe leaves it off too (``prune_screen_size`` 0), so that it trains
    as 3DGS and gsplat's own loop do (tests/test_train_recipes.py pins the two strategies
    together on a small scene); the world-size prune that the release runs beside it (largest
    scale above 0.1 x the extent, after the first reset) stays.
    In the sparse regime this recipe overfits: held-out PSNR peaks early and falls while the
    model grows (docs/lessons.md).

``dropgaussian``
    DropGaussian (Park et al., CVPR 2025) as its release trains LLFF 3 views
    (DCVL-3D/DropGaussian_release): 3DGS with Gaussian dropout during training, the rate ramped
    linearly to 0.2 over the run (``0.2 * iteration / 10000`` of its 10,000 iterations),
    survivors scaled by 1 / (1 - p); densify from 500 to 10,000 of 10,000 iterations every 100
    with the gradient threshold 5e-4 (2.5x 3DGS's), opacity reset every 3,000 (30 %); the
    release prunes by opacity only (its ``size_threshold`` is None: neither the screen-size nor
    the world-size prune, ``prune_world_size`` 0). No cap, no depth term. A shorter run
    compresses the schedule in proportion and the period stays 100.

``sparse``
    The sparse-view regularisation the field converged on, each part with its own switch:

    * Gaussian dropout (DropGaussian, CVPR 2025): during training only, each Gaussian's
      opacity is zeroed with probability p, ramping linearly from 0 to ``dropout_rate`` over
      the run, survivors scaled by 1 / (1 - p) (:mod:`splat_train.parts.dropout`);
    * a depth prior from the initialiser's own dense output, weighted by its confidence: a
      scale-invariant (Pearson) loss between rendered and prior depth, weight ramped in over
      ``depth_ramp_fraction`` of the run (:mod:`splat_train.parts.depth_prior`); off when the seed has
      no prior file;
    * a model sized to its views: growth keeps the best candidates under a cap of
      ``gaussians_per_pixel`` x the training pixels (:mod:`splat_train.strategy.densify`), densifying
      every 100 iterations (the field's period: 3DGS, gsplat, DropGaussian) from 5 % of the run
      to its end: under the cap, growth keeps replacing the weakest Gaussians by better ones;
    * opacity decay (Binocular3DGS, NeurIPS 2024): every opacity x 0.995 after each iteration
      from the densification start (:mod:`splat_train.parts.opacity_decay`), so that Gaussians the
      views stop holding up fade and the prune removes them; the release densifies to the end
      of the run while the decay acts, and so does this recipe;
    * no opacity reset (nor the size prune 3DGS runs after one): measured, the reset cost the
      sparse model about 1 dB held out that it never recovered;
    * binocular stereo consistency (Binocular3DGS, NeurIPS 2024) from the densification start
      on: each training view is rendered again from a camera shifted sideways and warped back
      with the rendered depth, which must reproduce the training image
      (:mod:`splat_train.parts.binocular`; one more render per iteration), from earlier than the
      release's 2/3 of the run;
    * gsplat's opacity regulariser in its place (``opacity_reg`` 0.01 x mean opacity, the value
      of its MCMC preset, :mod:`splat_train.parts.compose`): Gaussians that no training view needs
      fade, and the 3DGS prune (opacity below 0.005) removes them, which frees the cap for
      Gaussians the views do need;
    * the mean colour of the training images behind the model (``background``
      :data:`BACKGROUND_MEAN`; black in the field's recipes): from a few views a held-out view
      sees what no training view did, and there the render is this colour.

    A seed larger than the cap (3DGS's random initialisation, 0.25 per training pixel, where
    three views triangulate nothing) shrinks towards the cap (``seed_over_cap`` "cap"): raising
    the cap to the seed, or relocating it as ``mcmc`` does, lost 0.71 and 0.41 dB on the six
    randomly seeded tuning cells.

    Every value was chosen on the tuning scenes of the sparse-view benchmark
    (docs/reference.md section 3a says how; docs/lessons.md what each choice measured): a
    densification period of 1 % of the run (20 at 1,000 iterations) filled the cap by
    iteration 200 on statistics of 20 steps and lost held-out PSNR there; SH degree 1 or 0
    did not help.

``mcmc``
    3DGS as Markov Chain Monte Carlo (Kheradmand et al., NeurIPS 2024, arXiv:2404.09591) as
    gsplat's ``mcmc`` preset runs it (``examples/simple_trainer.py``, ``gsplat/strategy/mcmc.py``
    ``MCMCStrategy``; here :mod:`splat_train.strategy.mcmc`): no clone / split / prune / opacity reset;
    every 100/30000 of the run (gsplat's ``refine_every`` 100 at its 30,000 steps; at least
    :data:`MIN_DENSIFY_EVERY`) from 500/30000 to 25000/30000 of the run, dead Gaussians (opacity <= ``prune_opacity`` 0.005) are relocated onto live ones
    and 5 % more are added until the cap; position noise ``noise_lr`` 5e5 x the position rate
    after every step; the loss adds ``opacity_reg`` 0.01 x mean opacity and ``scale_reg`` 0.01 x
    mean scale; the SH degree rises every 1000/30000 of the run (gsplat's
    ``sh_degree_interval``). No dropout, no depth term.

    The cap is ``gaussians_per_pixel`` 0.175 x the training pixels: LLFF at 1/8 resolution
    (504 x 378) with 3 views has 571,536 training pixels, so the cap is 100k, the size of the
    field's LLFF 3-view models (80k-120k). gsplat's absolute ``cap_max`` 1e6 is sized for
    dense 360-degree captures of 100-300 views (under 0.01 per pixel); an absolute cap would
    not follow the view count or resolution, and 1e6 is ten times the field's 3-view models.
    The release always grows from its initial points towards a cap above them (its configs'
    ``cap_max`` is 1.5-59x the 100,000 random points it starts from), so a seed that fills
    the per-pixel cap (3DGS's random initialisation, 0.25 per training pixel) raises the cap
    to :data:`CAP_OVER_SEED` x its size (``seed_over_cap`` "grow"): it grows as the release's
    runs do instead of staying at its seed (MCMC never removes Gaussians, so a seed above the
    cap keeps its size either way).

    Growth (``mcmc_growth`` "reach_cap"): gsplat's int(1.05 N) per refine step, except where it
    cannot take the seed to the cap within the refine window; there the count follows the
    geometric path from the seed's size to the cap over the window's refine steps, so that the
    model reaches the budget it is given, as gsplat's runs do from their SfM seeds of
    100k-300k points (:func:`splat_train.strategy.mcmc.growth_target`). The seeds of the sparse-view
    benchmark are the 12-95 points three views triangulate: at 5 % per step a 3,000-iteration
    run (122 refine steps) ends them at a few thousand Gaussians, a 1,000-iteration one (40
    steps) at 7x the seed, and a seed under 20 never grows (int(1.05 N) = N; the Stitch toy's
    13-point seed stayed at 13 Gaussians). The MCMC paper's answer to a poor SfM seed is random
    points; here every recipe starts from the same measured points, and growth does the rest.

    Initial opacity and scale: gsplat's preset starts SfM points at opacity 0.5 and a tenth of
    the neighbour distance; here the seed PLY's own opacities and scales are kept (the Bridge's
    uncertainty-gated opacity is part of the initialiser under test), as in the other recipes.

Variants (:data:`VARIANTS`)
    A recipe's earlier values, kept under a name of their own so that the runs made with them
    (experiments/records/sparse_views) stay readable and can be reproduced: a variant is a
    preset like a recipe (``--config '{"recipe": "paper-seedcode"}'``, ``TrainConfig(recipe=...)``),
    not one of the recipes a user picks (``--recipe``, the workflow's config, the benchmark's
    targets).

    * ``paper-seedcode``: ``paper`` with the seed code's schedule (densify from 500/10000 of the
      run to its end, reset opacity every 30 %, SH degree every 10 %);
    * ``dropgaussian-wsprune``: ``dropgaussian`` with 3DGS's world-size prune, which its
      release never runs;
    * ``mcmc-keep``: ``mcmc`` with a seed over its cap kept at its size (``seed_over_cap``
      "keep"), so a seed that fills the cap does not grow.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from splat_train.tree import (BACKGROUND_BLACK, BACKGROUND_MEAN, DENSIFY_FROM_3DGS, MIN_DENSIFY_EVERY, RECIPE_KEYS,
                              SCHEDULE_KEYS, ConfigTree, OptimConfig, RecipeSchedule)
from splat_train.parts.configs import (BINOCULAR_FROM_FRACTION, OPACITY_DECAY_BINOCULAR, BinocularConfig,
                                      DepthPriorConfig, DropoutConfig, OpacityDecayConfig, RegularisersConfig)
from splat_train.strategy.configs import (CAP_OVER_SEED, GRAD_THRESHOLD_3DGS, MCMC_GROWTH,  # noqa: F401
                                          PRUNE_WORLD_SIZE_3DGS, SEED_OVER_CAP, STRATEGIES, MCMCStrategyConfig,
                                          StrategyConfig)

__all__ = ["RECIPES", "RECIPE_NAMES", "RECIPE_SUMMARIES", "DEFAULT_RECIPE", "PART_KEYS", "SCHEDULE_KEYS", "VALUE_KEYS",
           "RAMP_KEYS", "STRATEGIES", "SEED_OVER_CAP", "MCMC_GROWTH", "MIN_DENSIFY_EVERY", "BACKGROUND_BLACK",
           "BACKGROUND_MEAN", "BINOCULAR_FROM_FRACTION", "CAP_OVER_SEED", "PRUNE_WORLD_SIZE_3DGS", "PAPER",
           "DROPGAUSSIAN", "SPARSE", "MCMC", "VARIANTS", "ITERATIONS_3DGS", "recipe_config", "recipe_defaults",
           "register_recipe"]

DEFAULT_RECIPE = "sparse"

# The recipe keys (splat_train.config.RECIPE_KEYS) by kind: the regularisation parts and their
# "off" values (gaussians_per_pixel: no per-pixel cap) ...
PART_KEYS = {"dropout_rate": 0.0, "depth_weight": 0.0, "gaussians_per_pixel": 0.0, "opacity_reg": 0.0,
             "scale_reg": 0.0, "binocular_weight": 0.0, "opacity_decay": 1.0}
# ... the shares of the run that say when a part acts: over which share a weight or rate ramps
# in from 0 (1: all of it), or after which share a term starts (binocular_from_fraction) ...
RAMP_KEYS = ("depth_ramp_fraction", "dropout_ramp_fraction", "binocular_from_fraction")
# ... and the values every recipe gives: the densification thresholds, how the model grows
# (``strategy``), the background.
VALUE_KEYS = ("densify_grad_threshold", "prune_screen_size", "prune_world_size", "strategy", "seed_over_cap",
              "mcmc_growth", "background")
assert set(RECIPE_KEYS) == {*PART_KEYS, *RAMP_KEYS, *VALUE_KEYS}

# gsplat's MCMC preset's opacity regulariser weight (simple_trainer.py ``opacity_reg``)
OPACITY_REG_GSPLAT = 0.01
# FSGS's Pearson depth weight (docs/field.md), ``sparse``'s; 0.1 lost 0.06 dB over twelve
# scenes (docs/lessons.md)
DEPTH_WEIGHT_FSGS = 0.05

# The 3DGS release's run length and its schedule there (arguments/__init__.py OptimizationParams,
# train.py; docs/reference.md section 7)
ITERATIONS_3DGS = 30000
SCHEDULE_3DGS = RecipeSchedule(densify_from=500 / ITERATIONS_3DGS, densify_until=15000 / ITERATIONS_3DGS,
                               opacity_reset_every=3000 / ITERATIONS_3DGS, sh_increase_every=1000 / ITERATIONS_3DGS)

# ``paper``: the base with the 3DGS release's schedule as fractions of its 30,000 iterations:
# densify from 500/30000 of the run to half of it every 100 iterations (the period absolute, as
# its code keeps it), reset opacity every 10 %, SH degree every 1000/30000; the default strategy
# at 3DGS's gradient threshold 2e-4, the world-size prune at 3DGS's 0.1 and prune_screen_size
# off: the official code never applies it (see the module docstring); no cap (seed_over_cap
# "cap": nothing to hold), mcmc_growth not read (no mcmc strategy); every part off (dropout,
# depth, regularisers, binocular stereo consistency (splat_train/parts/binocular.py), opacity
# decay (splat_train/parts/opacity_decay.py)); black behind the model.
PAPER = ConfigTree(recipe="paper", shares=SCHEDULE_3DGS)

# ``dropgaussian``: ``paper`` with DropGaussian's dropout, ramped to 0.2 over the whole run
# (DropGaussian's ramp, the DropoutConfig default), its densification gradient threshold, no
# world-size prune (the release passes size_threshold None, which skips both size prunes) and
# its release's schedule at its 10,000 iterations (RecipeSchedule's defaults: densify from 500
# to the end, reset every 3,000, SH every 1,000).
DROPGAUSSIAN = replace(
    PAPER, recipe="dropgaussian", parts=(DropoutConfig(rate=0.2),), shares=RecipeSchedule(),
    growth=replace(PAPER.growth, default=replace(PAPER.growth.default, grad_threshold=5e-4, prune_world_size=0.0)))

SPARSE = ConfigTree(
    recipe="sparse",
    # the training images' mean colour behind the model, chosen on the tuning scenes
    # (docs/lessons.md: +0.10 ± 0.37 dB over fourteen cells, 3 seeds) and held on the five
    # evaluation scenes (docs/results.md)
    optim=OptimConfig(background=BACKGROUND_MEAN),
    shares=RecipeSchedule(
        # every 100 like the field's recipes (the base's period), to the end of the run (the
        # base's end), as Binocular3DGS's release grows while its opacity decay acts
        # (docs/lessons.md)
        # no opacity reset (None: never; nor the size prune that follows it): on fern posed
        # n = 3 the held-out PSNR peaked just before the reset and fell ~1 dB after it at both
        # 3,000 and 10,000 iterations; without it the 3,000-iteration run ended 1.3 dB higher
        # (docs/lessons.md). The cap and dropout do the reset's job of bounding the model.
        opacity_reset_every=None),
    growth=StrategyConfig(
        # chosen on the tuning scenes only (docs/lessons.md): on fern
        # posed n = 3, 1,000 iterations, 3 seeds, 0.1 per training pixel held out LPIPS-Alex
        # 0.252 / VGG 0.345 against 0.327 / 0.378 for 0.03 and 0.274 / 0.366 for `paper`, at
        # 0.21 dB below 0.03 and 0.46 dB above `paper`; with no cap the model grew to 100k and
        # lost 1.4 dB. The field's LLFF 3-view models hold 80k-120k: 0.1 gives 57k there.
        # At 3,000 iterations 0.2 lost 0.06 dB over twelve scenes.
        gaussians_per_pixel=0.1,
        # seed_over_cap "cap" (the base's); mcmc_growth "gsplat", not read (no seed over the cap
        # grows by relocation); prune_screen_size 0 (the base's): no reset, hence no size prune
        # of either kind
    ),
    parts=(
        # DropGaussian's final rate (docs/field.md), DropGaussian's ramp over the whole run
        DropoutConfig(rate=0.2),
        # FSGS's Pearson depth weight, reached after 10 % of the run
        DepthPriorConfig(weight=DEPTH_WEIGHT_FSGS, ramp_fraction=0.1),
        # chosen on the tuning scenes (docs/lessons.md)
        RegularisersConfig(opacity_reg=OPACITY_REG_GSPLAT),
        # binocular stereo consistency (splat_train/parts/binocular.py) with Binocular3DGS's weight,
        # chosen on the tuning scenes (docs/lessons.md: fourteen cells, 3 seeds, +0.05 dB and
        # lower LPIPS-Alex and VGG than without it), from the densification start rather than
        # the release's 2/3 of the run (+0.12 dB more): the held-out declines it holds back
        # happen while the model grows
        BinocularConfig(weight=1.0, from_fraction=DENSIFY_FROM_3DGS),
        # Binocular3DGS's opacity decay (splat_train/parts/opacity_decay.py) at its release's factor,
        # chosen on the tuning scenes (docs/lessons.md: +0.40 ± 0.22 dB over fourteen cells)
        OpacityDecayConfig(factor=OPACITY_DECAY_BINOCULAR),
    ),
)

MCMC = ConfigTree(
    recipe="mcmc",
    # gsplat's MCMCStrategy at 30,000 steps: refine_start_iter 500, refine_stop_iter 25000,
    # refine_every 100; simple_trainer's sh_degree_interval 1000. The period is a fraction
    # too: growth is 5 % per refine step, so an absolute 100 would leave a 1,000-iteration
    # run 8 steps (x1.5) where gsplat's run has 245 (the cap)
    shares=RecipeSchedule(densify_from=500 / 30000, densify_until=25000 / 30000, densify_every=100 / 30000,
                          densify_every_count=None, opacity_reset_every=None, sh_increase_every=1000 / 30000),
    growth=StrategyConfig(
        name="mcmc",
        # 100k at LLFF 3 views, 1/8 resolution (571,536 pixels); see the module docstring
        gaussians_per_pixel=0.175,
        # the release grows from its initial points towards a cap above them: a seed that fills
        # the per-pixel cap raises it to CAP_OVER_SEED x its size (see the module docstring)
        seed_over_cap="grow",
        # gsplat's 5 % per refine step, but never a model that cannot reach its cap: from the
        # 12-95 points three views triangulate, 5 % per step leaves it at a few hundred
        # Gaussians (under 20 it never grows: int(1.05 N) = N); see the module docstring
        mcmc=MCMCStrategyConfig(growth="reach_cap"),
        # the default strategy's settings (the base's: 3DGS's threshold, no size prune) are not
        # read by the mcmc strategy (no clone / split / size prune)
    ),
    # simple_trainer's mcmc preset; no dropout, no depth term, no binocular consistency
    # (splat_train/parts/binocular.py), no opacity decay (splat_train/parts/opacity_decay.py)
    parts=(RegularisersConfig(opacity_reg=OPACITY_REG_GSPLAT, scale_reg=0.01),),
)

RECIPES: dict[str, ConfigTree] = {"paper": PAPER, "dropgaussian": DROPGAUSSIAN, "sparse": SPARSE, "mcmc": MCMC}
RECIPE_NAMES = tuple(RECIPES)

# A recipe's earlier values, kept so that the runs made with them stay readable and can be
# reproduced (see the module docstring); never among RECIPES.
VARIANTS: dict[str, ConfigTree] = {
    # paper before it took the release's schedule: the seed code's (RecipeSchedule's defaults)
    "paper-seedcode": replace(PAPER, recipe="paper-seedcode", shares=RecipeSchedule()),
    # dropgaussian before it dropped the world-size prune
    "dropgaussian-wsprune": replace(DROPGAUSSIAN, recipe="dropgaussian-wsprune", growth=replace(
        DROPGAUSSIAN.growth, default=replace(DROPGAUSSIAN.growth.default, prune_world_size=PRUNE_WORLD_SIZE_3DGS))),
    # mcmc before a seed that fills its cap raised it: the seed kept at its size
    "mcmc-keep": replace(MCMC, recipe="mcmc-keep", growth=replace(MCMC.growth, seed_over_cap="keep")),
}

# One line per recipe, for help texts (the module docstring has the full account).
RECIPE_SUMMARIES = {
    "paper": "3DGS as its release trains, its schedule in proportion to the run",
    "dropgaussian": "3DGS with Gaussian dropout, as DropGaussian trains LLFF",
    "sparse": "dropout, the initialiser's depth prior, binocular consistency, growth capped per training pixel, "
              "opacity decay and an opacity regulariser instead of the opacity reset",
    "mcmc": "3DGS as MCMC: dead Gaussians relocated, growth to a per-pixel cap (gsplat's preset)",
}


def recipe_config(name: str) -> ConfigTree:
    """The recipe or variant ``name`` (a tree; ``iterations`` unresolved); ValueError naming the
    valid recipes otherwise."""
    if name in VARIANTS:
        return VARIANTS[name]
    if name not in RECIPES:
        raise ValueError(f"recipe must be one of {list(RECIPES)} (or a kept variant: {list(VARIANTS)}), got {name!r}")
    return RECIPES[name]


def recipe_defaults(name: str) -> dict[str, Any]:
    """The recipe ``name``'s values of the keys it decides (:data:`splat_train.config.RECIPE_KEYS`),
    as flat keys; ValueError naming the valid recipes otherwise."""
    flat = recipe_config(name).to_flat()
    return {k: flat[k] for k in RECIPE_KEYS}


def register_recipe(preset: ConfigTree, summary: str) -> ConfigTree:
    """Add a recipe (a tree whose ``recipe`` is its new name) to :data:`RECIPES` and
    :data:`RECIPE_SUMMARIES`; the CLI's ``--recipe`` and the config keys take it from then on.
    The workflow's config schema lists the recipes it accepts (docs/contracts.md, "Adding a
    recipe")."""
    global RECIPE_NAMES
    if preset.recipe in RECIPES or preset.recipe in VARIANTS:
        raise ValueError(f"a recipe named {preset.recipe!r} exists already")
    RECIPES[preset.recipe] = preset
    RECIPE_SUMMARIES[preset.recipe] = summary
    RECIPE_NAMES = tuple(RECIPES)
    return preset
