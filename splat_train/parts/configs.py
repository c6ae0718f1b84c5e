"""The configs of the training parts (:mod:`splat_train.parts.base`), one small dataclass per part,
and the registry the training config reads them from.

Each config holds its part's settings, says whether the part acts (:meth:`PartConfig.active`:
its switch at its "off" value means it does not) and makes the part (:meth:`PartConfig.build`,
which imports the part's module: this module stays light, without torch, because the recipes
and the workflow's config check read it). The training config holds a tuple of them
(:attr:`splat_train.config.TrainConfig.parts`); the trainer runs the parts they build in the
order of :data:`PARTS` (the order of their loss terms, opacity maps and random draws):

1. :class:`DropoutConfig` (:mod:`splat_train.parts.dropout`);
2. :class:`DepthPriorConfig` (:mod:`splat_train.parts.depth_prior`; acts only when the seed comes with
   a depth prior);
3. :class:`RegularisersConfig` (:class:`splat_train.parts.regularisers.GaussianRegularisers`);
4. :class:`BinocularConfig` (:mod:`splat_train.parts.binocular`);
5. :class:`OpacityDecayConfig` (:mod:`splat_train.parts.opacity_decay`);
6. :class:`PoseRefinementConfig` (:mod:`splat_train.parts.pose`).

A new part registers its config with :func:`register_part` (docs/contracts.md, "Adding a
training part"); its fields' flat keys then work in ``--config`` and the workflow's ``train:``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar

from runtime.checks import Range
from splat_train.fields import FRACTION, ITERATION, POSITIVE, RATE, WEIGHT, check

if TYPE_CHECKING:
    import torch

    from splat_train.data import View
    from splat_train.parts.base import TrainPart, ViewRenderer

__all__ = ["PartConfig", "PartContext", "PARTS", "register_part", "part_order", "DropoutConfig",
           "DepthPriorConfig", "RegularisersConfig", "BinocularConfig", "OpacityDecayConfig",
           "PoseRefinementConfig", "BINOCULAR_FROM_FRACTION", "OPACITY_DECAY_BINOCULAR"]

log = logging.getLogger(__name__)

# Binocular3DGS's release turns its consistency term on after 20,000 of 30,000 iterations
BINOCULAR_FROM_FRACTION = 20000 / 30000
# and multiplies every opacity by this after each iteration (train.py ``opacity_decay_factor``)
OPACITY_DECAY_BINOCULAR = 0.995


@dataclass(frozen=True)
class PartContext:
    """What a part config may need to make its part for one run.

    Attributes:
        cfg: the run's :class:`splat_train.config.TrainConfig` (iterations resolved).
        schedule: the run's :class:`splat_train.config.Schedule` (resolved once per run).
        views: the training views, in the trainer's order (names, image sizes).
        cameras: [4, 4] cam_from_world of each view (world frame of the seed), on the training device.
        generator: the trainer's CPU generator (every random draw of a part).
        depth_prior: the seed's ``depth_prior.npz``, or None.
        targets: [H, W, 3] training image of each view on the training device (or None), and
        renderer: the trainer (or None); a part that renders views of its own needs both.
    """

    cfg: Any
    schedule: Any
    views: list[View]
    cameras: list[torch.Tensor]
    generator: torch.Generator
    depth_prior: Path | None = None
    targets: list[torch.Tensor] | None = None
    renderer: ViewRenderer | None = None

    @property
    def iterations(self) -> int:
        return int(self.cfg.iterations)

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]


@dataclass(frozen=True)
class PartConfig:
    """Base of the part configs: a frozen dataclass whose fields (with ranges, as
    :mod:`splat_train.fields`) are the part's settings.

    Attributes:
        name: the part's key (the registry's, the checkpoint's ``parts`` and the log line's).
        flat_prefix, flat_names: how its fields are spelt as flat keys (:func:`splat_train.fields.flat_names`).
        reads_depth_prior: whether the part reads the seed's depth prior (the trainer then
            finds it beside the seed, and its bytes are part of the inputs digest).
    """

    name: ClassVar[str] = "part"
    flat_prefix: ClassVar[str] = ""
    flat_names: ClassVar[dict[str, str]] = {}
    reads_depth_prior: ClassVar[bool] = False

    def __post_init__(self) -> None:
        check(self)

    def active(self) -> bool:
        """Whether the part acts (False: its switch is at its off value; nothing is built)."""
        return True

    def check_backend(self, backend: str) -> None:
        """Refuse (ValueError) a rasterizer backend the active part cannot train with; called
        before the run reads anything."""

    def build(self, ctx: PartContext) -> TrainPart | None:
        """The part of one run (None: it has nothing to act on in this run)."""
        raise NotImplementedError


# name -> config class, in the order the trainer runs the parts (register_part appends)
PARTS: dict[str, type[PartConfig]] = {}


def register_part(cls: type[PartConfig]) -> type[PartConfig]:
    """Add a part config class to :data:`PARTS` (a class decorator); its name must be new, and
    its flat keys must not name another field of the training config."""
    if cls.name in PARTS and PARTS[cls.name] is not cls:
        raise ValueError(f"a training part named {cls.name!r} is registered already")
    PARTS[cls.name] = cls
    return cls


def part_order(cfg_cls: type[PartConfig]) -> int:
    """The position of a part config class in the trainer's order."""
    return list(PARTS).index(cfg_cls.name)


