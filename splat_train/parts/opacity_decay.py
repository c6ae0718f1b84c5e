"""Opacity decay (Binocular3DGS, Han et al., NeurIPS 2024, Sec. 3.3): every Gaussian's opacity
shrinks by a constant factor after each iteration, so that only those the training views keep
needing stay opaque.

The paper's rule, alpha <- lambda alpha with lambda = 0.995, applied in its release
(hanl2010/Binocular3DGS ``train.py``, ``GaussianModel.opacity_decay``) to the opacity in
[0, 1] after every backward pass from the densification start on, stored back as a logit;
the Adam state is left alone. A Gaussian the photometric gradient holds up climbs back each
step; one it does not fades below the prune threshold (opacity 0.005) and the next
densification step removes it. The release also densifies to the end of training while the
decay is on (and never resets opacity): the prune is what turns the decay into a smaller
model, so a run that stops densifying early keeps its faded Gaussians to the end.

Per iteration the decay moves a logit x by about -(1 - lambda) / (1 - sigmoid(x)), -0.05 at
opacity 0.9: as much as one Adam step at 3DGS's opacity rate (0.05), so a nearly opaque
Gaussian stays so only while its gradient keeps pushing it up.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from splat_train.parts.base import TrainPart

__all__ = ["OpacityDecay", "opacity_decay"]


def opacity_decay(opacity_logits: Tensor, factor: float) -> Tensor:
    """Binocular3DGS's opacity decay, alpha <- factor alpha, on logits.

    Args:
        opacity_logits: [N] logit(alpha) of the Gaussians.
        factor: lambda in (0, 1].

    Returns:
        [N] logit(factor sigmoid(x)), as log(factor) - softplus(-x) - log1p(-factor sigmoid(x)):
        finite for every finite x (no logit of 0 or 1), about x + log(factor) where alpha is
        small; x itself when factor is 1.
    """
    if factor == 1.0:
        return opacity_logits.clone()
    return (torch.log(torch.as_tensor(factor, dtype=opacity_logits.dtype, device=opacity_logits.device))
            - F.softplus(-opacity_logits) - torch.log1p(-factor * torch.sigmoid(opacity_logits)))


class OpacityDecay(TrainPart):
    """:func:`opacity_decay` of the Gaussians' opacities after every Adam step past ``start``
    (the run's densification start, as the release), in place and without a host read."""

    name = "opacity_decay"

    def __init__(self, factor: float, start: int, iterations: int) -> None:
        if not 0.0 < factor <= 1.0:
            raise ValueError(f"opacity decay factor must be in (0, 1], got {factor}")
        self.factor, self.start, self.iterations = float(factor), int(start), int(iterations)

    def after_step(self, iteration: int, params: dict[str, Tensor]) -> None:
        """``params["opacity"]`` [N] (logits) <- :func:`opacity_decay` from ``start`` + 1 on."""
        if iteration > self.start:
            with torch.no_grad():
                params["opacity"].copy_(opacity_decay(params["opacity"], self.factor))

    def summary(self) -> dict[str, Any]:
        """The factor and the iterations it acted on (every one after ``start``)."""
        return {"opacity_decay": {"factor": self.factor, "from_iteration": self.start + 1,
                                  "iterations": max(0, self.iterations - self.start)}}
