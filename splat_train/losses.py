"""Photometric losses and metrics: L1, SSIM (exactly as 3DGS computes it), PSNR.

Image layouts accepted by every function here:

* ``[B, 3, H, W]`` (channels first, batched), or
* ``[H, W, 3]`` (one channel-last image, the layout of :mod:`camio` and of the rasterizer).

Values are expected in [0, 1]; SSIM's constants C1 = (0.01)^2, C2 = (0.03)^2 assume that range.
"""

from __future__ import annotations

import logging
import math
import os

import torch

from imgmetrics.ssim import gaussian_window, gaussian_window_1d, ssim_map
from splat_train.render.cpu import ssim as cpu_ssim

__all__ = ["ssim", "ssim_map", "l1_loss", "psnr", "photometric_loss", "photometric_terms", "TrainingLoss",
           "gaussian_regularisers", "gaussian_window", "gaussian_window_1d", "graphed_checked", "CUDA_GRAPHS"]

log = logging.getLogger(__name__)

#: Whether the training losses run as CUDA graphs on CUDA devices (:class:`TrainingLoss`, the
#: depth prior's term; environment ``SPLAT_TRAIN_CUDA_GRAPHS=0`` switches them off: the same
#: losses, launched op by op).
CUDA_GRAPHS = os.environ.get("SPLAT_TRAIN_CUDA_GRAPHS", "1") != "0"


def _to_bchw(img: torch.Tensor, name: str) -> torch.Tensor:
    if img.dim() == 4:
        return img
    if img.dim() == 3 and img.shape[-1] == 3:
        return img.permute(2, 0, 1).unsqueeze(0)
    raise ValueError(f"{name} must be [B, C, H, W] or [H, W, 3], got shape {tuple(img.shape)}")


def ssim(
    img1: torch.Tensor,
    img2: torch.Tensor,
    window_size: int = 11,
    sigma: float = 1.5,
    reduction: str = "mean",
) -> torch.Tensor:
    """Structural similarity exactly as the 3DGS training code computes it.

    Local statistics use an ``window_size`` x ``window_size`` Gaussian window (sigma 1.5),
    applied per channel by ``conv2d`` with zero padding ``window_size // 2`` (so the map has
    the image size and border windows see zeros outside the image), C1 = 0.01^2, C2 = 0.03^2:

        ssim_map = ((2 mu1 mu2 + C1)(2 sigma12 + C2)) / ((mu1^2 + mu2^2 + C1)(sigma1^2 + sigma2^2 + C2))

    with sigma1^2 = E[x^2] - mu1^2 etc. The result is the mean of the map over channels and
    pixels (and images). Differentiable; any float dtype.

    Args:
        img1, img2: [B, C, H, W] or [H, W, 3], same shape, values in [0, 1].
        window_size, sigma: the Gaussian window (3DGS: 11 and 1.5).
        reduction: "mean" -> scalar; "none" -> [B] per-image means.

    Returns:
        Scalar (or [B]) tensor; 1 for identical images.
    """
    if img1.shape != img2.shape:
        raise ValueError(f"ssim: shapes differ: {tuple(img1.shape)} vs {tuple(img2.shape)}")
    m = ssim_map(_to_bchw(img1, "img1"), _to_bchw(img2, "img2"), window_size, sigma)
    if reduction == "mean":
        return m.mean()
    if reduction == "none":
        return m.flatten(1).mean(1)
    raise ValueError(f"ssim: reduction must be 'mean' or 'none', got {reduction!r}")


