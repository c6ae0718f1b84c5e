"""Training hyperparameters (the evaluation protocol's defaults) and the schedule they imply.

Every key is a field of :class:`TrainConfig`. The keys a training *recipe* decides
(:mod:`splat_train.recipes`, chosen by ``recipe``) default to None
and take the recipe's value when the config is made; a value the user sets is kept as it is.
Schedule keys (densify_from, densify_until, densify_every, opacity_reset_every,
sh_increase_every) are iterations of this run: the recipes give them as fractions of the run
(``densify_until_fraction`` ...), resolved once by :meth:`TrainConfig.schedule` and printed by
the trainer; a number the user writes is never rescaled.

At the paper's 10,000 iterations the ``paper`` recipe gives the seed code's counts: densify
from 500 to 10000 every 100, reset opacity every 3000, raise the SH degree every 1000 up to 3.
A shorter run compresses them in proportion (the densification *period* stays 100 in
``paper``: densifying 5x as often in a 5x shorter run grew 4000 seeds to 120k Gaussians by
iteration 400 on the 256 px synthetic scene); the scaled opacity-reset period is kept >= 3
densification periods (a reset needs time to recover). The learning rates are not scaled; the
position rate decays exponentially over the whole run whatever its length.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

__all__ = ["TrainConfig", "Schedule", "DEFAULT_ITERATIONS", "PAPER_ITERATIONS", "default_iterations", "resolve_device",
           "RESUME_FREE_KEYS", "POSE_KEYS", "BACKGROUND_MEAN", "load_config"]

from camio.ply import SH_DEGREE
from runtime.checks import RGB, Range, check_fields
from runtime.cliargs import is_device
from splat_train.recipes import (BACKGROUND_MEAN, DEFAULT_RECIPE, MIN_DENSIFY_EVERY, PART_KEYS, RAMP_KEYS, RECIPE_NAMES, SCHEDULE_KEYS,
                                 STRATEGIES, SEED_OVER_CAP, MCMC_GROWTH, VALUE_KEYS,
                                 recipe_defaults)

# Training iterations on a CPU when none are given: finishes in minutes on a 2-core machine;
# on a GPU the paper's 10,000 (PAPER_ITERATIONS). Timings: benchmarks/README.md.
DEFAULT_ITERATIONS = 1000
# The paper's budget ("10K iterations", docs/reference.md section 3): the default on a GPU, and the
# run length the seed code's schedule was written for.
PAPER_ITERATIONS = 10000


def resolve_device(device: str) -> str:
    """The config's ``device`` with 'auto' resolved: 'cuda' when torch sees a CUDA GPU, else 'cpu'."""
    if device == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def default_iterations(device: str) -> int:
    """Iterations of a run that names none: :data:`PAPER_ITERATIONS` where training runs on a
    GPU (``device`` 'cuda', or 'auto' with a CUDA device visible), :data:`DEFAULT_ITERATIONS`
    on a CPU."""
    return PAPER_ITERATIONS if resolve_device(device).startswith("cuda") else DEFAULT_ITERATIONS


# The ranges of the fields (each field names its own beside its default; runtime.checks.Range).
# Iteration counts and periods: a count >= 1, a start or a period where 0 means never >= 0.
COUNT = Range(1, integer=True)
ITERATION = Range(0, integer=True)
# Adam step sizes (a rate of 0 freezes the parameter) and loss weights / thresholds (0 = off).
RATE = Range(0.0)
WEIGHT = Range(0.0)
POSITIVE = Range(0.0, lo_open=True)
# Probabilities, fractions of the run, opacities.
FRACTION = Range(0.0, 1.0)
# torch.manual_seed's range: an unsigned 64-bit integer.
SEED = Range(0, 2**64 - 1, integer=True)
# Thread counts: 0 = the library's own choice.
THREADS = Range(0, integer=True)

# Config fields that do not change the optimisation result: they may differ on resume.
# The rasterizer backend is among them: the backends are parity-tested against one reference
# (tests/test_raster_parity.py, tests/test_raster_gsplat.py), so a run started on CPU may go on
# on a GPU, and checkpoints written before the key existed still resume.
RESUME_FREE_KEYS = ("checkpoint_every", "keep_checkpoints", "eval_every", "num_threads", "kernel_threads",
                    "rasterizer", "eval_lpips", "lpips_weights")
# Config fields that only matter with pose_refine: a run without refinement may resume a
# checkpoint that differs in them (or predates them).
POSE_KEYS = ("lr_pose", "pose_refine_from", "pose_warmup", "pose_refine_focal", "lr_focal")


