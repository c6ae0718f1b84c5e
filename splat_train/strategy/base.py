"""How the model grows: the :class:`Strategy` interface the trainer calls.

A strategy (as gsplat's ``gsplat.strategy.Strategy``) holds its settings and is called by the
trainer at fixed points of every iteration: :meth:`Strategy.update_state` after the backward
pass (the view-space gradient statistics), :meth:`Strategy.step` after the Adam step (grow,
prune, relocate). Two strategies: ``densify``, 3DGS's clone / split / prune and opacity reset
(:class:`splat_train.strategy.densify.DensifyStrategy`), and ``mcmc``, relocation of dead Gaussians and
growth to a cap (:class:`splat_train.strategy.mcmc.MCMCStrategy`); each is made by its config
(:mod:`splat_train.strategy.configs`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

if TYPE_CHECKING:
    import torch

__all__ = ["Strategy"]

class Strategy:
    """Base of the growth strategies; the trainer calls only these methods.

    Attributes:
        name: the strategy's key (``train.json`` ``strategy``).
    """

    name: ClassVar[str] = "strategy"

    def init_state(self, n: int, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """The running state of a model of ``n`` Gaussians (checkpointed as ``strategy_state``)."""
        raise NotImplementedError

    def wants_stats(self, iteration: int) -> bool:
        """Whether 1-based ``iteration``'s render statistics are read (else the render skips them)."""
        return False

    def update_state(self, state: dict[str, torch.Tensor], means2d_grad: torch.Tensor, radii: torch.Tensor,
                     visible: torch.Tensor, width: int, height: int, iteration: int) -> None:
        """Accumulate one view's statistics: ``means2d_grad`` [N, 2] d loss / d means2d in
        pixels, ``radii`` [N] screen radius in pixels, ``visible`` [N] bool."""

    def step(self, params: dict[str, torch.Tensor], optimizer: torch.optim.Optimizer,
             state: dict[str, torch.Tensor], iteration: int, extent: float,
             generator: torch.Generator | None = None) -> dict[str, int]:
        """Grow / prune / relocate after the Adam step of 1-based ``iteration``; counts of what ran."""
        raise NotImplementedError

    def totals(self, state: dict[str, torch.Tensor]) -> dict[str, int]:
        """Running totals for ``train.json`` ``strategy_totals`` (default: none)."""
        return {}
