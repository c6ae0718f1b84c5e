"""A part of the training loop: one regulariser or extra optimisation, with the state it owns.

The trainer (:class:`splat_train.training.trainer.Trainer`) runs the Gaussians' own loop (view, render,
photometric loss, backward, Adam, densification strategy) and, at fixed points of every
iteration, the hooks of its config's parts (each made by its config,
:mod:`splat_train.parts.configs`; :func:`splat_train.parts.recipe_parts`), in the list's order. A part overrides only the hooks it needs; the defaults do nothing. As gsplat's
densification strategies (``gsplat.strategy.Strategy``: settings in the object, hooks before
and after the backward pass) and kornia's training callbacks, the loop calls the part; a part
never calls the loop.

One iteration ``it`` (1-based) of training view ``view`` (index into the training views):

1. :meth:`TrainPart.camera`: the camera the view is rendered with (pose refinement);
2. :meth:`TrainPart.opacity_fn`: a map of the [N] opacities before the rasterizer (Gaussian
   dropout); training renders only, never a scored or exported one;
3. :meth:`TrainPart.loss`: a term added to the photometric loss (depth prior, the opacity and
   scale regularisers), in the parts' order;
4. backward, the Gaussians' Adam step;
5. :meth:`TrainPart.after_step`: the part's own optimiser step (pose corrections), or a change
   of the Gaussians in place (opacity decay);

and, outside the iteration, :meth:`TrainPart.state_dict` / :meth:`TrainPart.load_state_dict`
(the checkpoint, so that a resumed run continues bit for bit) and :meth:`TrainPart.summary`
(keys of ``train.json``); :attr:`TrainPart.moves_cameras` / :attr:`TrainPart.moves_intrinsics`
say whether the part's cameras replace the given ones in the final evaluation and in
``cameras_refined/``. Randomness comes from the trainer's generator, passed to the part
when it is made: its state is in every checkpoint.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol

from torch import Tensor

__all__ = ["TrainPart", "OpacityFn", "ViewRenderer"]

# [N] opacities in [0, 1] -> [N] opacities (differentiable)
OpacityFn = Callable[[Tensor], Tensor]


class ViewRenderer(Protocol):
    """What a part that renders a view of its own (binocular consistency) may ask of the trainer."""

    def view_camera(self, view: int) -> tuple[Tensor, Tensor]:
        """([4, 4] cam_from_world, [3, 3] K) that training view ``view`` is rendered with now."""

    def render_rgb(self, cam_from_world: Tensor, K: Tensor, width: int, height: int) -> Tensor:
        """[H, W, 3] differentiable render of the current model into a camera, at the current
        iteration's SH degree and background, without the opacity map of :meth:`TrainPart.opacity_fn`."""


class TrainPart:
    """Base of the training parts; every hook defaults to "nothing to do".

    Attributes:
        name: the part's key in the checkpoint's ``parts`` and in the trainer's log line.
        needs_depth: whether the part's loss reads the render's depth.
        moves_cameras: whether :meth:`camera` changes the training poses (pose refinement):
            the trainer then scores the training views with the part's cameras at the end and
            writes them to ``cameras_refined/``.
        moves_intrinsics: whether :meth:`camera` also changes K (focal refinement): the
            written cameras then take the part's K.
    """

    name: str = "part"
    #: whether :meth:`loss` reads the render's ``depth``: when no part does, the training
    #: render skips the depth outputs (gsplat renders colour only)
    needs_depth: bool = False
    moves_cameras: bool = False
    moves_intrinsics: bool = False

    def camera(self, iteration: int, view: int, cam_from_world: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """The camera training view ``view`` is rendered with at ``iteration``.

        Args:
            iteration: 1-based iteration (the current one; after training, the last one).
            view: index of the training view.
            cam_from_world: [4, 4] world -> OpenCV camera (x right, y down, z forward).
            K: [3, 3] intrinsics in pixels of the training image (COLMAP convention).

        Returns:
            (cam_from_world [4, 4], K [3, 3]), the given ones by default.
        """
        return cam_from_world, K

    def opacity_fn(self, iteration: int) -> OpacityFn | None:
        """The map applied to the [N] opacities (after the sigmoid) of this iteration's training
        render, or None (the default) to leave them as they are."""
        return None

    def loss(self, iteration: int, view: int, render: dict[str, Tensor], params: dict[str, Tensor]) -> Tensor | None:
        """A term added to this iteration's loss, or None (the default) for none.

        Args:
            iteration: 1-based iteration.
            view: index of the training view rendered.
            render: the :func:`splat_train.rasterize` dict of the render (``rgb`` [H, W, 3],
                ``depth`` [H, W] camera z, ...).
            params: the trainable Gaussians (:mod:`splat_train.gaussians`: world frame, log
                scales, logit opacities).

        Returns:
            [] differentiable scalar (weight included), or None.
        """
        return None

    def after_step(self, iteration: int, params: dict[str, Tensor]) -> None:
        """Called after the Gaussians' Adam step of ``iteration`` (their gradients cleared);
        ``params``: the trainable Gaussians, which the part may change in place (opacity decay)."""

    def state_dict(self) -> dict[str, Any] | None:
        """Plain tensors and dicts to checkpoint (``torch.load(weights_only=True)``), or None
        (the default) when the part holds no state across iterations."""
        return None

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned (tensors already on the training device)."""

    def summary(self) -> dict[str, Any]:
        """Entries of ``train.json`` that describe this part after training (default: none)."""
        return {}
