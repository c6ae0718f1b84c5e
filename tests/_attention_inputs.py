"""Inputs and error measure shared by the attention fast-path tests."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def qkv(B: int, H: int, N: int, D: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Three float64 [B, H, N, D] tensors like VGGT's qk-normed heads: unit-variance rows
    scaled by 1.5, so the softmax is peaked."""
    g = torch.Generator().manual_seed(seed)
    return tuple(F.layer_norm(torch.randn(B, H, N, D, generator=g, dtype=torch.float64), (D,)) * 1.5
                 for _ in range(3))


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """Relative L2 error ||a - b|| / ||b|| in float64."""
    return float((a.double() - b.double()).norm() / b.double().norm())