def l1_loss(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference (any equal shapes) -> scalar."""
    if img1.shape != img2.shape:
        raise ValueError(f"l1_loss: shapes differ: {tuple(img1.shape)} vs {tuple(img2.shape)}")
    return (img1 - img2).abs().mean()


def psnr(img1: torch.Tensor, img2: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (any equal shapes): -10 log10(MSE); inf when equal."""
    mse = float(((img1.double() - img2.double()) ** 2).mean())
    return float("inf") if mse == 0.0 else -10.0 * math.log10(mse)


def _cpu_kernel_for(render: torch.Tensor, target: torch.Tensor):
    """:mod:`splat_train.render.cpu.ssim` when it applies to these images (CPU float32/float64, one
    shape, a target that needs no gradient, the kernel built), else None."""
    if (render.device.type == "cpu" and target.device.type == "cpu" and not target.requires_grad
            and render.dtype in (torch.float32, torch.float64) and render.shape == target.shape):
        if cpu_ssim.available():
            return cpu_ssim
    return None


def _training_ssim(render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """:func:`ssim` (mean), through the C++ kernel (:mod:`splat_train.render.cpu.ssim`) for CPU
    float32/float64 images with a target that needs no gradient; the reference otherwise."""
    kernel = _cpu_kernel_for(render, target)
    if kernel is not None:
        return kernel.ssim_cpu(_to_bchw(render, "render"), _to_bchw(target, "target").to(render.dtype))
    return ssim(render, target)


def photometric_loss(
    render: torch.Tensor, target: torch.Tensor, lambda_dssim: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 3DGS loss (1 - lambda) L1 + lambda (1 - SSIM).

    Args:
        render, target: [H, W, 3] (or [B, 3, H, W]) images in [0, 1].
        lambda_dssim: weight of the SSIM term (0.2).

    Returns:
        (loss, l1, ssim) scalars; loss carries the gradient.
    """
    kernel = _cpu_kernel_for(render, target) if render.dim() == 3 else None
    if kernel is not None:
        # both terms in one C++ pass on the [H, W, 3] images (no transposed copies, no
        # per-term torch ops): the same values as the two calls below
        l1, s = kernel.l1_ssim_cpu(render, target.to(render.dtype))
        return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1, s
    l1 = l1_loss(render, target)
    s = _training_ssim(render, target)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s), l1, s


def photometric_terms(render: torch.Tensor, target: torch.Tensor,
                      lambda_dssim: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The training step's loss and what its log records, from one render.

    Args:
        render: [H, W, 3] training render in [0, 1] (carries the gradient).
        target: [H, W, 3] the view's image.
        lambda_dssim: weight of the SSIM term.

    Returns:
        (loss [] of :func:`photometric_loss`, differentiable; stats [3] = (L1, SSIM, MSE of the
        render), detached).
    """
    loss, l1, s = photometric_loss(render, target, lambda_dssim)
    with torch.no_grad():
        mse = ((render.detach() - target) ** 2).mean()
    return loss, torch.stack([l1.detach(), s.detach(), mse])


class TrainingLoss:
    """:func:`photometric_terms` for every training view; on a CUDA device, one CUDA graph per
    image shape (``torch.cuda.make_graphed_callables``: the forward and the backward pass each
    one replay instead of ~40 and ~60 kernel launches, each launch a few microseconds of host
    time that a step of a small model is made of). The render and target are copied into the
    graph's own input buffers at each call, so each view may pass its own tensors.

    The first call at a shape checks the graph against the op-by-op loss on the same inputs
    (value and gradient, relative 1e-5 and 1e-4); on a mismatch or any error while building,
    it logs a warning and stays op by op for the rest of the run. ``CUDA_GRAPHS`` (or
    ``graphs=False``) switches graphs off; other devices never use them.

    Args:
        lambda_dssim: weight of the SSIM term.
        device: the training device.
        graphs: None follows :data:`CUDA_GRAPHS`.
    """

    def __init__(self, lambda_dssim: float, device: torch.device, graphs: bool | None = None) -> None:
        self.lambda_dssim = float(lambda_dssim)
        self.use_graphs = (CUDA_GRAPHS if graphs is None else bool(graphs)) and torch.device(device).type == "cuda"
        self._graphed: dict[tuple, object] = {}

    def eager(self, render: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return photometric_terms(render, target, self.lambda_dssim)

    def __call__(self, render: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss [], stats [3] (L1, SSIM, MSE)) as :func:`photometric_terms`; render, target [H, W, 3]."""
        if not self.use_graphs or not render.requires_grad:
            return self.eager(render, target)
        key = (tuple(render.shape), render.dtype, target.dtype, render.device)
        fn = self._graphed.get(key)
        if fn is None:
            fn = self._build(render, target)
            if fn is None:
                return self.eager(render, target)
            self._graphed[key] = fn
        return fn(render, target)

    def _build(self, render: torch.Tensor, target: torch.Tensor):
        """The graphed loss for this shape, checked against :meth:`eager`; None on failure (graphs
        are then off for the run)."""
        fn = graphed_checked(self.eager, (torch.rand_like(render).requires_grad_(True), torch.rand_like(target)),
                             (render, target), "training loss")
        if fn is None:
            self.use_graphs = False
            return None
        log.info("training loss: one CUDA graph for %s images", "x".join(map(str, render.shape)))
        return fn


def graphed_checked(fn, sample: tuple[torch.Tensor, ...], probe: tuple[torch.Tensor, ...], what: str):
    """``fn`` as a CUDA graph (``torch.cuda.make_graphed_callables`` on ``sample``: the forward
    and the backward pass each one replay), checked against ``fn`` op by op on ``probe``: every
    output (relative 1e-5) and the gradient of the first argument (relative 1e-4).

    Args:
        fn: a function of tensors of fixed shapes (its first argument differentiable) returning
            a tensor or a tuple of tensors, the first one differentiable.
        sample: arguments of the shapes, dtypes and devices it will be called with (the first
            requires grad), used to capture it.
        probe: real arguments to compare on (detached copies are used).
        what: its name in the warning.

    Returns:
        The graphed callable, or None on a mismatch or any error while building (a warning says
        which; the caller stays op by op).
    """
    try:
        graphed = torch.cuda.make_graphed_callables(fn, sample)
        first = probe[0].detach().clone().requires_grad_(True)
        ref = probe[0].detach().clone().requires_grad_(True)
        out_g, out_e = graphed(first, *probe[1:]), fn(ref, *probe[1:])
        out_g, out_e = (out_g, out_e) if isinstance(out_g, tuple) else ((out_g,), (out_e,))
        out_g[0].backward()
        out_e[0].backward()
        same = (all(torch.allclose(g, e, rtol=1e-5, atol=1e-7) for g, e in zip(out_g, out_e))
                and torch.allclose(first.grad, ref.grad, rtol=1e-4, atol=1e-9))
        if not same:
            raise RuntimeError(f"graphed result differs from the op-by-op one (first output {float(out_g[0])} vs "
                               f"{float(out_e[0])}, max gradient difference "
                               f"{float((first.grad - ref.grad).abs().max()):.3g})")
    except Exception as exc:  # noqa: BLE001  (any failure: the op-by-op function is always right)
        log.warning("%s as a CUDA graph unavailable (%s); running it op by op", what, exc)
        return None
    return graphed


def gaussian_regularisers(opacity_logits: torch.Tensor, log_scales: torch.Tensor, opacity_reg: float,
                          scale_reg: float) -> torch.Tensor | None:
    """The MCMC recipe's regularisers (gsplat ``opacity_reg_loss``, ``scale_reg_loss``):
    ``opacity_reg`` mean(sigmoid(opacity_logits)) + ``scale_reg`` mean(exp(log_scales)).

    Args:
        opacity_logits: [N] logit opacities; log_scales: [N, 3] log scales.
        opacity_reg, scale_reg: weights (0: that term off).

    Returns:
        The scalar term (carries the gradient), or None when both weights are 0.
    """
    terms = []
    if opacity_reg > 0:
        terms.append(opacity_reg * torch.sigmoid(opacity_logits).mean())
    if scale_reg > 0:
        terms.append(scale_reg * torch.exp(log_scales).mean())
    return sum(terms[1:], terms[0]) if terms else None