@dataclass
class TrainConfig:
    """Every hyperparameter of a training run. Field names are the JSON override keys; each
    field's type and range is its annotation (``Annotated[float, RATE]``; the ranges above),
    checked when the config is made (:func:`runtime.checks.check_fields`) and taken by the
    flag that sets it.

    Attributes (learning rates are Adam step sizes for the stored parameterisation):
        iterations: optimisation steps; None (the default): :func:`default_iterations` of
            ``device`` (10,000 on a GPU, 1,000 on a CPU), resolved when the config is made.
        recipe: "sparse" (the default), "paper", "dropgaussian" or "mcmc"
            (:mod:`splat_train.recipes`); fills every key below whose value is None.
        seed: seed of the run's random generator (view order, random backgrounds, splits,
            dropout masks).
        sh_degree: maximum SH degree (3 as in 3DGS).
        sh_increase_every: raise the active SH degree by one every so many iterations.
        lr_position_init, lr_position_final: position rate at the start / end, multiplied by
            the scene extent; exponential decay over the run.
        lr_sh_dc, lr_sh_rest, lr_opacity, lr_scaling, lr_rotation: constant rates.
        adam_eps: Adam epsilon (3DGS uses 1e-15).
        lambda_dssim: weight of (1 - SSIM) in the loss (1 - w) L1 + w (1 - SSIM).
        background: RGB in [0, 1] behind the Gaussians, or "mean" (:data:`BACKGROUND_MEAN`):
            the mean colour of the training images, pooled over their pixels (an RGBA image
            composited on black for it), resolved once by :func:`splat_train.trainer.train`,
            which also composites RGBA images on it; train.json's config has the colour and
            its ``background_from`` says which was asked. None: the recipe's (black in the
            field's recipes, the mean in ``sparse``). From a few views a held-out view also
            sees what no training view did, where the render is this colour (docs/reference.md
            section 3a).
        random_background: draw a uniform random background every iteration instead.
        densify_from, densify_until, densify_every: densification window and period
            (iterations of this run; None: the recipe's fraction of the run).
        densify_grad_threshold: mean view-space (NDC) positional gradient norm above which a
            Gaussian is cloned (small) or split (large); None: the recipe's (3DGS's 2e-4;
            ``dropgaussian``: 5e-4).
        percent_dense: a Gaussian is "large" when its largest scale exceeds this fraction of
            the scene extent.
        opacity_reset_every: set every opacity to min(opacity, opacity_reset_value) this often
            (0: never, and no size prune; None: the recipe's: ``paper`` every 30 % of the run,
            ``sparse`` never).
        prune_opacity: remove Gaussians whose opacity falls below this at densification.
        prune_screen_size: after the first opacity reset, also remove Gaussians whose 2D
            radius exceeded this many pixels (0: never, as the official 3DGS code and gsplat
            run; None: the recipe's, 0 in every recipe) ...
        prune_world_size: ... or whose largest scale exceeds this fraction of the extent.
        max_gaussians: cap on the Gaussian count (None: none). When the clone and split
            candidates exceed the room left, the ones with the largest view-space gradient
            are kept (:mod:`splat_train.densify`).
        gaussians_per_pixel: a second cap, this many Gaussians per training pixel (summed
            over the training views at the training resolution); the smaller cap applies.
            0: no such cap; None: the recipe's value (``paper``: no cap; ``sparse``: 0.1).
        strategy: how the model grows: "densify" (3DGS clone / split / prune,
            :mod:`splat_train.densify`) or "mcmc" (relocation of dead Gaussians and 5 % growth
            per refine step up to the cap, :mod:`splat_train.mcmc`; needs a cap, and reads the
            densify_* schedule as its refine schedule and prune_opacity as its dead
            threshold); None: the recipe's (``mcmc`` for the ``mcmc`` recipe, ``densify`` in
            the others).
        seed_over_cap: what a run does with a seed larger than its cap (:data:`SEED_OVER_CAP`):
            "cap" holds the cap (the prune shrinks the model towards it), "keep" raises the cap
            to the seed's size, "relocate" raises it and grows with the mcmc strategy; a seed
            within the cap trains the same under all three; None: the recipe's.
        mcmc_growth: with the mcmc strategy, how the count grows (:data:`MCMC_GROWTH`): "gsplat",
            5 % per refine step up to the cap; "reach_cap", the same unless that cannot reach
            the cap within the refine window, then the geometric path from the seed's size to
            the cap (:func:`splat_train.mcmc.growth_target`); None: the recipe's.
        noise_lr: with the mcmc strategy, the position noise per unit of position rate
            (gsplat's 5e5).
        opacity_reg, scale_reg: weights of mean(opacity) and mean(scale) added to the loss
            (0 = off; None: the recipe's, 0.01 each in ``mcmc``, off elsewhere).
        dropout_rate: Gaussian dropout's final rate (0 = off; None: the recipe's), ramped in
            linearly over ``dropout_ramp_fraction`` of the run: :mod:`splat_train.dropout`.
        dropout_ramp_fraction: see ``dropout_rate`` (None: the recipe's; 1 in every recipe).
        depth_weight: weight of the Pearson depth-prior loss (0 = off; None: the recipe's),
            ramped in linearly over ``depth_ramp_fraction`` of the run; acts only when the
            seed comes with a depth prior (:mod:`splat_train.depth_prior`).
        depth_ramp_fraction: see ``depth_weight`` (None: the recipe's).
        binocular_weight: weight of the binocular stereo consistency term (0 = off; None: the
            recipe's, 1 in ``sparse``, off in the others): from ``binocular_from_fraction`` of
            the run on, each training view is rendered again from a camera shifted sideways and
            warped back with the rendered depth (:mod:`splat_train.binocular`); one more render
            per iteration.
        binocular_from_fraction: see ``binocular_weight`` (None: the recipe's, the
            densification start in ``sparse``, 2/3 as in Binocular3DGS's release in the others).
        binocular_shift: the largest sideways shift, as a fraction of the view's median rendered
            depth.
        opacity_decay: the factor every opacity is multiplied by after each iteration from the
            densification start on (1 = off; None: the recipe's): Binocular3DGS's opacity decay
            (:mod:`splat_train.opacity_decay`), 0.995 in its release, which densifies to the end
            of the run while it acts.
        depth_use_confidence: weight the prior's samples by the initialiser's confidence
            (False: every sample weighs 1; for measuring what the confidence adds).
        depth_min_samples: a training view whose prior has fewer usable samples than this gets
            no depth term (a correlation over a handful of samples constrains nothing reliably).
        pose_refine: learn small se(3) corrections of the training cameras (off by default;
            the first camera and the scale stay fixed, :mod:`splat_train.pose`).
        lr_pose: Adam rate of the pose corrections (rotation in radians, translation in units
            of the RMS distance of the training-camera centres from the first one).
        pose_refine_from: first iteration at which the poses move (the Gaussians settle first).
        pose_warmup: the pose (and focal) rate ramps linearly from 0 to its value over this
            many iterations after ``pose_refine_from`` (0: no ramp).
        pose_refine_focal: with ``pose_refine``, also learn one log-focal correction per
            camera (fx and fy scaled together).
        lr_focal: Adam rate of the log-focal corrections.
        downsample: integer area-downsampling factor of the training images.
        checkpoint_every, keep_checkpoints: checkpoint period and how many to keep.
        eval_every: held-out evaluation period (only with test cameras): PSNR and SSIM, and
            LPIPS with ``eval_lpips``; 0 disables (final only).
        eval_lpips: also compute LPIPS (v0.1, AlexNet) at every held-out evaluation
            (``log.parquet`` ``test_lpips``). Off by default: the AlexNet pass costs several
            times PSNR + SSIM per view and needs a weight file; the study configs turn it on. Without weights the column stays null and a warning says how to get them.
        lpips_weights: folder or file of the LPIPS-alex safetensors weights (None: the
            :func:`imgmetrics.lpips.find_weights` search order, LPIPS_WEIGHTS_DIR then the
            user cache).
        device: "auto" (CUDA when available), "cpu", "cuda" or "cuda:N" (GPU N).
        rasterizer: the :func:`splat_train.rasterize` backend; "auto" = the C++ kernel on CPU,
            gsplat on CUDA when installed (else the PyTorch tile code, with a warning). The
            backend that ran is logged and written to ``train.json`` (``rasterizer``).
        extent_from_points: the scene extent (position rate, world-size prune) is at least 1.1 x
            the median seed distance from the camera mean, not only the camera spread (see
            :func:`splat_train.data.scene_extent`); False keeps the plain 3DGS rule.
        kernel_threads: threads of the C++ rasterizer kernel on CPU (0: every CPU available to
            the process). Its threads do not spin, so it uses the cores torch leaves idle.
        num_threads: torch CPU threads (0: leave torch's default). Default 1: on the 2-core CPU
            machines here, 2 intra-op threads made 30 iterations on a 128x96 scene take 26.7 s
            instead of 0.8 s whenever the other core was busy (spinning worker threads), and
            the rasterizer benchmark saw 2-8x slowdowns at every size; one thread per training
            job also lets Snakemake run two jobs side by side on --cores 2.
    """

    iterations: Annotated[int | None, COUNT] = None
    recipe: str = DEFAULT_RECIPE
    seed: Annotated[int, SEED] = 0
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
    background: Annotated[list[float] | str | None, RGB] = None
    random_background: bool = False
    densify_from: Annotated[int | None, ITERATION] = None
    densify_until: Annotated[int | None, ITERATION] = None
    densify_every: Annotated[int | None, COUNT] = None
    densify_grad_threshold: Annotated[float | None, WEIGHT] = None
    percent_dense: Annotated[float, WEIGHT] = 0.01
    opacity_reset_every: Annotated[int | None, ITERATION] = None
    opacity_reset_value: Annotated[float, FRACTION] = 0.01
    prune_opacity: Annotated[float, FRACTION] = 0.005
    prune_screen_size: Annotated[float | None, WEIGHT] = None
    prune_world_size: Annotated[float, WEIGHT] = 0.1
    max_gaussians: Annotated[int | None, COUNT] = None
    gaussians_per_pixel: Annotated[float | None, WEIGHT] = None
    strategy: str | None = None
    seed_over_cap: str | None = None
    mcmc_growth: str | None = None
    noise_lr: Annotated[float, RATE] = 5e5
    opacity_reg: Annotated[float | None, WEIGHT] = None
    scale_reg: Annotated[float | None, WEIGHT] = None
    dropout_rate: Annotated[float | None, Range(0.0, 1.0, hi_open=True)] = None
    dropout_ramp_fraction: Annotated[float | None, FRACTION] = None
    depth_weight: Annotated[float | None, WEIGHT] = None
    depth_ramp_fraction: Annotated[float | None, FRACTION] = None
    depth_use_confidence: bool = True
    binocular_weight: Annotated[float | None, WEIGHT] = None
    binocular_from_fraction: Annotated[float | None, FRACTION] = None
    # Binocular3DGS's shift of up to 0.4 scene units on LLFF is 1.0-1.4 % of the median point
    # depth of fern, horns and trex in their COLMAP frames (splat_train/binocular.py)
    binocular_shift: Annotated[float, POSITIVE] = 0.012
    opacity_decay: Annotated[float | None, Range(0.0, 1.0, lo_open=True)] = None
    depth_min_samples: Annotated[int, Range(2, integer=True)] = 16
    pose_refine: bool = False
    # From benchmarks/bench_pose.py --quick (posed/oracle + VGGT-level noise, 300 iterations): rate
    # 1e-3 from iteration 1 walked the cameras away on fern (ATE 1.5 -> 30 % of the radius) while
    # the Gaussians were still a blur; 1e-4 after 100 iterations with a 100-iteration ramp lowered
    # both errors on both scenes (benchmarks/README.md).
    lr_pose: Annotated[float, RATE] = 1e-4
    pose_refine_from: Annotated[int, ITERATION] = 100
    pose_warmup: Annotated[int, ITERATION] = 100
    pose_refine_focal: bool = False
    lr_focal: Annotated[float, RATE] = 1e-4
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
        check_fields(self)  # every field's type and range, as annotated above
        if not is_device(self.device):
            raise ValueError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N' (N = the GPU's index), got {self.device!r}")
        if self.iterations is None:
            self.iterations = default_iterations(self.device)
        preset = recipe_defaults(self.recipe)
        for key in (*PART_KEYS, *RAMP_KEYS, *VALUE_KEYS):
            if getattr(self, key) is None:
                setattr(self, key, preset[key])
        check_fields(self)  # the recipe's values too
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {list(STRATEGIES)}, got {self.strategy!r}")
        if self.seed_over_cap not in SEED_OVER_CAP:
            raise ValueError(f"seed_over_cap must be one of {list(SEED_OVER_CAP)}, got {self.seed_over_cap!r}")
        if self.mcmc_growth not in MCMC_GROWTH:
            raise ValueError(f"mcmc_growth must be one of {list(MCMC_GROWTH)}, got {self.mcmc_growth!r}")
        if self.strategy == "mcmc" and not self.gaussians_per_pixel and self.max_gaussians is None:
            raise ValueError("the mcmc strategy grows to a cap: set gaussians_per_pixel > 0 or max_gaussians")
        if isinstance(self.background, str):
            if self.background != BACKGROUND_MEAN:
                raise ValueError(f"background must be {RGB.describe()} (RGB) or {BACKGROUND_MEAN!r}, "
                                 f"got {self.background!r}")
        else:
            self.background = [float(x) for x in self.background]
        from splat_train.rasterize import BACKENDS

        if self.rasterizer not in BACKENDS:
            raise ValueError(f"rasterizer must be one of {BACKENDS}, got {self.rasterizer!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **overrides: Any) -> "TrainConfig":
        """A copy with ``overrides`` applied; unknown keys raise ValueError naming them."""
        _check_keys(overrides)
        return dataclasses.replace(self, **overrides)

    def schedule(self) -> "Schedule":
        """The iteration counts of this run: the values set, else the recipe's fractions of
        ``iterations`` (see the module docstring); ``source`` says which for each key."""
        preset = recipe_defaults(self.recipe)
        n = int(self.iterations)
        values: dict[str, int] = {}
        source: dict[str, str] = {}
        for key in SCHEDULE_KEYS:
            set_value = getattr(self, key)
            if set_value is not None:
                values[key], source[key] = int(set_value), "set"
            elif key in preset:  # an absolute count of the recipe (paper's period)
                values[key], source[key] = int(preset[key]), f"recipe {self.recipe}"
            elif preset[f"{key}_fraction"] is None:  # the recipe never does it (sparse: no reset)
                values[key], source[key] = 0, f"recipe {self.recipe}: never"
            else:
                frac = preset[f"{key}_fraction"]
                values[key] = max(1, int(round(frac * n)))
                source[key] = f"recipe {self.recipe}: {frac:g} x {n}"
        if source["densify_every"] != "set" and "densify_every" not in preset:
            values["densify_every"] = max(values["densify_every"], MIN_DENSIFY_EVERY)
        if source["opacity_reset_every"] != "set" and values["opacity_reset_every"] > 0:
            # a reset needs time to recover: never more often than every 3 densifications
            values["opacity_reset_every"] = max(values["opacity_reset_every"], 3 * values["densify_every"])
        return Schedule(**values, source=source)

    def max_gaussians_for(self, train_pixels: int, seed_size: int = 0) -> int | None:
        """The Gaussian cap of a run on ``train_pixels`` training pixels (summed over views):
        the smaller of ``max_gaussians`` and ``gaussians_per_pixel`` x pixels, raised to
        ``seed_size`` (the seed's Gaussians) unless ``seed_over_cap`` is "cap"; None: no cap."""
        cap = self._set_cap(train_pixels)
        if cap is None or self.seed_over_cap == "cap":
            return cap
        return max(cap, int(seed_size))

    def strategy_for(self, train_pixels: int, seed_size: int) -> str:
        """The growth strategy of a run: ``strategy``, or "mcmc" where ``seed_over_cap`` is
        "relocate" and the seed is larger than the cap that holds without it."""
        cap = self._set_cap(train_pixels)
        over = cap is not None and seed_size > cap
        return "mcmc" if self.seed_over_cap == "relocate" and over else self.strategy

    def _set_cap(self, train_pixels: int) -> int | None:
        """The cap the config sets, before any seed raises it: the smaller of ``max_gaussians``
        and ``gaussians_per_pixel`` x ``train_pixels``; None: no cap."""
        caps = [c for c in (self.max_gaussians,
                            None if not self.gaussians_per_pixel
                            else max(1, int(self.gaussians_per_pixel * train_pixels))) if c is not None]
        return min(caps) if caps else None


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


def _check_keys(keys: dict[str, Any]) -> None:
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(keys) - known)
    if unknown:
        raise ValueError(f"unknown training config keys {unknown}; valid keys: {sorted(known)}")


def load_config(overrides: str | Path | dict | None = None, **cli: Any) -> TrainConfig:
    """Defaults, then JSON overrides (a file path, a JSON string or a dict), then ``cli``
    values that are not None (the CLI flags win).

    Raises:
        ValueError: one line naming the source ("--config FILE: lr_opacity must be a finite
            number >= 0, got -1"): an unreadable or malformed file, an unknown key, a value of
            the wrong type or out of its field's range.
    """
    data: dict[str, Any] = {}
    source = "config"
    if isinstance(overrides, dict):
        data = dict(overrides)
    elif overrides is not None:
        text = str(overrides)
        p = Path(text)
        source = f"--config {text}" if p.is_file() else "--config (JSON string)"
        try:
            data = json.loads(p.read_text() if p.is_file() else text)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{source}: must be a JSON file or a JSON object string: {exc}") from exc
        if not isinstance(data, dict):
            raise ValueError(f"{source}: must hold a JSON object, got {type(data).__name__}")
    data.update({k: v for k, v in cli.items() if v is not None})
    try:
        _check_keys(data)
        return TrainConfig(**data)  # made once, so an unset iterations follows the device given
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None

