"""A recipe's training parts: the list the trainer runs (:func:`recipe_parts`).

A recipe (:mod:`splat_train.recipes`) is a densification strategy (:mod:`splat_train.densify`,
:mod:`splat_train.mcmc`) plus a list of training parts (:mod:`splat_train.train_part`), made
here from the run's :class:`splat_train.config.TrainConfig` (its recipe values resolved), in
the order the trainer runs their hooks:

1. :class:`splat_train.dropout.GaussianDropout` when ``dropout_rate`` > 0;
2. :class:`splat_train.depth_prior.DepthPriorLoss` when ``depth_weight`` > 0 and the seed
   comes with a depth prior;
3. :class:`GaussianRegularisers` when ``opacity_reg`` or ``scale_reg`` > 0 (``mcmc``);
4. :class:`splat_train.binocular.BinocularConsistency` when ``binocular_weight`` > 0;
5. :class:`splat_train.opacity_decay.OpacityDecay` when ``opacity_decay`` < 1;
6. :class:`splat_train.pose.PoseRefinement` with ``pose_refine``.

The loss terms are added to the photometric loss in this order.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import Tensor

from camio.depth_prior import DEPTH_PRIOR_FILE
from splat_train.binocular import BinocularConsistency
from splat_train.config import TrainConfig
from splat_train.data import View
from splat_train.depth_prior import DepthPriorLoss, load_depth_prior
from splat_train.dropout import GaussianDropout
from splat_train.losses import gaussian_regularisers
from splat_train.opacity_decay import OpacityDecay
from splat_train.pose import PoseRefinement
from splat_train.train_part import OpacityFn, TrainPart, ViewRenderer

__all__ = ["GaussianRegularisers", "opacity_map", "recipe_parts"]

log = logging.getLogger(__name__)


class GaussianRegularisers(TrainPart):
    """The opacity and scale regularisers as a training part (:func:`splat_train.losses.gaussian_regularisers`:
    ``opacity_reg`` mean opacity + ``scale_reg`` mean scale, gsplat's MCMC losses)."""

    name = "regularisers"

    def __init__(self, opacity_reg: float, scale_reg: float) -> None:
        self.opacity_reg, self.scale_reg = float(opacity_reg), float(scale_reg)

    def loss(self, iteration: int, view: int, render: dict[str, Tensor], params: dict[str, Tensor]) -> Tensor | None:
        """The term of ``params["opacity"]`` [N] (logits) and ``params["scales"]`` [N, 3] (log)."""
        return gaussian_regularisers(params["opacity"], params["scales"], self.opacity_reg, self.scale_reg)


def recipe_parts(cfg: TrainConfig, views: list[View], cameras: list[Tensor], generator: torch.Generator,
                 depth_prior: str | Path | None = None, targets: list[Tensor] | None = None,
                 renderer: ViewRenderer | None = None) -> list[TrainPart]:
    """The training parts of ``cfg`` (module docstring), in the order the trainer runs them.

    Args:
        cfg: the run's config (recipe values filled in).
        views: the training views, in the trainer's order (names, image sizes).
        cameras: [4, 4] cam_from_world of each view (world frame of the seed), on the training
            device.
        generator: the trainer's CPU generator (dropout's masks).
        depth_prior: the seed's ``depth_prior.npz``, or None (then no depth term).
        targets: [H, W, 3] training image of each view on the training device, and
        renderer: the trainer; both needed with ``binocular_weight`` > 0.

    Returns:
        The parts that act in this run (an empty list: plain 3DGS).
    """
    parts: list[TrainPart] = []
    names = [v.name for v in views]
    if cfg.dropout_rate > 0:
        parts.append(GaussianDropout(cfg.dropout_rate, cfg.iterations, generator, cfg.dropout_ramp_fraction))
    if depth_prior is not None and cfg.depth_weight > 0:
        prior = load_depth_prior(depth_prior, {v.name: (v.camera.width, v.camera.height) for v in views},
                                 cameras[0].device, use_confidence=cfg.depth_use_confidence,
                                 min_samples=cfg.depth_min_samples)
        log.info("depth prior %s: %d samples in %d of %d training views", depth_prior, prior.num_samples,
                 len(prior.views), len(views))
        parts.append(DepthPriorLoss(prior, names, cfg.depth_weight, cfg.depth_ramp_fraction, cfg.iterations))
    elif cfg.depth_weight > 0:
        log.info("depth term off: the seed has no depth prior (%s beside it)", DEPTH_PRIOR_FILE)
    if cfg.opacity_reg > 0 or cfg.scale_reg > 0:
        parts.append(GaussianRegularisers(cfg.opacity_reg, cfg.scale_reg))
    if cfg.binocular_weight > 0:
        if targets is None or renderer is None:
            raise ValueError("binocular_weight > 0 needs the training images and a renderer")
        start = round(cfg.binocular_from_fraction * cfg.iterations)
        parts.append(BinocularConsistency(cfg.binocular_weight, cfg.binocular_shift, start, cfg.iterations, targets,
                                          generator, renderer))
    if cfg.opacity_decay < 1.0:
        parts.append(OpacityDecay(cfg.opacity_decay, cfg.schedule().densify_from, cfg.iterations))
    if cfg.pose_refine:
        parts.append(PoseRefinement(cameras, names, cfg.pose_refine_focal, cfg.lr_pose, cfg.lr_focal,
                                    cfg.pose_refine_from, cfg.pose_warmup))
    return parts


def opacity_map(parts: list[TrainPart], iteration: int) -> OpacityFn | None:
    """The parts' maps of the training render's [N] opacities at ``iteration``, composed in the
    parts' order (None when no part maps them)."""
    fns = [f for f in (p.opacity_fn(iteration) for p in parts) if f is not None]
    if len(fns) <= 1:
        return fns[0] if fns else None

    def composed(opacities: Tensor) -> Tensor:
        for f in fns:
            opacities = f(opacities)
        return opacities
    return composed
