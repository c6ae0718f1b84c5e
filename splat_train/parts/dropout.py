"""Gaussian dropout (DropGaussian, CVPR 2025): a training-only regulariser for sparse views.

At each training iteration every Gaussian's opacity is zeroed with probability p and the
survivors' opacity is divided by 1 - p, so that the expected opacity of each Gaussian is
unchanged; p ramps linearly from 0 to the final rate over the run, or over its first part
(:func:`dropout_rate_at`).
The renders that are scored, exported or shown (held-out evaluation, ``render``) never drop
anything: only the training render of :meth:`splat_train.training.trainer.Trainer.step` goes through
:class:`GaussianDropout`, the training part (:mod:`splat_train.parts.base`) that applies
:func:`gaussian_dropout`. Working on the opacities before the rasterizer, it renders the same
through every backend. One difference follows from gsplat's semantics: gsplat culls a Gaussian
of opacity below 1/255 in its projection, so a dropped Gaussian is not counted as seen in that
step's densification statistics there, while the CPU backends count it, as 3DGS's rasterizer
(under DropGaussian's release) does (``splat_train.render._gsplat_backend``; emulated on the CPU it
moves the trained model by -0.04 ± 0.15 dB over 15 seeds, docs/results.md).
"""

from __future__ import annotations

import torch
from torch import Tensor

from splat_train.rng import uniform
from splat_train.parts.base import OpacityFn, TrainPart

__all__ = ["dropout_rate_at", "gaussian_dropout", "GaussianDropout"]


def dropout_rate_at(iteration: int, iterations: int, final_rate: float, ramp_fraction: float = 1.0) -> float:
    """DropGaussian's rate at 1-based ``iteration`` of ``iterations``: final_rate x it / (ramp_fraction x
    iterations), at most final_rate. ``ramp_fraction`` 1 is DropGaussian's ramp over the whole run,
    0 the final rate from the first iteration."""
    if final_rate <= 0.0:
        return 0.0
    ramp = ramp_fraction * float(iterations)
    return float(final_rate) * (1.0 if ramp <= 0.0 else min(1.0, iteration / ramp))


def gaussian_dropout(opacities: Tensor, rate: float, generator: torch.Generator | None = None) -> Tensor:
    """Drop each Gaussian with probability ``rate``, compensating the survivors.

    Args:
        opacities: [N] opacities in [0, 1] (after the sigmoid), any device; differentiable.
        rate: drop probability p in [0, 1).
        generator: CPU generator of the draw (the trainer's, so that a resumed run draws the
            same masks); the [N] uniform draw is :func:`splat_train.rng.uniform` (on the CPU
            from ``generator`` itself, on a GPU from a device generator it seeds: no sync).

    Returns:
        [N] opacities * keep / (1 - p), keep ~ Bernoulli(1 - p); ``opacities`` itself when
        p == 0. E[result] = opacities; the compensated value may exceed 1 (the rasterizer
        clamps each pixel's alpha at 0.99, as 3DGS and DropGaussian do).
    """
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"dropout rate must be in [0, 1), got {rate}")
    if rate == 0.0:
        return opacities
    if generator is None:
        generator = torch.default_generator
    u = uniform(opacities.shape[0], generator, opacities.device)
    keep = (u >= rate).to(opacities.dtype)
    return opacities * (keep / (1.0 - rate))


class GaussianDropout(TrainPart):
    """Gaussian dropout as a training part: each training render's opacities go through
    :func:`gaussian_dropout` at the rate :func:`dropout_rate_at` gives for the iteration.

    Args:
        final_rate: the rate reached at the end of the ramp (> 0).
        iterations: the run's length.
        generator: the trainer's CPU generator (checkpointed by the trainer).
        ramp_fraction: the fraction of the run over which the rate ramps up from 0 (1: all of it).
    """

    name = "dropout"

    def __init__(self, final_rate: float, iterations: int, generator: torch.Generator,
                 ramp_fraction: float = 1.0) -> None:
        self.final_rate, self.iterations, self.generator = float(final_rate), int(iterations), generator
        self.ramp_fraction = float(ramp_fraction)

    def opacity_fn(self, iteration: int) -> OpacityFn | None:
        """[N] opacities -> :func:`gaussian_dropout` at this iteration's rate (None at rate 0);
        each call of the map draws one mask from the generator."""
        rate = dropout_rate_at(iteration, self.iterations, self.final_rate, self.ramp_fraction)
        if rate <= 0:
            return None
        return lambda opacities: gaussian_dropout(opacities, rate, self.generator)
