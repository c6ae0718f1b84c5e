"""Camera head, DPT dense heads and their output activations (chosen by name).

Every head reads the aggregator outputs ``tokens = {layer index: [B, S, N, 2C]}`` with
N = patch_start_idx + P, or each output as its (frame, global) halves [B, S, N, C]
(``Aggregator(..., concat=False)``); the heads join and cast only the slice they read
(:func:`take_tokens`), a frame chunk at a time in the DPT heads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from vggt_init.model.config import CameraHeadConfig, DPTHeadConfig
from vggt_init.model.layers import Block, Linear, Mlp

__all__ = ["ACTIVATIONS", "activation", "CameraHead", "DPTHead", "Projected", "dpt_position_embedding",
           "take_tokens"]


def take_tokens(t: torch.Tensor | tuple[torch.Tensor, torch.Tensor], frames: slice, tokens: slice | int,
                dtype: torch.dtype) -> torch.Tensor:
    """``t[:, frames, tokens]`` of one aggregator output, in ``dtype``.

    Args:
        t: [B, S, N, 2C], or its halves (frame, global) [B, S, N, C] each (joined frame first).
        frames, tokens: index of dims 1 and 2 (an int token index drops dim 2).

    Returns:
        [B, s, n, 2C] (or [B, s, 2C]); a copy only where joining or casting needs one.
    """
    if isinstance(t, tuple):
        out = torch.cat((t[0][:, frames, tokens], t[1][:, frames, tokens]), dim=-1)
    else:
        out = t[:, frames, tokens]
    return out.to(dtype)


def _inv_log(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.expm1(torch.abs(x))


ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "linear": lambda x: x,
    "relu": F.relu,
    "exp": torch.exp,
    "expp1": lambda x: 1 + torch.exp(x),
    "expp0": torch.exp,
    "sigmoid": torch.sigmoid,
    "inv_log": _inv_log,
}


def activation(name: str) -> Callable[[torch.Tensor], torch.Tensor]:
    """The activation called ``name``; ValueError naming the known ones otherwise."""
    try:
        return ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; known: {sorted(ACTIVATIONS)}") from None


# ---------------------------------------------------------------------------- camera head
class CameraHead(nn.Module):
    """Pose encoding from the camera tokens: 4 adaLN-modulated refinement iterations.

    Output encoding per frame (9 numbers): t (3) of cam_from_world, quaternion XYZW (4),
    fov_h, fov_w (radians).
    """

    def __init__(self, cfg: CameraHeadConfig) -> None:
        super().__init__()
        self.cfg = cfg
        D = cfg.dim_in
        self.token_norm = nn.LayerNorm(D, eps=cfg.layernorm_eps)
        self.trunk = nn.Sequential(*[Block(D, cfg.num_heads, cfg.mlp_ratio, eps=cfg.layernorm_eps)
                                     for _ in range(cfg.trunk_depth)])
        self.trunk_norm = nn.LayerNorm(D, eps=cfg.layernorm_eps)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, cfg.target_dim))
        self.embed_pose = Linear(cfg.target_dim, D)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), Linear(D, 3 * D))
        self.adaln_norm = nn.LayerNorm(D, elementwise_affine=False, eps=cfg.adaln_eps)
        self.pose_branch = Mlp(D, cfg.pose_branch_hidden, cfg.target_dim)
        for name in (cfg.trans_act, cfg.quat_act, cfg.fl_act):
            activation(name)  # fail early on an unknown name

    def activate(self, raw: torch.Tensor) -> torch.Tensor:
        """Raw [..., 9] -> activated copy (translation, quaternion, FoV activations)."""
        c = self.cfg
        return torch.cat((activation(c.trans_act)(raw[..., :3]), activation(c.quat_act)(raw[..., 3:7]),
                          activation(c.fl_act)(raw[..., 7:])), dim=-1)

    def forward(self, tokens: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
                debug: dict | None = None) -> list[torch.Tensor]:
        """tokens [B, S, N, 2C] (one aggregator output, or its two halves) -> list of
        num_iterations [B, S, 9]. Reads the camera token (token 0) only."""
        tok = take_tokens(tokens, slice(None), 0, self.token_norm.weight.dtype)  # [B, S, 2C]
        B, S = tok.shape[:2]
        tok = self.token_norm(tok)
        raw = None
        out: list[torch.Tensor] = []
        for it in range(self.cfg.num_iterations):
            cond_in = self.empty_pose_tokens.expand(B, S, -1) if raw is None else raw
            shift, scale, gate = self.poseLN_modulation(self.embed_pose(cond_in)).chunk(3, dim=-1)
            z = gate * (self.adaln_norm(tok) * (1 + scale) + shift) + tok
            z = self.trunk(z)
            delta = self.pose_branch(self.trunk_norm(z))
            if debug is not None:
                debug[f"camera_head.delta.{it}"] = delta.detach().clone()
            raw = delta if raw is None else raw + delta  # the raw prediction is fed back
            out.append(self.activate(raw))
        return out


# ---------------------------------------------------------------------------- DPT head
@dataclass
class Projected:
    """A DPT head's input made ahead: per layer k and frame chunk j (``DPTHead.frame_chunks(frames,
    chunk)``) the map ``maps[k][j]`` [batch * s_j, out_channels[k], h, w] of ``DPTHead.project``."""

    batch: int
    frames: int
    chunk: int | None  # the frames_chunk_size the maps were made with
    maps: list[list[torch.Tensor | None]] = field(default_factory=list)


def _sincos(pos: torch.Tensor, dim: int, omega_0: float) -> torch.Tensor:
    """pos [M] -> [M, dim]: sin(pos*omega_j) for j < dim/2, then cos; float64 maths."""
    omega = torch.arange(dim // 2, dtype=torch.float64, device=pos.device) / (dim / 2.0)
    omega = 1.0 / omega_0 ** omega
    ang = pos.reshape(-1).to(torch.float64)[:, None] * omega[None, :]
    return torch.cat((torch.sin(ang), torch.cos(ang)), dim=1)


def dpt_position_embedding(hh: int, ww: int, channels: int, aspect: float, dtype: torch.dtype,
                           device: torch.device, omega_0: float = 100.0) -> tuple[torch.Tensor, torch.Tensor]:
    """DPT sin/cos embedding of an hh x ww map, as its two separable float32 factors.

    The reference builds pe [channels, hh, ww] from a full grid (and casts it to float32):
    u spans +-(ar/d)(ww-1)/ww, v spans +-(1/d)(hh-1)/hh with ar = W/H of the *input image*
    and d = sqrt(ar^2 + 1); the grid in ``dtype``, sin/cos in float64. Its channels [0, C/2)
    depend on the column (u) only and [C/2, C) on the row (v) only, so

    Returns:
        ex [channels/2, ww] and ey [channels/2, hh] with ``pe[:C/2, i, j] == ex[:, j]`` and
        ``pe[C/2:, i, j] == ey[:, i]`` bit for bit.
    """
    if channels % 4:
        raise ValueError(f"DPT position embedding needs channels divisible by 4, got {channels}")
    diag = (aspect ** 2 + 1.0) ** 0.5
    sx, sy = aspect / diag, 1.0 / diag
    xs = torch.linspace(-sx * (ww - 1) / ww, sx * (ww - 1) / ww, steps=ww, dtype=dtype, device=device)
    ys = torch.linspace(-sy * (hh - 1) / hh, sy * (hh - 1) / hh, steps=hh, dtype=dtype, device=device)
    ex = _sincos(xs, channels // 2, omega_0).float().T.contiguous()
    ey = _sincos(ys, channels // 2, omega_0).float().T.contiguous()
    return ex, ey


class ResidualConvUnit(nn.Module):
    """y = conv2(relu(conv1(relu(x)))) + relu(x)  (the reference's in-place ReLU on the skip)."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, 1, 1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, 1, 1, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [B, F, h, w] -> [B, F, h, w]; x is overwritten by relu(x), as in the reference.

        In-place ops touch only tensors whose backward does not need them (conv outputs), so
        autograd still works; the heads write no new [B, F, h, w] buffer they can avoid.
        """
        x = F.relu_(x)
        return self.conv2(F.relu_(self.conv1(x))).add_(x)


class FusionBlock(nn.Module):
    """RefineNet fusion: (a [+ RCU1(b)]) -> RCU2 -> bilinear resize (align_corners) -> 1x1 conv."""

    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.has_residual = has_residual
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, 1, 1, 0, bias=True)

    def forward(self, a: torch.Tensor, b: torch.Tensor | None = None,
                size: tuple[int, int] | None = None) -> torch.Tensor:
        out = self.resConfUnit1(b).add_(a) if self.has_residual else a
        out = self.resConfUnit2(out)
        if size is None:
            out = F.interpolate(out, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            out = F.interpolate(out, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(out)


class Scratch(nn.Module):
    """Container matching the checkpoint's ``scratch.*`` names."""

    def __init__(self, out_channels: tuple[int, ...], features: int, head_features_2: int, output_dim: int) -> None:
        super().__init__()
        for i, oc in enumerate(out_channels, start=1):
            setattr(self, f"layer{i}_rn", nn.Conv2d(oc, features, 3, 1, 1, bias=False))
        self.refinenet1 = FusionBlock(features)
        self.refinenet2 = FusionBlock(features)
        self.refinenet3 = FusionBlock(features)
        self.refinenet4 = FusionBlock(features, has_residual=False)
        self.output_conv1 = nn.Conv2d(features, features // 2, 3, 1, 1)
        self.output_conv2 = nn.Sequential(nn.Conv2d(features // 2, head_features_2, 3, 1, 1), nn.ReLU(),
                                          nn.Conv2d(head_features_2, output_dim, 1, 1, 0))


class DPTHead(nn.Module):
    """Dense prediction head: 4 token layers -> multi-scale maps -> fused full-res output."""

    def __init__(self, cfg: DPTHeadConfig, agg_depth: int) -> None:
        super().__init__()
        self.cfg = cfg
        self.layers = [i % agg_depth for i in cfg.intermediate_layer_idx]  # non-negative indices
        oc = cfg.out_channels
        self.norm = nn.LayerNorm(cfg.dim_in, eps=cfg.layernorm_eps)
        self.projects = nn.ModuleList(nn.Conv2d(cfg.dim_in, c, 1, 1, 0) for c in oc)
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(oc[0], oc[0], kernel_size=4, stride=4, padding=0),
            nn.ConvTranspose2d(oc[1], oc[1], kernel_size=2, stride=2, padding=0),
            nn.Identity(),
            nn.Conv2d(oc[3], oc[3], kernel_size=3, stride=2, padding=1),
        ])
        self.scratch = Scratch(oc, cfg.features, cfg.head_features_2, cfg.output_dim)
        activation(cfg.activation)
        activation(cfg.conf_activation)

    def _pos(self, x: torch.Tensor, W: int, H: int) -> torch.Tensor:
        if not self.cfg.pos_embed:
            return x
        ex, ey = dpt_position_embedding(x.shape[-2], x.shape[-1], x.shape[1], W / H, x.dtype, x.device,
                                        self.cfg.pos_embed_omega_0)
        # x + pe * ratio with the float32 product, as the reference adds it; pe is separable, so the
        # two halves are added as broadcasts instead of materialising [C, h, w] (same values).
        ex, ey = ex * self.cfg.pos_embed_ratio, ey * self.cfg.pos_embed_ratio
        half = x.shape[1] // 2
        x[:, :half] += ex[None, :, None, :]  # x is a conv / resize output owned by this head
        x[:, half:] += ey[None, :, :, None]
        return x

    def project(self, k: int, tokens: torch.Tensor | tuple[torch.Tensor, torch.Tensor], patch_start_idx: int,
                H: int, W: int, s0: int, s1: int) -> torch.Tensor:
        """Layer ``self.layers[k]``'s patch tokens of frames s0:s1 -> [B*s, out_channels[k], h, w]:
        LayerNorm, 1x1 projection and position embedding (the per-layer part before the resize)."""
        p = self.cfg.patch_size
        h, w = H // p, W // p
        x = take_tokens(tokens, slice(s0, s1), slice(patch_start_idx, None), self.norm.weight.dtype)
        B, s = x.shape[:2]
        x = self.norm(x.reshape(B * s, -1, x.shape[-1]))
        x = x.permute(0, 2, 1).reshape(B * s, x.shape[-1], h, w)
        return self._pos(self.projects[k](x), W, H)

    def frame_chunks(self, S: int, frames_chunk_size: int | None = None) -> list[tuple[int, int]]:
        """The (s0, s1) frame ranges :meth:`forward` processes together."""
        chunk = frames_chunk_size or self.cfg.frames_chunk_size or S
        return [(s0, min(S, s0 + chunk)) for s0 in range(0, S, chunk)]

    def project_all(self, k: int, tokens: torch.Tensor | tuple[torch.Tensor, torch.Tensor], patch_start_idx: int,
                    image_hw: tuple[int, int], frames_chunk_size: int | None = None) -> list[torch.Tensor]:
        """:meth:`project` of every frame chunk of :meth:`frame_chunks` -> one [B*s, out_channels[k], h, w]
        per chunk, kept as the projection made it (its memory layout decides the next convolution's
        algorithm, hence its rounding).

        What :meth:`forward` takes as ``projected``: a kept layer's 2C channels per token become
        out_channels[k] (256 to 1024) as soon as the layer exists, the same numbers as projecting
        it inside the forward.
        """
        H, W = image_hw
        S = (tokens[0] if isinstance(tokens, tuple) else tokens).shape[1]
        return [self.project(k, tokens, patch_start_idx, H, W, s0, s1)
                for s0, s1 in self.frame_chunks(S, frames_chunk_size)]

    def _forward_frames(self, tokens: dict[int, torch.Tensor] | None, patch_start_idx: int, H: int, W: int,
                        s0: int, s1: int, projected: list[torch.Tensor] | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames s0:s1 -> (fused [B*s, F/2, 8h', 8w'] output_conv1 map, raw output [B*s, od, H, W])."""
        cfg = self.cfg
        p = cfg.patch_size
        h, w = H // p, W // p
        feats = []
        for k, layer in enumerate(self.layers):
            if projected is not None:
                x = projected[k]  # this chunk's projection (forward checks the ranges)
            else:
                x = self.project(k, tokens[layer], patch_start_idx, H, W, s0, s1)
            feats.append(self.resize_layers[k](x))
        sc = self.scratch
        r1, r2, r3, r4 = (getattr(sc, f"layer{i}_rn")(f) for i, f in enumerate(feats, start=1))
        del feats
        out = sc.refinenet4(r4, size=r3.shape[2:])
        out = sc.refinenet3(out, r3, size=r2.shape[2:])
        out = sc.refinenet2(out, r2, size=r1.shape[2:])
        out = sc.refinenet1(out, r1)
        fused = sc.output_conv1(out)
        out = F.interpolate(fused, size=(int(h * p / cfg.down_ratio), int(w * p / cfg.down_ratio)),
                            mode="bilinear", align_corners=True)
        conv_a, _, conv_b = sc.output_conv2  # conv 3x3, ReLU, conv 1x1 (checkpoint names kept)
        out = conv_a(self._pos(out, W, H))
        out = conv_b(F.relu_(out))
        return fused, out

    def forward(self, tokens: dict[int, torch.Tensor] | None, image_hw: tuple[int, int], patch_start_idx: int,
                frames_chunk_size: int | None = None, debug: dict | None = None,
                debug_name: str = "dpt", projected: "Projected | None" = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Dense prediction, processed ``frames_chunk_size`` frames at a time.

        Args:
            tokens: {layer: [B, S, N, 2C] or its two halves} holding every index in ``self.layers``
                (any float dtype: each chunk is cast to the head's); None with ``projected``.
            image_hw: (H, W) of the network input.
            projected: instead of ``tokens``, every layer's :meth:`project_all` (see
                :class:`Projected`), made with the same ``frames_chunk_size``; each chunk's maps
                are dropped (set to None) once used.

        Returns:
            value [B, S, H, W, output_dim - 1] and confidence [B, S, H, W].
        """
        H, W = image_hw
        if projected is not None:
            B, S = projected.batch, projected.frames
            if self.frame_chunks(S, projected.chunk) != self.frame_chunks(S, frames_chunk_size):
                raise ValueError("projected was made with another frames_chunk_size")
        else:
            any_t = tokens[self.layers[0]]
            B, S = (any_t[0] if isinstance(any_t, tuple) else any_t).shape[:2]
        act_v, act_c = activation(self.cfg.activation), activation(self.cfg.conf_activation)
        values = confs = None  # written a chunk at a time (no list of chunks and its concatenation)
        fused_all = []
        for j, (s0, s1) in enumerate(self.frame_chunks(S, frames_chunk_size)):
            proj = None
            if projected is not None:
                proj = [maps[j] for maps in projected.maps]
                for maps in projected.maps:
                    maps[j] = None  # used: dropped
            fused, raw = self._forward_frames(tokens, patch_start_idx, H, W, s0, s1, proj)
            del proj
            if debug is not None:
                fused_all.append(fused.reshape(B, s1 - s0, *fused.shape[1:]))
            fmap = raw.permute(0, 2, 3, 1)
            value = act_v(fmap[..., :-1]).reshape(B, s1 - s0, *fmap.shape[1:3], -1)
            conf = act_c(fmap[..., -1]).reshape(B, s1 - s0, *fmap.shape[1:3])
            if values is None:
                values = torch.empty(B, S, *value.shape[2:], dtype=value.dtype, device=value.device)
                confs = torch.empty(B, S, *conf.shape[2:], dtype=conf.dtype, device=conf.device)
            values[:, s0:s1] = value
            confs[:, s0:s1] = conf
            del raw, fmap, fused, value, conf
        if debug is not None:
            debug[f"{debug_name}.fused"] = torch.cat(fused_all, dim=1).flatten(0, 1)
        return values, confs
