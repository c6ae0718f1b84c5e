"""A run's training parts: the list the trainer runs (:func:`recipe_parts`).

A training config (:class:`splat_train.config.TrainConfig`) is a growth strategy
(:mod:`splat_train.strategy`) plus a tuple of part configs (:mod:`splat_train.parts.configs`);
each active config makes its part (:mod:`splat_train.parts.base`), in the order of the registry
:data:`splat_train.parts.configs.PARTS`, which is the order the trainer runs their hooks and adds
their loss terms to the photometric loss. This module makes a run's parts and composes their
opacity maps (:func:`opacity_map`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from splat_train.data import View
from splat_train.parts.base import OpacityFn, TrainPart, ViewRenderer
from splat_train.parts.configs import PartContext, build_parts

__all__ = ["opacity_map", "recipe_parts"]


def recipe_parts(cfg: Any, views: list[View], cameras: list[Tensor], generator: torch.Generator,
                 depth_prior: str | Path | None = None, targets: list[Tensor] | None = None,
                 renderer: ViewRenderer | None = None, schedule: Any = None) -> list[TrainPart]:
    """The training parts of ``cfg`` (its ``parts``, each made by its config), in the order the
    trainer runs them.

    Args:
        cfg: the run's :class:`splat_train.config.TrainConfig` (iterations resolved).
        views: the training views, in the trainer's order (names, image sizes).
        cameras: [4, 4] cam_from_world of each view (world frame of the seed), on the training
            device.
        generator: the trainer's CPU generator (dropout's masks).
        depth_prior: the seed's ``depth_prior.npz``, or None (then no depth term).
        targets: [H, W, 3] training image of each view on the training device, and
        renderer: the trainer; both needed by a part that renders views of its own (binocular).
        schedule: the run's :class:`splat_train.config.Schedule` (None: ``cfg.schedule()``).

    Returns:
        The parts that act in this run (an empty list: plain 3DGS).
    """
    ctx = PartContext(cfg, schedule or cfg.schedule(), views, cameras, generator,
                      None if depth_prior is None else Path(depth_prior), targets, renderer)
    return build_parts(cfg.parts, ctx)


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
