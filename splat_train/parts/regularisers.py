"""The opacity and scale regularisers as a training part (gsplat's MCMC losses; config
:class:`splat_train.parts.configs.RegularisersConfig`)."""

from __future__ import annotations

import torch

from splat_train.losses import gaussian_regularisers
from splat_train.parts.base import TrainPart

__all__ = ["GaussianRegularisers"]


class GaussianRegularisers(TrainPart):
    """The opacity and scale regularisers as a training part (:func:`splat_train.losses.gaussian_regularisers`:
    ``opacity_reg`` mean opacity + ``scale_reg`` mean scale, gsplat's MCMC losses; config
    :class:`splat_train.parts.configs.RegularisersConfig`)."""

    name = "regularisers"

    def __init__(self, opacity_reg: float, scale_reg: float) -> None:
        self.opacity_reg, self.scale_reg = float(opacity_reg), float(scale_reg)

    def loss(self, iteration: int, view: int, render: dict[str, torch.Tensor],
             params: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """The term of ``params["opacity"]`` [N] (logits) and ``params["scales"]`` [N, 3] (log)."""
        return gaussian_regularisers(params["opacity"], params["scales"], self.opacity_reg, self.scale_reg)

