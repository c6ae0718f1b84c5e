"""The training config's tree: its configs, its flat keys, and the schedule it implies.

A training config is a tree (:class:`ConfigTree`): the run (:class:`RunConfig`), the
optimisation (:class:`OptimConfig`), the growth strategy (``growth``,
:class:`splat_train.strategy.configs.StrategyConfig`), the training parts (a tuple of
:mod:`splat_train.parts.configs` configs) and the recipe's schedule as shares of the run
(:class:`RecipeSchedule`). Every flat key (:data:`FLAT_KEYS`, and those of parts registered
later) names exactly one field of it (:func:`flat_index`, :func:`field_of`). Light (no torch):
the recipes and the workflow's config check read it; :mod:`splat_train.config` builds on it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any

from camio.ply import SH_DEGREE
from runtime.checks import RGB, Range
from runtime.cliargs import is_device
from splat_train.fields import COUNT, FRACTION, ITERATION, POSITIVE, RATE, SEED, THREADS, check, flat_names
from splat_train.parts.configs import PARTS, PartConfig, part_order
from splat_train.strategy.configs import STRATEGIES, StrategyConfig

__all__ = ["ConfigTree", "RunConfig", "OptimConfig", "RecipeSchedule", "Schedule", "BACKGROUND_MEAN",
           "BACKGROUND_BLACK", "SCHEDULE_KEYS", "RECIPE_KEYS", "FLAT_KEYS", "MIN_DENSIFY_EVERY", "DENSIFY_FROM_3DGS",
           "flat_index", "field_of", "check_keys", "apply_flat", "added_at_default", "SEED"]

# A densification period below this would average the view-space gradient over too few views.
MIN_DENSIFY_EVERY = 20
# 3DGS densifies from iteration 500 of the seed code's 10,000 (gsplat's refine_start_iter 500)
DENSIFY_FROM_3DGS = 500 / 10000

# The colour behind the Gaussians (``background``): RGB in [0, 1], or BACKGROUND_MEAN, the mean
# colour of the training images (splat_train.data.mean_colour, resolved once per run by
# splat_train.training.trainer.train). Black is 3DGS's default and the field's recipes'.
BACKGROUND_BLACK = (0.0, 0.0, 0.0)
BACKGROUND_MEAN = "mean"

# Schedule keys: an int in the config is iterations of this run; None takes the recipe's
# share of the run (:class:`RecipeSchedule`).
SCHEDULE_KEYS = ("densify_from", "densify_until", "densify_every", "opacity_reset_every", "sh_increase_every")

@dataclass(frozen=True)
class RunConfig:
    """How a run runs: its length and randomness, the data, the device, checkpoints and evaluation.

    Attributes:
        iterations: optimisation steps; None: :func:`default_iterations` of ``device`` (10,000 on
            a GPU, 1,000 on a CPU), resolved when the config is made from flat keys.
        seed: seed of the run's random generator (view order, random backgrounds, splits,
            dropout masks).
        downsample: integer area-downsampling factor of the training images.
        checkpoint_every: checkpoint period K.
        keep_checkpoints: how many checkpoints to keep.
        eval_every: held-out evaluation period M (only with test cameras): PSNR and SSIM, and
            LPIPS with ``eval_lpips``; 0 disables (final only).
        eval_lpips: also compute LPIPS (v0.1, AlexNet) at every held-out evaluation
            (``log.parquet`` ``test_lpips``). Off by default: the AlexNet pass costs several
            times PSNR + SSIM per view and needs a weight file; the study configs turn it on.
            Without weights the column stays null and a warning says how to get them.
        lpips_weights: folder or file of the LPIPS-alex safetensors weights (None: the
            :func:`imgmetrics.lpips.find_weights` search order, LPIPS_WEIGHTS_DIR then the
            user cache).
        device: "auto" (CUDA when available), "cpu", "cuda" or "cuda:N" (GPU N).
        rasterizer: the :func:`splat_train.rasterize` backend; "auto" = the C++ kernel on CPU,
            gsplat on CUDA when installed (else the PyTorch tile code, with a warning). The
            backend that ran is logged and written to ``train.json`` (``rasterizer``).
        num_threads: torch CPU threads (0: leave torch's default). Default 1: on the 2-core CPU
            machines here, 2 intra-op threads made 30 iterations on a 128x96 scene take 26.7 s
            instead of 0.8 s whenever the other core was busy (spinning worker threads), and
            the rasterizer benchmark saw 2-8x slowdowns at every size; one thread per training
            job also lets Snakemake run two jobs side by side on --cores 2.
        kernel_threads: threads of the C++ rasterizer kernel on CPU (0: every CPU available to
            the process). Its threads do not spin, so it uses the cores torch leaves idle.
        extent_from_points: the scene extent (position rate, world-size prune) is at least 1.1 x
            the median seed distance from the camera mean, not only the camera spread (see
            :func:`splat_train.data.scene_extent`); False keeps the plain 3DGS rule.
    """

    iterations: Annotated[int | None, COUNT] = None
    seed: Annotated[int, SEED] = 0
    downsample: Annotated[int, COUNT] = 1
    checkpoint_every: Annotated[int, COUNT] = 500
    keep_checkpoints: Annotated[int, COUNT] = 2
    eval_every: Annotated[int, ITERATION] = 200
    eval_lpips: bool = False
    lpips_weights: str | None = None
    device: str = "auto"
    rasterizer: str = "auto"
    num_threads: Annotated[int, THREADS] = 1
    kernel_threads: Annotated[int, THREADS] = 0
    extent_from_points: bool = True

    def __post_init__(self) -> None:
        check(self)
        if not is_device(self.device):
            raise ValueError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N' (N = the GPU's index), got {self.device!r}")


@dataclass(frozen=True)
class OptimConfig:
    """The optimisation of the Gaussians: Adam step sizes (for the stored parameterisation), the
    SH degree, the loss and the colour behind the model.

    Attributes:
        sh_degree: maximum SH degree (3 as in 3DGS).
        sh_increase_every: raise the active SH degree by one every so many iterations (None:
            the recipe's share of the run).
        lr_position_init: position rate at the start, multiplied by the scene extent;
            exponential decay over the run.
        lr_position_final: position rate at the end, multiplied by the scene extent.
        lr_sh_dc, lr_sh_rest, lr_opacity, lr_scaling, lr_rotation: constant rates.
        adam_eps: Adam epsilon (3DGS uses 1e-15).
        lambda_dssim: weight of (1 - SSIM) in the loss (1 - w) L1 + w (1 - SSIM).
        background: RGB in [0, 1] behind the Gaussians, or "mean" (:data:`BACKGROUND_MEAN`):
            the mean colour of the training images, pooled over their pixels (an RGBA image
            composited on black for it), resolved once per run by
            :func:`splat_train.training.trainer.train`, which also composites RGBA images on it;
            train.json's config has the colour and its ``background_from`` says which was
            asked. From a few views a held-out view also sees what no training view did, where
            the render is this colour (docs/reference.md section 3a).
        random_background: draw a uniform random background every iteration instead.
    """

    sh_degree: Annotated[int, Range(0, SH_DEGREE, integer=True)] = SH_DEGREE
    sh_increase_every: Annotated[int | None, COUNT] = None
    lr_position_init: Annotated[float, RATE] = 1.6e-4
    lr_position_final: Annotated[float, RATE] = 1.6e-6
    lr_sh_dc: Annotated[float, RATE] = 2.5e-3
    lr_sh_rest: Annotated[float, RATE] = 2.5e-3 / 20.0
    lr_opacity: Annotated[float, RATE] = 0.05
    lr_scaling: Annotated[float, RATE] = 5e-3
    lr_rotation: Annotated[float, RATE] = 1e-3
    adam_eps: Annotated[float, POSITIVE] = 1e-15
    lambda_dssim: Annotated[float, FRACTION] = 0.2
    background: Annotated[list[float] | str, RGB] = BACKGROUND_BLACK
    random_background: bool = False

    def __post_init__(self) -> None:
        check(self)
        if isinstance(self.background, str):
            if self.background != BACKGROUND_MEAN:
                raise ValueError(f"background must be {RGB.describe()} (RGB) or {BACKGROUND_MEAN!r}, "
                                 f"got {self.background!r}")
        else:
            object.__setattr__(self, "background", [float(x) for x in self.background])


@dataclass(frozen=True)
class RecipeSchedule:
    """A recipe's schedule as shares of the run (not flat keys: a schedule key the user sets is
    iterations of this run and wins over these). Each share is a fraction of ``iterations``
    (None: never); ``densify_every_count`` is a period kept at any run length (``paper``'s 100),
    used instead of the share ``densify_every`` where given. The defaults are 3DGS's at the seed
    code's 10,000 iterations.

    Attributes:
        densify_from: the densification start (3DGS: 500 of 10,000).
        densify_until: the densification end.
        densify_every: the densification period as a share of the run (at least
            :data:`MIN_DENSIFY_EVERY` iterations).
        densify_every_count: the densification period in iterations, at any run length.
        opacity_reset_every: the opacity-reset period (3,000 of 10,000; at least 3
            densification periods).
        sh_increase_every: the SH-degree period (1,000 of 10,000).
    """

    densify_from: Annotated[float | None, FRACTION] = DENSIFY_FROM_3DGS
    densify_until: Annotated[float | None, FRACTION] = 1.0
    densify_every: Annotated[float | None, FRACTION] = None
    densify_every_count: Annotated[int | None, COUNT] = 100
    opacity_reset_every: Annotated[float | None, FRACTION] = 0.3
    sh_increase_every: Annotated[float | None, FRACTION] = 0.1

    def __post_init__(self) -> None:
        check(self)


@dataclass(frozen=True)
class Schedule:
    """Iteration counts in effect for one run; ``source`` says where each came from ("set" or
    the recipe's fraction of the run)."""

    densify_from: int
    densify_until: int
    densify_every: int
    opacity_reset_every: int
    sh_increase_every: int
    source: dict[str, str] = field(default_factory=dict, compare=False)

    def sh_degree_at(self, iteration: int, max_degree: int) -> int:
        """Active SH degree at 1-based ``iteration``: +1 every ``sh_increase_every``."""
        return min(max_degree, (iteration - 1) // self.sh_increase_every)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# The flat keys in the order of train.json's ``config`` (the order of the flat dataclass these
# keys were the fields of); keys of parts registered later follow in registry order.
FLAT_KEYS = (
    "iterations", "recipe", "seed", "sh_degree", "sh_increase_every", "lr_position_init", "lr_position_final",
    "lr_sh_dc", "lr_sh_rest", "lr_opacity", "lr_scaling", "lr_rotation", "adam_eps", "lambda_dssim", "background",
    "random_background", "densify_from", "densify_until", "densify_every", "densify_grad_threshold",
    "percent_dense", "opacity_reset_every", "opacity_reset_value", "prune_opacity", "prune_screen_size",
    "prune_world_size", "max_gaussians", "gaussians_per_pixel", "strategy", "seed_over_cap", "mcmc_growth",
    "noise_lr", "opacity_reg", "scale_reg", "dropout_rate", "dropout_ramp_fraction", "depth_weight",
    "depth_ramp_fraction", "depth_use_confidence", "binocular_weight", "binocular_from_fraction",
    "binocular_shift", "opacity_decay", "depth_min_samples", "pose_refine", "lr_pose", "pose_refine_from",
    "pose_warmup", "pose_refine_focal", "lr_focal", "downsample", "checkpoint_every", "keep_checkpoints",
    "eval_every", "eval_lpips", "lpips_weights", "device", "rasterizer", "num_threads", "kernel_threads",
    "extent_from_points")
# Keys whose value None means "the recipe's" (set from the flat vocabulary: the recipe's value
# is kept): the parts' switches and shares, the thresholds every recipe gives, the strategy and
# what a seed over the cap does, the background.
RECIPE_KEYS = ("dropout_rate", "depth_weight", "gaussians_per_pixel", "opacity_reg", "scale_reg",
               "binocular_weight", "opacity_decay", "depth_ramp_fraction", "dropout_ramp_fraction",
               "binocular_from_fraction", "densify_grad_threshold", "prune_screen_size", "prune_world_size",
               "strategy", "seed_over_cap", "mcmc_growth", "background")

# Where a flat key lives: ("recipe",), (group, field) for group in run / optim / growth,
# ("growth", "default" | "mcmc", field), ("part", part name, field).
Location = tuple[str, ...]
_INDEX: dict[tuple, dict[str, Location]] = {}


def flat_index() -> dict[str, Location]:
    """{flat key: where it lives in the tree}, for the registered parts (:data:`FLAT_KEYS` first)."""
    key = tuple(PARTS.values())
    if key not in _INDEX:
        index: dict[str, Location] = {"recipe": ("recipe",)}
        for group, cls in (("run", RunConfig), ("optim", OptimConfig), ("growth", StrategyConfig)):
            index.update({k: (group, f) for f, k in flat_names(cls).items()})
        for name in STRATEGIES.values():
            cls = type(getattr(StrategyConfig(), name))
            index.update({k: ("growth", name, f) for f, k in flat_names(cls).items()})
        for name, cls in PARTS.items():
            for f, k in flat_names(cls).items():
                if k in index:
                    raise ValueError(f"part {name!r}: its key {k!r} names another field of the training config")
                index[k] = ("part", name, f)
        missing = set(FLAT_KEYS) - set(index)
        if missing:
            raise ValueError(f"flat keys without a field: {sorted(missing)}")
        order = [*FLAT_KEYS, *(k for k in index if k not in FLAT_KEYS)]
        _INDEX[key] = {k: index[k] for k in order}
    return _INDEX[key]


def field_of(key: str) -> tuple[type, str]:
    """(the config dataclass, its field) that flat key ``key`` names (``("recipe",)``: ConfigTree's
    ``recipe``): where its type, range, default and description live (the CLI's flags read them)."""
    loc = flat_index()[key]
    if loc[0] == "recipe":
        return ConfigTree, "recipe"
    if loc[0] == "part":
        return PARTS[loc[1]], loc[2]
    cls = {"run": RunConfig, "optim": OptimConfig, "growth": StrategyConfig}[loc[0]]
    if len(loc) == 3:
        cls = type(getattr(StrategyConfig(), loc[1]))
    return cls, loc[-1]


def added_at_default(flat: dict[str, Any]) -> set[str]:
    """The keys of ``flat`` beyond :data:`FLAT_KEYS` (of parts registered since) whose value is
    their part's default: left out of the inputs digest and the resume check, so that adding a
    part leaves every run without it as it was (its digest, its checkpoints)."""
    index = flat_index()
    out = set()
    for key in flat.keys() - set(FLAT_KEYS):
        loc = index.get(key)
        if loc is not None and loc[0] == "part" and flat[key] == getattr(PARTS[loc[1]](), loc[2]):
            out.add(key)
    return out


def check_keys(keys: dict[str, Any]) -> None:
    known = flat_index()
    unknown = sorted(set(keys) - set(known))
    if unknown:
        raise ValueError(f"unknown training config keys {unknown}; valid keys: {sorted(known)}")


@dataclass(frozen=True)
class ConfigTree:
    """Every hyperparameter of a training run, as a tree: what a recipe is
    (:mod:`splat_train.recipes`), and the base of :class:`splat_train.config.TrainConfig`. A
    flat key reads as an attribute (``cfg.dropout_rate``; ``cfg.strategy`` is the strategy's
    name, its config ``cfg.growth``); :meth:`to_flat` gives them all.

    Attributes:
        recipe: the recipe the config was made from ("sparse", the default, "paper",
            "dropgaussian" or "mcmc"; :mod:`splat_train.recipes`).
        run: iterations, seed, data, device, threads, checkpoints, evaluation.
        optim: learning rates, SH degree, loss, background.
        growth: the growth strategy (flat key ``strategy``: its name) and its settings.
        parts: the training parts' configs, in the trainer's order (:data:`splat_train.parts.configs.PARTS`).
        shares: the recipe's schedule as shares of the run.
    """

    recipe: str
    run: RunConfig = field(default_factory=RunConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    growth: StrategyConfig = field(default_factory=StrategyConfig)
    parts: tuple[PartConfig, ...] = ()
    shares: RecipeSchedule = field(default_factory=RecipeSchedule)

    def __post_init__(self) -> None:
        if not isinstance(self.recipe, str) or not self.recipe:
            raise ValueError(f"a training config names its recipe, got {self.recipe!r}")
        object.__setattr__(self, "parts", tuple(sorted(self.parts, key=lambda c: part_order(type(c)))))

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        index = flat_index()
        if name not in index:
            raise AttributeError(f"{type(self).__name__!s} has no field or flat key {name!r}")
        return self.flat(name)

    def flat(self, key: str) -> Any:
        """The value of flat key ``key``."""
        loc = flat_index()[key]
        if loc[0] == "recipe":
            return self.recipe
        if loc[0] == "part":
            return getattr(self.part(loc[1]), loc[2])
        obj = object.__getattribute__(self, loc[0])
        for step in loc[1:]:
            obj = getattr(obj, step)
        return obj

    def part(self, name: str) -> PartConfig:
        """The config of part ``name``: the tree's, or the part's defaults (off) where the tree has none."""
        return next((c for c in self.parts if c.name == name), None) or PARTS[name]()

    def to_flat(self) -> dict[str, Any]:
        """The flat dict (train.json's ``config``): every key, in :data:`FLAT_KEYS` order."""
        return {k: self.flat(k) for k in flat_index()}

    to_dict = to_flat

    def schedule(self) -> Schedule:
        """The iteration counts of this run: the values set, else the recipe's shares of
        ``iterations`` (see the module docstring); ``source`` says which for each key."""
        shares, name = self.shares, self.recipe
        n = int(self.run.iterations)
        values: dict[str, int] = {}
        source: dict[str, str] = {}
        for key in SCHEDULE_KEYS:
            set_value = self.flat(key)
            frac = getattr(shares, key)
            if set_value is not None:
                values[key], source[key] = int(set_value), "set"
            elif key == "densify_every" and shares.densify_every_count is not None:  # paper's period
                values[key], source[key] = int(shares.densify_every_count), f"recipe {name}"
            elif frac is None:  # the recipe never does it (sparse: no reset)
                values[key], source[key] = 0, f"recipe {name}: never"
            else:
                values[key] = max(1, int(round(frac * n)))
                source[key] = f"recipe {name}: {frac:g} x {n}"
        if source["densify_every"] != "set" and shares.densify_every_count is None:
            values["densify_every"] = max(values["densify_every"], MIN_DENSIFY_EVERY)
        if source["opacity_reset_every"] != "set" and values["opacity_reset_every"] > 0:
            # a reset needs time to recover: never more often than every 3 densifications
            values["opacity_reset_every"] = max(values["opacity_reset_every"], 3 * values["densify_every"])
        return Schedule(**values, source=source)

    def reads_depth_prior(self) -> bool:
        """Whether an active part reads the seed's depth prior."""
        return any(c.reads_depth_prior and c.active() for c in self.parts)

    def max_gaussians_for(self, train_pixels: int, seed_size: int = 0) -> int | None:
        """The Gaussian cap of a run (:meth:`splat_train.strategy.configs.StrategyConfig.max_gaussians_for`)."""
        return self.growth.max_gaussians_for(train_pixels, seed_size)

    def strategy_for(self, train_pixels: int, seed_size: int) -> str:
        """The strategy that runs (:meth:`splat_train.strategy.configs.StrategyConfig.strategy_for`)."""
        return self.growth.strategy_for(train_pixels, seed_size)




def apply_flat(tree: dict[str, Any], flat: dict[str, Any]) -> dict[str, Any]:
    """``tree`` (run, optim, growth, parts, shares) with the flat keys ``flat`` set; None for a
    :data:`RECIPE_KEYS` key keeps the tree's value. Each changed config is made again, so its
    checks run."""
    check_keys(flat)
    index = flat_index()
    groups: dict[Location, dict[str, Any]] = {}
    for key, value in flat.items():
        loc = index[key]
        if loc[0] == "recipe" or (value is None and key in RECIPE_KEYS):
            continue
        groups.setdefault(loc[:-1], {})[loc[-1]] = value
    out = dict(tree)
    for group in ("run", "optim"):
        if (group,) in groups:
            out[group] = dataclasses.replace(out[group], **groups[(group,)])
    growth = out["growth"]
    own = {name: dataclasses.replace(getattr(growth, name), **groups[("growth", name)])
           for name in STRATEGIES.values() if ("growth", name) in groups}
    if own or ("growth",) in groups:
        out["growth"] = dataclasses.replace(growth, **groups.get(("growth",), {}), **own)
    parts = {c.name: c for c in out["parts"]}
    for loc, values in groups.items():
        if loc[0] == "part":
            old = parts.get(loc[1])
            parts[loc[1]] = dataclasses.replace(old, **values) if old is not None else PARTS[loc[1]](**values)
    out["parts"] = tuple(parts.values())
    return out