@register_part
@dataclass(frozen=True)
class DropoutConfig(PartConfig):
    """Gaussian dropout (DropGaussian; :class:`splat_train.parts.dropout.GaussianDropout`).

    Attributes:
        rate: the final dropout rate (0 = off), ramped in linearly over ``ramp_fraction`` of
            the run.
        ramp_fraction: the share of the run over which the rate ramps in from 0.
    """

    name: ClassVar[str] = "dropout"
    flat_prefix: ClassVar[str] = "dropout_"

    rate: Annotated[float, Range(0.0, 1.0, hi_open=True)] = 0.0
    ramp_fraction: Annotated[float, FRACTION] = 1.0  # DropGaussian's ramp, over the whole run

    def active(self) -> bool:
        return self.rate > 0

    def build(self, ctx: PartContext) -> TrainPart | None:
        from splat_train.parts.dropout import GaussianDropout

        return GaussianDropout(self.rate, ctx.iterations, ctx.generator, self.ramp_fraction)


@register_part
@dataclass(frozen=True)
class DepthPriorConfig(PartConfig):
    """The Pearson depth-prior loss against the initialiser's depths
    (:class:`splat_train.parts.depth_prior.DepthPriorLoss`).

    Attributes:
        weight: weight of the Pearson depth-prior loss (0 = off), ramped in linearly over
            ``ramp_fraction`` of the run; acts only when the seed comes with a depth prior.
        ramp_fraction: the share of the run over which the weight ramps in.
        use_confidence: weight the prior's samples by the initialiser's confidence (False:
            every sample weighs 1; for measuring what the confidence adds).
        min_samples: a training view whose prior has fewer usable samples than this gets no
            depth term (a correlation over a handful of samples constrains nothing reliably).
    """

    name: ClassVar[str] = "depth_prior"
    flat_prefix: ClassVar[str] = "depth_"
    reads_depth_prior: ClassVar[bool] = True

    weight: Annotated[float, WEIGHT] = 0.0
    ramp_fraction: Annotated[float, FRACTION] = 0.0
    use_confidence: bool = True
    min_samples: Annotated[int, Range(2, integer=True)] = 16

    def active(self) -> bool:
        return self.weight > 0

    def build(self, ctx: PartContext) -> TrainPart | None:
        from camio.depth_prior import DEPTH_PRIOR_FILE
        from splat_train.parts.depth_prior import DepthPriorLoss, load_depth_prior

        if ctx.depth_prior is None:
            log.info("depth term off: the seed has no depth prior (%s beside it)", DEPTH_PRIOR_FILE)
            return None
        prior = load_depth_prior(ctx.depth_prior, {v.name: (v.camera.width, v.camera.height) for v in ctx.views},
                                 ctx.cameras[0].device, use_confidence=self.use_confidence,
                                 min_samples=self.min_samples)
        log.info("depth prior %s: %d samples in %d of %d training views", ctx.depth_prior, prior.num_samples,
                 len(prior.views), len(ctx.views))
        return DepthPriorLoss(prior, ctx.names, self.weight, self.ramp_fraction, ctx.iterations)


@register_part
@dataclass(frozen=True)
class RegularisersConfig(PartConfig):
    """The opacity and scale regularisers (gsplat's MCMC losses;
    :class:`splat_train.parts.regularisers.GaussianRegularisers`).

    Attributes:
        opacity_reg: weight of mean(opacity) added to the loss (0 = off).
        scale_reg: weight of mean(scale) added to the loss (0 = off).
    """

    name: ClassVar[str] = "regularisers"

    opacity_reg: Annotated[float, WEIGHT] = 0.0
    scale_reg: Annotated[float, WEIGHT] = 0.0

    def active(self) -> bool:
        return self.opacity_reg > 0 or self.scale_reg > 0

    def build(self, ctx: PartContext) -> TrainPart | None:
        from splat_train.parts.regularisers import GaussianRegularisers

        return GaussianRegularisers(self.opacity_reg, self.scale_reg)


