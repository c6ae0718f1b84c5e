"""The growth strategies' configs (:mod:`splat_train.strategy.base`): one small dataclass per strategy
beside the training config's strategy, :class:`StrategyConfig`.

:class:`StrategyConfig` is the training config's strategy (``ConfigTree.growth``): the one that
runs (``name``, the flat key ``strategy``), what every strategy reads (the refine schedule, the
dead / prune opacity, the growth cap and what a seed over it does), and each strategy's own
settings (:class:`DefaultStrategyConfig`, :class:`MCMCStrategyConfig`). Both are kept because
``seed_over_cap`` "relocate" switches a ``densify`` run to ``mcmc`` when the seed is larger than
the cap. Light (no torch): a strategy's module is imported when one is built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any, ClassVar

from splat_train.fields import COUNT, FRACTION, ITERATION, RATE, WEIGHT, check

if TYPE_CHECKING:
    from splat_train.strategy.base import Strategy

__all__ = ["StrategyConfig", "DefaultStrategyConfig", "MCMCStrategyConfig", "STRATEGIES", "SEED_OVER_CAP",
           "MCMC_GROWTH", "GRAD_THRESHOLD_3DGS", "PRUNE_WORLD_SIZE_3DGS", "CAP_OVER_SEED"]

# 3DGS's densification gradient threshold (the mean NDC view-space gradient norm)
GRAD_THRESHOLD_3DGS = 2e-4
# 3DGS's world-size prune (scene/gaussian_model.py densify_and_prune: largest scale above 0.1 x
# the extent, after the first opacity reset); 0: off, as DropGaussian's release runs
PRUNE_WORLD_SIZE_3DGS = 0.1
# What a run does with a seed larger than its growth cap (a dense initialiser's point map, or
# 3DGS's random initialisation where the views triangulate nothing): "cap" holds the cap, so
# the prune shrinks the model towards it and growth never refills past it; "keep" raises the
# cap to the seed's size; "grow" raises it to CAP_OVER_SEED x the seed's size, so that the seed
# still grows (the mcmc recipe); "relocate" raises it to the seed's size and grows by relocation
# (the mcmc strategy) instead of clone / split / prune. Nothing changes for a seed within the
# cap, except under "grow" where the seed is over 1 / CAP_OVER_SEED of it.
SEED_OVER_CAP = ("cap", "keep", "grow", "relocate")
# "grow": the cap is at least this many times the seed. The 3DGS-MCMC release's smallest
# cap_max over the 100,000 random points it starts from (configs/hotdog.json, 150,000); its
# other configs put the cap 2.7-59x above them.
CAP_OVER_SEED = 1.5
# How the mcmc strategy grows (splat_train.strategy.mcmc.growth_target): "gsplat", 5 % per refine step
# (int(1.05 N), gsplat's MCMCStrategy); "reach_cap", the same unless 5 % per step cannot take
# the seed to the cap within the refine window, in which case the count follows the geometric
# path from the seed's size to the cap over the window's refine steps. Read only by the mcmc
# strategy (the mcmc recipe, or seed_over_cap "relocate").
MCMC_GROWTH = ("gsplat", "reach_cap")



@dataclass(frozen=True)
class DefaultStrategyConfig:
    """3DGS's densification (:class:`splat_train.strategy.densify.DensifyStrategy`); the defaults are the
    official code's.

    Attributes:
        grad_threshold: mean view-space (NDC) positional gradient norm above which a Gaussian
            is cloned (small) or split (large).
        percent_dense: a Gaussian is "large" when its largest scale exceeds this fraction of
            the scene extent.
        opacity_reset_every: set every opacity to min(opacity, opacity_reset_value) this often
            (iterations of this run; 0: never, and no size prune; None: the recipe's share of
            the run).
        opacity_reset_value: the opacity a reset sets.
        prune_screen_size: after the first opacity reset, also remove Gaussians whose 2D
            radius exceeded this many pixels (0: never, as the official 3DGS code and gsplat
            run) ...
        prune_world_size: ... or whose largest scale exceeds this fraction of the extent (0:
            never, as DropGaussian's release runs).
    """

    flat_names: ClassVar[dict[str, str]] = {"grad_threshold": "densify_grad_threshold"}

    grad_threshold: Annotated[float, WEIGHT] = GRAD_THRESHOLD_3DGS
    percent_dense: Annotated[float, WEIGHT] = 0.01
    opacity_reset_every: Annotated[int | None, ITERATION] = None
    opacity_reset_value: Annotated[float, FRACTION] = 0.01
    # off: the official code never applies it (splat_train.recipes)
    prune_screen_size: Annotated[float, WEIGHT] = 0.0
    prune_world_size: Annotated[float, WEIGHT] = PRUNE_WORLD_SIZE_3DGS

    def __post_init__(self) -> None:
        check(self)

    def build(self, strategy: StrategyConfig, schedule: Any, max_gaussians: int | None,
              seed_size: int = 0, **overrides: Any) -> Strategy:
        """The :class:`splat_train.strategy.densify.DensifyStrategy` of this run's ``schedule``
        (:class:`splat_train.config.Schedule`) and cap."""
        from splat_train.strategy.densify import DensifyStrategy

        fields = dict(
            densify_from=schedule.densify_from, densify_until=schedule.densify_until,
            densify_every=schedule.densify_every, opacity_reset_every=schedule.opacity_reset_every,
            grad_threshold=self.grad_threshold, percent_dense=self.percent_dense,
            prune_opacity=strategy.prune_opacity, prune_screen_size=self.prune_screen_size,
            prune_world_size=self.prune_world_size, reset_value=self.opacity_reset_value,
            max_gaussians=max_gaussians)
        fields.update(overrides)
        return DensifyStrategy(**fields)


@dataclass(frozen=True)
class MCMCStrategyConfig:
    """3DGS as MCMC (:class:`splat_train.strategy.mcmc.MCMCStrategy`): reads the refine schedule as its
    relocate / add schedule and ``prune_opacity`` as its dead threshold.

    Attributes:
        growth: how the count grows (:data:`MCMC_GROWTH`): "gsplat", 5 % per refine step up to
            the cap; "reach_cap", the same unless that cannot reach the cap within the refine
            window, then the geometric path from the seed's size to the cap
            (:func:`splat_train.strategy.mcmc.growth_target`).
        noise_lr: the position noise per unit of position rate (gsplat's 5e5).
    """

    flat_names: ClassVar[dict[str, str]] = {"growth": "mcmc_growth"}

    growth: str = MCMC_GROWTH[0]
    noise_lr: Annotated[float, RATE] = 5e5

    def __post_init__(self) -> None:
        check(self)
        if self.growth not in MCMC_GROWTH:
            raise ValueError(f"mcmc_growth must be one of {list(MCMC_GROWTH)}, got {self.growth!r}")

    def build(self, strategy: StrategyConfig, schedule: Any, max_gaussians: int | None,
              seed_size: int = 0, **overrides: Any) -> Strategy:
        """The :class:`splat_train.strategy.mcmc.MCMCStrategy` of this run's ``schedule``, capped at
        ``max_gaussians`` (required: MCMC grows to its cap)."""
        from splat_train.strategy.mcmc import MCMCStrategy

        if max_gaussians is None:
            raise ValueError("the mcmc strategy needs a cap on the Gaussian count: set gaussians_per_pixel > 0 "
                             "or max_gaussians")
        fields = dict(refine_from=schedule.densify_from, refine_until=schedule.densify_until,
                      refine_every=schedule.densify_every, cap=int(max_gaussians),
                      min_opacity=strategy.prune_opacity, noise_lr=self.noise_lr,
                      seed_size=seed_size if self.growth == "reach_cap" else None)
        fields.update(overrides)
        return MCMCStrategy(**fields)


# The growth strategies by name (the flat key ``strategy``) and the StrategyConfig field that
# holds each one's settings.
STRATEGIES = {"densify": "default", "mcmc": "mcmc"}


@dataclass(frozen=True)
class StrategyConfig:
    """The training config's growth strategy.

    Attributes:
        name: how the model grows: "densify" (3DGS clone / split / prune,
            :mod:`splat_train.strategy.densify`) or "mcmc" (relocation of dead Gaussians and 5 % growth
            per refine step up to the cap, :mod:`splat_train.strategy.mcmc`; needs a cap).
        densify_from, densify_until, densify_every: densification (mcmc: refine) window and
            period (iterations of this run; None: the recipe's share of the run).
        prune_opacity: remove Gaussians whose opacity falls below this at densification
            (mcmc: the dead threshold).
        max_gaussians: cap on the Gaussian count (None: none). When the clone and split
            candidates exceed the room left, the ones with the largest view-space gradient
            are kept (:mod:`splat_train.strategy.densify`).
        gaussians_per_pixel: a second cap, this many Gaussians per training pixel (summed
            over the training views at the training resolution); the smaller cap applies.
            0: no such cap.
        seed_over_cap: what a run does with a seed larger than its cap (:data:`SEED_OVER_CAP`):
            "cap" holds the cap (the prune shrinks the model towards it), "keep" raises the cap
            to the seed's size, "grow" raises it to :data:`CAP_OVER_SEED` x the seed's size
            (``mcmc``), "relocate" raises it to the seed's size and grows with the mcmc
            strategy; a seed within the cap trains the same under "cap", "keep" and "relocate".
        default: the densify strategy's own settings.
        mcmc: the mcmc strategy's own settings.
    """

    flat_names: ClassVar[dict[str, str]] = {"name": "strategy"}

    name: str = "densify"
    densify_from: Annotated[int | None, ITERATION] = None
    densify_until: Annotated[int | None, ITERATION] = None
    densify_every: Annotated[int | None, COUNT] = None
    prune_opacity: Annotated[float, FRACTION] = 0.005
    max_gaussians: Annotated[int | None, COUNT] = None
    gaussians_per_pixel: Annotated[float, WEIGHT] = 0.0
    seed_over_cap: str = SEED_OVER_CAP[0]
    default: DefaultStrategyConfig = field(default_factory=DefaultStrategyConfig)
    mcmc: MCMCStrategyConfig = field(default_factory=MCMCStrategyConfig)

    def __post_init__(self) -> None:
        check(self)
        if self.name not in STRATEGIES:
            raise ValueError(f"strategy must be one of {list(STRATEGIES)}, got {self.name!r}")
        if self.seed_over_cap not in SEED_OVER_CAP:
            raise ValueError(f"seed_over_cap must be one of {list(SEED_OVER_CAP)}, got {self.seed_over_cap!r}")
        if self.name == "mcmc" and not self.gaussians_per_pixel and self.max_gaussians is None:
            raise ValueError("the mcmc strategy grows to a cap: set gaussians_per_pixel > 0 or max_gaussians")

    def set_cap(self, train_pixels: int) -> int | None:
        """The cap the config sets, before any seed raises it: the smaller of ``max_gaussians``
        and ``gaussians_per_pixel`` x ``train_pixels``; None: no cap."""
        caps = [c for c in (self.max_gaussians,
                            None if not self.gaussians_per_pixel
                            else max(1, int(self.gaussians_per_pixel * train_pixels))) if c is not None]
        return min(caps) if caps else None

    def max_gaussians_for(self, train_pixels: int, seed_size: int = 0) -> int | None:
        """The Gaussian cap of a run on ``train_pixels`` training pixels (summed over views),
        raised to ``seed_size`` (the seed's Gaussians) unless ``seed_over_cap`` is "cap", and
        to :data:`CAP_OVER_SEED` x ``seed_size`` where it is "grow"; None: no cap."""
        cap = self.set_cap(train_pixels)
        if cap is None or self.seed_over_cap == "cap":
            return cap
        if self.seed_over_cap == "grow":
            return max(cap, math.ceil(CAP_OVER_SEED * int(seed_size)))
        return max(cap, int(seed_size))

    def strategy_for(self, train_pixels: int, seed_size: int) -> str:
        """The strategy that runs: ``name``, or "mcmc" where ``seed_over_cap`` is "relocate" and
        the seed is larger than the cap that holds without it."""
        cap = self.set_cap(train_pixels)
        over = cap is not None and seed_size > cap
        return "mcmc" if self.seed_over_cap == "relocate" and over else self.name

    def settings(self, name: str) -> DefaultStrategyConfig | MCMCStrategyConfig:
        """The own settings of strategy ``name``."""
        return getattr(self, STRATEGIES[name])

    def build(self, name: str, schedule: Any, max_gaussians: int | None, seed_size: int = 0) -> Strategy:
        """Strategy ``name`` (:meth:`strategy_for`) of this run."""
        return self.settings(name).build(self, schedule, max_gaussians, seed_size)
