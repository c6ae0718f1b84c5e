"""splat_train package: 3DGS training from a seed PLY and COLMAP cameras.

The package face hands on :func:`rasterize`, :class:`TrainConfig`, :func:`psnr`, :func:`ssim`,
:func:`train`, :class:`TrainResult` and :class:`NonFiniteLossError`, each imported on first
use, so that reading a light module (``splat_train.recipes``, whose recipe names the workflow's
config check reads) does not import torch.

Rooms, lowest first: :mod:`.render` (the rasterizer, its maths and the C++ kernels; it imports
nothing else of the package), the run's building blocks (:mod:`.config` with :mod:`.tree`,
:mod:`.recipes` and :mod:`.fields`; :mod:`.data`, :mod:`.gaussians`, :mod:`.losses`, :mod:`.rng`;
the growth strategies :mod:`.strategy` and the training parts :mod:`.parts`), the commands that
draw a model (:mod:`.export`, :mod:`.flythrough`, :mod:`.testpose`), one training run
(:mod:`.training`), the browser viewer (:mod:`.view`) and the CLI (:mod:`.__main__`).
"""
from __future__ import annotations

from runtime.stops import early_if_main as _early

_early()  # first: a stop while `python -m` loads the command is one line, exit 128 + the signal

import importlib
import sys

_FACE = {
    "rasterize": "splat_train.render.rasterize",
    "TrainConfig": "splat_train.config",
    "psnr": "splat_train.losses",
    "ssim": "splat_train.losses",
    "NonFiniteLossError": "splat_train.training.trainer",
    "TrainResult": "splat_train.training.trainer",
    "train": "splat_train.training.trainer",
}

__all__ = sorted(_FACE)


def __getattr__(name: str):
    if name in _FACE:
        value = getattr(importlib.import_module(_FACE[name]), name)
        setattr(sys.modules[__name__], name, value)
        return value
    raise AttributeError(f"module 'splat_train' has no attribute {name!r}")

