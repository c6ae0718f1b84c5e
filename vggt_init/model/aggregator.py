"""The aggregator: DINOv2 patch embedding, then alternating frame / global attention.

Token layout per frame: [camera (1), registers (R), patches (P)], patch_start_idx = 1 + R.
Only the aggregator outputs that the heads read are kept (``keep`` argument).
"""

from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from vggt_init.model.config import AggregatorConfig, DinoConfig, VGGTConfig
from vggt_init.model.layers import Block, RoPE2D

__all__ = ["DinoViT", "Aggregator", "LayerTokens"]

LayerTokens = torch.Tensor | tuple[torch.Tensor, torch.Tensor]  # [B,S,N,2C], or its two [B,S,N,C] halves


class PatchEmbed(nn.Module):
    """Conv patchifier. [N,3,H,W] -> [N, h*w, C] (row-major patches)."""

    def __init__(self, patch_size: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoViT(nn.Module):
    """DINOv2 ViT with registers; returns the final-norm patch tokens only."""

    def __init__(self, cfg: DinoConfig) -> None:
        super().__init__()
        self.cfg = cfg
        C = cfg.embed_dim
        self.patch_embed = PatchEmbed(cfg.patch_size, C)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, C))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.pos_embed_grid ** 2, C))
        self.register_tokens = (nn.Parameter(torch.zeros(1, cfg.num_register_tokens, C))
                                if cfg.num_register_tokens else None)
        self.mask_token = nn.Parameter(torch.zeros(1, C))  # in the checkpoint, unused at inference
        self.blocks = nn.ModuleList(
            Block(C, cfg.num_heads, cfg.mlp_ratio, cfg.qkv_bias, cfg.proj_bias, cfg.ffn_bias,
                  eps=cfg.layernorm_eps)
            for _ in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(C, eps=cfg.layernorm_eps)

    def position_embedding(self, h: int, w: int, dtype: torch.dtype) -> torch.Tensor:
        """[1, 1 + h*w, C]: CLS row then the patch grid resized to (h, w).

        The resize is bicubic with antialias to an explicit size, computed in float32 and
        cast back (as the reference); skipped when the grid already is h x w (square).
        """
        n_stored = self.pos_embed.shape[1] - 1
        M = int(math.sqrt(n_stored))
        if h == w == M and M * M == n_stored:
            return self.pos_embed.to(dtype)
        pe = self.pos_embed.float()
        cls_pe, patch_pe = pe[:, :1], pe[:, 1:]
        C = pe.shape[-1]
        grid = patch_pe.reshape(1, M, M, C).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", antialias=self.cfg.interpolate_antialias)
        patch_pe = grid.permute(0, 2, 3, 1).reshape(1, h * w, C)
        return torch.cat((cls_pe, patch_pe), dim=1).to(dtype)

    def forward(self, x: torch.Tensor, debug: dict | None = None) -> torch.Tensor:
        """x [N,3,H,W] normalised images -> patch tokens [N, P, C], P = (H/p)(W/p)."""
        N, _, H, W = x.shape
        p = self.cfg.patch_size
        h, w = H // p, W // p
        t = self.patch_embed(x)
        t = torch.cat((self.cls_token.expand(N, -1, -1), t), dim=1)  # promotes like the reference
        pe = self.position_embedding(h, w, t.dtype)
        if debug is not None:
            debug["dino.pos_embed"] = pe.detach().clone()
        t = t + pe
        if self.register_tokens is not None:
            t = torch.cat((t[:, :1], self.register_tokens.expand(N, -1, -1), t[:, 1:]), dim=1)
        for blk in self.blocks:
            t = blk(t)
        t = self.norm(t)
        out = t[:, 1 + self.cfg.num_register_tokens:]
        if debug is not None:
            debug["dino.patch_tokens"] = out.detach().clone()
        return out


def _special_tokens(token: torch.Tensor, B: int, S: int) -> torch.Tensor:
    """token [1, 2, X, C] -> [B*S, X, C]: slot 0 for frame 0 of each scene, slot 1 for the rest."""
    first = token[:, :1].expand(B, 1, *token.shape[2:])
    rest = token[:, 1:].expand(B, S - 1, *token.shape[2:])
    return torch.cat((first, rest), dim=1).reshape(B * S, *token.shape[2:])


def patch_positions(n: int, h: int, w: int, n_special: int, device: torch.device) -> torch.Tensor:
    """RoPE positions [n, n_special + h*w, 2] (row, col): special tokens (0,0), patch (r+1, c+1)."""
    rows = torch.arange(h, device=device).repeat_interleave(w)
    cols = torch.arange(w, device=device).repeat(h)
    grid = torch.stack((rows, cols), dim=-1) + 1
    pos = torch.cat((torch.zeros(n_special, 2, dtype=grid.dtype, device=device), grid), dim=0)
    return pos[None].expand(n, -1, -1)


class Aggregator(nn.Module):
    """Alternating-attention trunk. Parameter names as in the official checkpoint."""

    def __init__(self, config: VGGTConfig) -> None:
        super().__init__()
        cfg: AggregatorConfig = config.aggregator
        self.cfg = cfg
        self.patch_size = config.patch_size
        C = cfg.embed_dim
        self.patch_embed = DinoViT(config.dino)
        self.rope = RoPE2D(cfg.rope_freq)
        mk = lambda: Block(C, cfg.num_heads, cfg.mlp_ratio, cfg.qkv_bias, cfg.proj_bias,  # noqa: E731
                           cfg.ffn_bias, eps=cfg.layernorm_eps, qk_norm=cfg.qk_norm,
                           qk_norm_eps=cfg.qk_norm_eps, rope=self.rope)
        self.frame_blocks = nn.ModuleList(mk() for _ in range(cfg.depth))
        self.global_blocks = nn.ModuleList(mk() for _ in range(cfg.depth))
        self.camera_token = nn.Parameter(torch.zeros(1, 2, 1, C))
        self.register_token = nn.Parameter(torch.zeros(1, 2, cfg.num_register_tokens, C))

    @property
    def patch_start_idx(self) -> int:
        return self.cfg.patch_start_idx

    def forward(self, images: torch.Tensor, keep: list[int] | None = None,
                debug: dict | None = None, concat: bool = True,
                on_layer: Callable[[int, torch.Tensor, torch.Tensor], None] | None = None) -> dict[int, LayerTokens]:
        """Run the trunk.

        Args:
            images: [B, S, 3, H, W] RGB in [0, 1]; H, W multiples of the patch size.
            keep: aggregator output indices (0-based, non-negative) to return; all if None.
            debug: if a dict, DINO intermediates are stored in it.
            concat: False returns each output as its two halves instead of their concatenation
                (what the model passes to its heads: the concatenation would be a second copy
                of every kept layer for all frames at once; the heads join the halves a frame
                chunk at a time, see :func:`vggt_init.model.heads.take_tokens`).

            on_layer: if given, each kept output is handed to ``on_layer(i, frame, global)``
                (halves [B, S, P + patch_start_idx, C]) as soon as step i is done, and not
                returned: the caller keeps what it needs of it (the model: the heads' inputs).

        Returns:
            {i: [B, S, P + patch_start_idx, 2C]} = concat(frame output, global output) of
            step i, frame part first; with ``concat=False`` {i: (frame output, global output)},
            each [B, S, P + patch_start_idx, C]; empty with ``on_layer``.
        """
        cfg = self.cfg
        B, S, _, H, W = images.shape
        p = self.patch_size
        h, w = H // p, W // p
        # The reference keeps mean/std as float32 buffers: use float32-rounded constants.
        mean = torch.tensor(cfg.normalize_mean, dtype=torch.float32, device=images.device)
        std = torch.tensor(cfg.normalize_std, dtype=torch.float32, device=images.device)
        mean = mean.to(images.dtype).view(1, 1, 3, 1, 1)
        std = std.to(images.dtype).view(1, 1, 3, 1, 1)
        x = ((images - mean) / std).reshape(B * S, 3, H, W)
        patches = self.patch_embed(x, debug)  # [B*S, P, C]
        del x
        dtype = patches.dtype
        tokens = torch.cat((_special_tokens(self.camera_token, B, S).to(dtype),
                            _special_tokens(self.register_token, B, S).to(dtype),
                            patches), dim=1)
        del patches
        N, C = tokens.shape[1], tokens.shape[2]
        pos = patch_positions(B * S, h, w, cfg.patch_start_idx, images.device)
        pos_frame = pos
        pos_global = pos.reshape(B, S * N, 2)

        keep_set = set(range(cfg.depth)) if keep is None else set(keep)
        outputs: dict[int, torch.Tensor] = {}
        frame_i = global_i = out_i = 0
        for _ in range(cfg.depth // cfg.aa_block_size):
            frame_out: list[torch.Tensor] = []
            global_out: list[torch.Tensor] = []
            for kind in cfg.aa_order:
                if kind == "frame":
                    tokens = tokens.reshape(B * S, N, C)
                    for _ in range(cfg.aa_block_size):
                        tokens = self.frame_blocks[frame_i](tokens, pos_frame)
                        frame_i += 1
                        frame_out.append(tokens.reshape(B, S, N, C) if out_i + len(frame_out) in keep_set else None)
                else:
                    tokens = tokens.reshape(B, S * N, C)
                    for _ in range(cfg.aa_block_size):
                        tokens = self.global_blocks[global_i](tokens, pos_global)
                        global_i += 1
                        global_out.append(tokens.reshape(B, S, N, C) if out_i + len(global_out) in keep_set else None)
            for f, g in zip(frame_out, global_out):
                if out_i in keep_set and on_layer is not None:
                    on_layer(out_i, f, g)
                elif out_i in keep_set:
                    outputs[out_i] = torch.cat((f, g), dim=-1) if concat else (f, g)
                out_i += 1
            # drop this step's outputs now: the loop variables would keep a kept pair (2 [B,S,N,C])
            # alive through the next step
            f = g = frame_out = global_out = None
        return outputs
