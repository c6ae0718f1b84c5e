"""Our weight-compatible VGGT implementation (inference only, no track head)."""

from vggt_init.model.config import (
    HEAD_NAMES,
    AggregatorConfig,
    CameraHeadConfig,
    DinoConfig,
    DPTHeadConfig,
    VGGTConfig,
)
from vggt_init.model.vggt import TRACK_HEAD_PREFIX, VGGT

__all__ = [
    "HEAD_NAMES",
    "AggregatorConfig",
    "CameraHeadConfig",
    "DinoConfig",
    "DPTHeadConfig",
    "VGGTConfig",
    "VGGT",
    "TRACK_HEAD_PREFIX",
]