@register_part
@dataclass(frozen=True)
class BinocularConfig(PartConfig):
    """Binocular stereo consistency (Binocular3DGS; :class:`splat_train.parts.binocular.BinocularConsistency`).

    Attributes:
        weight: weight of the binocular stereo consistency term (0 = off): from
            ``from_fraction`` of the run on, each training view is rendered again from a camera
            shifted sideways and warped back with the rendered depth; one more render per
            iteration.
        from_fraction: the share of the run after which the term acts (2/3 as in
            Binocular3DGS's release).
        shift: the largest sideways shift, as a fraction of the view's median rendered depth.
    """

    name: ClassVar[str] = "binocular"
    flat_prefix: ClassVar[str] = "binocular_"

    weight: Annotated[float, WEIGHT] = 0.0
    from_fraction: Annotated[float, FRACTION] = BINOCULAR_FROM_FRACTION
    # Binocular3DGS's shift of up to 0.4 scene units on LLFF is 1.0-1.4 % of the median point
    # depth of fern, horns and trex in their COLMAP frames (splat_train/parts/binocular.py)
    shift: Annotated[float, POSITIVE] = 0.012

    def active(self) -> bool:
        return self.weight > 0

    def build(self, ctx: PartContext) -> TrainPart | None:
        from splat_train.parts.binocular import BinocularConsistency

        if ctx.targets is None or ctx.renderer is None:
            raise ValueError("binocular_weight > 0 needs the training images and a renderer")
        start = round(self.from_fraction * ctx.iterations)
        return BinocularConsistency(self.weight, self.shift, start, ctx.iterations, ctx.targets,
                                    ctx.generator, ctx.renderer)


@register_part
@dataclass(frozen=True)
class OpacityDecayConfig(PartConfig):
    """Binocular3DGS's opacity decay (:class:`splat_train.parts.opacity_decay.OpacityDecay`).

    Attributes:
        factor: the factor every opacity is multiplied by after each iteration from the
            densification start on (1 = off); 0.995 in Binocular3DGS's release, which
            densifies to the end of the run while it acts.
    """

    name: ClassVar[str] = "opacity_decay"
    flat_names: ClassVar[dict[str, str]] = {"factor": "opacity_decay"}

    factor: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 1.0

    def active(self) -> bool:
        return self.factor < 1.0

    def build(self, ctx: PartContext) -> TrainPart | None:
        from splat_train.parts.opacity_decay import OpacityDecay

        return OpacityDecay(self.factor, ctx.schedule.densify_from, ctx.iterations)


@register_part
@dataclass(frozen=True)
class PoseRefinementConfig(PartConfig):
    """Learned se(3) corrections of the training cameras (:class:`splat_train.parts.pose.PoseRefinement`).

    Attributes:
        enabled: learn small se(3) corrections of the training cameras (off by default; the
            first camera and the scale stay fixed).
        lr: Adam rate of the pose corrections (rotation in radians, translation in units of
            the RMS distance of the training-camera centres from the first one).
        start: first iteration at which the poses move (the Gaussians settle first).
        warmup: the pose (and focal) rate ramps linearly from 0 to its value over this many
            iterations after ``pose_refine_from`` (0: no ramp).
        focal: with ``pose_refine``, also learn one log-focal correction per camera (fx and fy
            scaled together).
        lr_focal: Adam rate of the log-focal corrections.
    """

    name: ClassVar[str] = "pose"
    flat_names: ClassVar[dict[str, str]] = {"enabled": "pose_refine", "lr": "lr_pose", "start": "pose_refine_from",
                                            "warmup": "pose_warmup", "focal": "pose_refine_focal"}

    enabled: bool = False
    # From experiments/pose_refinement.py --quick (posed/oracle + VGGT-level noise, 300 iterations): rate
    # 1e-3 from iteration 1 walked the cameras away on fern (ATE 1.5 -> 30 % of the radius) while
    # the Gaussians were still a blur; 1e-4 after 100 iterations with a 100-iteration ramp lowered
    # both errors on both scenes (experiments/README.md, "Camera refinement").
    lr: Annotated[float, RATE] = 1e-4
    start: Annotated[int, ITERATION] = 100
    warmup: Annotated[int, ITERATION] = 100
    focal: bool = False
    lr_focal: Annotated[float, RATE] = 1e-4

    def active(self) -> bool:
        return self.enabled

    def check_backend(self, backend: str) -> None:
        if self.enabled and self.focal and backend == "gsplat":
            # gsplat 1.5.3's projection backward returns no gradient for Ks: the focal
            # corrections would silently stay at zero
            raise ValueError("focal refinement (pose_refine_focal) needs the gradient of the intrinsics, which "
                             "gsplat does not compute; train with rasterizer 'torch' (slower on a GPU) or "
                             "without focal refinement")

    def build(self, ctx: PartContext) -> TrainPart | None:
        from splat_train.parts.pose import PoseRefinement

        return PoseRefinement(ctx.cameras, ctx.names, self.focal, self.lr, self.lr_focal, self.start, self.warmup)


def build_parts(configs: Any, ctx: PartContext) -> list[TrainPart]:
    """The parts that act in a run: each active config's :meth:`PartConfig.build`, in ``configs``'
    order (None results left out)."""
    return [p for c in configs if c.active() and (p := c.build(ctx)) is not None]
