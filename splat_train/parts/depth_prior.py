"""The depth prior: the initialiser's own depth, weighted by its confidence, as a training loss.

The Bridge writes ``depth_prior.npz`` beside the seed (docs/contracts.md, "Bridge output"):
depth samples of each training camera, in the seed's normalised frame, each with a weight in
[0, 1] (the initialiser's confidence through Eq. 2's min-max ratio for VGGT and the oracle;
1 for the observed points of a COLMAP / posed model). During training the rendered expected
depth (``rasterize(...)["depth"]``, differentiable in every backend) is read at the samples'
pixels and compared with :func:`pearson_depth_loss`, which is invariant to the scale and
shift of either depth: a prior whose scale or offset differs from the model's still shapes
the geometry. The weight ramps in (:func:`depth_weight_at`). :class:`DepthPriorLoss` is the
training part (:mod:`splat_train.parts.base`) that adds the term to the trainer's loss.

This is where the initialiser's confidence keeps acting after iteration 0: a confident sample
pulls the rendered depth more than an unsure one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from camio.depth_prior import read_depth_prior
from splat_train.losses import CUDA_GRAPHS, graphed_checked
from splat_train.parts.base import TrainPart

__all__ = ["DepthPrior", "DepthPriorLoss", "ViewSamples", "load_depth_prior", "pearson_depth_loss",
           "depth_weight_at"]

log = logging.getLogger(__name__)


def depth_weight_at(iteration: int, iterations: int, weight: float, ramp_fraction: float) -> float:
    """The depth loss weight at 1-based ``iteration``: 0 -> ``weight`` linearly over the first
    ``ramp_fraction`` of the run, then constant (``weight`` from the start when the fraction is 0)."""
    if weight <= 0.0:
        return 0.0
    ramp = ramp_fraction * iterations
    return float(weight) if ramp <= 0 else float(weight) * min(1.0, iteration / ramp)


def pearson_depth_loss(rendered: Tensor, prior: Tensor, weight: Tensor) -> Tensor:
    """1 - the weighted Pearson correlation of rendered and prior depth (scale- and shift-invariant).

        r = cov_w(d, p) / sqrt(var_w(d) var_w(p)),   loss = 1 - r

    with weighted means over the samples (weights normalised to sum 1).

    Args:
        rendered: [M] rendered depth at the samples (differentiable).
        prior: [M] prior depth at the same samples.
        weight: [M] non-negative sample weights (the confidence).

    Returns:
        [] loss in [0, 2]: 0 when the depths are affinely related with a positive slope.
        Finite, with a finite gradient, on degenerate input: fewer than 2 samples, zero total
        weight, or a (weighted) constant rendered or prior depth (variance product below
        1e-12 of the product of the mean squares) give loss 1 and a zero gradient. No host
        synchronisation (safe to call every iteration on a GPU).
    """
    if rendered.numel() < 2:
        return rendered.sum() * 0.0 + 1.0
    w = weight.clamp_min(0)
    wsum = w.sum()
    wn = w / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    a = rendered - (wn * rendered).sum()
    b = prior - (wn * prior).sum()
    cov = (wn * a * b).sum()
    var = (wn * a * a).sum() * (wn * b * b).sum()
    scale = (wn * rendered * rendered).sum().detach() * (wn * prior * prior).sum()
    ok = (var > 1e-12 * scale) & (var > 0) & (wsum > 0)
    denom = torch.sqrt(torch.where(ok, var, torch.ones_like(var)))
    return 1.0 - torch.where(ok, cov / denom, torch.zeros_like(cov))


@dataclass
class ViewSamples:
    """One training view's prior at the training resolution: ``index`` [M] int64 flat pixel
    index (row * W + col), ``z`` [M] and ``weight`` [M] float32, on the training device."""

    index: Tensor
    z: Tensor
    weight: Tensor

    def loss(self, depth: Tensor) -> Tensor:
        """:func:`pearson_depth_loss` of the rendered ``depth`` [H, W] at these samples."""
        return pearson_depth_loss(depth.reshape(-1).index_select(0, self.index), self.z, self.weight)


@dataclass
class DepthPrior:
    """The prior of each training view (by image name), ready for the loss."""

    path: Path
    views: dict[str, ViewSamples]

    @property
    def num_samples(self) -> int:
        return sum(int(v.index.numel()) for v in self.views.values())


def load_depth_prior(path: str | Path, sizes: dict[str, tuple[int, int]], device: torch.device | str = "cpu",
                     use_confidence: bool = True, min_samples: int = 2) -> DepthPrior:
    """Read ``depth_prior.npz`` (:mod:`camio.depth_prior`) for the training views.

    Args:
        path: the file (docs/contracts.md, "Bridge output").
        sizes: image name -> (width, height) of each training view as trained (after any
            downsampling); a sample at pixel (x, y) of the prior's image size (W0, H0) lands on
            the training pixel (floor(x W / W0), floor(y H / H0)).
        device: where the samples live.
        use_confidence: weight the samples by the file's ``weight`` (the initialiser's
            confidence); False weighs every usable sample 1 (the ablation of the confidence).
        min_samples: a view with fewer usable samples (finite, positive depth and weight,
            inside the image) gets no depth term (a training run passes its config's
            ``depth_min_samples``; 2, the fewest a correlation is defined on, by default).

    Returns:
        :class:`DepthPrior` with the views of ``sizes`` that have samples.

    Raises:
        ValueError: the file is not a depth prior of the contract.
    """
    prior = read_depth_prior(path)
    xy, z, w = prior.xy.astype(np.float64), prior.z.astype(np.float64), prior.weight.astype(np.float64)
    views: dict[str, ViewSamples] = {}
    for k, name in enumerate(prior.image_names):
        if name not in sizes:
            continue
        W, H = sizes[name]
        W0, H0 = (int(v) for v in prior.image_sizes[k])
        rows = prior.view == k
        px = np.floor(xy[rows, 0] * (W / W0)).astype(np.int64)
        py = np.floor(xy[rows, 1] * (H / H0)).astype(np.int64)
        zk, wk = z[rows], w[rows]
        ok = (px >= 0) & (px < W) & (py >= 0) & (py < H) & np.isfinite(zk) & (zk > 0) & np.isfinite(wk) & (wk > 0)
        if int(ok.sum()) < min_samples:
            log.info("depth prior: %s has %d usable samples (< %d): no depth term for it", name, int(ok.sum()),
                     min_samples)
            continue
        views[name] = ViewSamples(
            index=torch.as_tensor(py[ok] * W + px[ok], device=device),
            z=torch.as_tensor(zk[ok], dtype=torch.float32, device=device),
            weight=torch.as_tensor(wk[ok] if use_confidence else np.ones(int(ok.sum())), dtype=torch.float32,
                                   device=device))
    return DepthPrior(Path(path), views)


class DepthPriorLoss(TrainPart):
    """The depth prior as a training part: adds ``depth_weight_at(it) x`` the Pearson loss of
    the rendered depth at the view's samples (no term for a view without samples).

    Args:
        prior: the loaded prior (:func:`load_depth_prior`).
        view_names: image name of each training view, in the trainer's order.
        weight, ramp_fraction, iterations: as :func:`depth_weight_at`.
        graphs: None follows :data:`splat_train.losses.CUDA_GRAPHS`; only a prior on a CUDA
            device is ever graphed.
    """

    name = "depth_prior"
    needs_depth = True

    def __init__(self, prior: DepthPrior, view_names: list[str], weight: float, ramp_fraction: float,
                 iterations: int, graphs: bool | None = None) -> None:
        self.prior, self.view_names = prior, list(view_names)
        self.weight, self.ramp_fraction, self.iterations = float(weight), float(ramp_fraction), int(iterations)
        cuda = any(v.z.is_cuda for v in prior.views.values())
        self.use_graphs = (CUDA_GRAPHS if graphs is None else bool(graphs)) and cuda
        self._graphed: dict[str, object] = {}  # view name -> graphed ViewSamples.loss (None: op by op)

    def loss(self, iteration: int, view: int, render: dict[str, Tensor], params: dict[str, Tensor]) -> Tensor | None:
        """``w(it) x`` :meth:`ViewSamples.loss` of ``render["depth"]`` [H, W] (camera z), or None.

        On a CUDA device the view's term runs as one CUDA graph (its forward and its backward
        each one replay instead of ~25 and ~50 kernel launches: host time that a small model's
        step is made of), built and checked against the op-by-op term at the view's first call
        (:func:`splat_train.losses.graphed_checked`); op by op where that fails."""
        name = self.view_names[view]
        samples = self.prior.views.get(name)
        w = depth_weight_at(iteration, self.iterations, self.weight, self.ramp_fraction)
        if samples is None or w <= 0:
            return None
        depth = render["depth"]
        if not (self.use_graphs and depth.requires_grad):
            return w * samples.loss(depth)
        if name not in self._graphed:
            self._graphed[name] = graphed_checked(samples.loss, (torch.rand_like(depth).requires_grad_(True),),
                                                  (depth,), f"depth prior term of {name}")
            if self._graphed[name] is not None:
                log.info("depth prior term of %s: one CUDA graph", name)
        fn = self._graphed[name]
        return w * (fn(depth) if fn is not None else samples.loss(depth))

    def summary(self) -> dict:
        """``depth_prior``: the file, its usable samples and the views that have them."""
        return {"depth_prior": {"path": str(self.prior.path), "samples": self.prior.num_samples,
                                "views": sorted(self.prior.views)}}
