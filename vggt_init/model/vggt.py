"""Top-level VGGT inference model: aggregator + the heads a run asks for (never the track head).

Output keys (only for the heads built): ``pose_enc`` [B,S,9], ``pose_enc_list`` (list of
[B,S,9]), ``depth`` [B,S,H,W,1], ``depth_conf`` [B,S,H,W], ``world_points`` [B,S,H,W,3],
``world_points_conf`` [B,S,H,W]. Poses are cam_from_world in OpenCV axes (VGGT's world
frame is frame 0's camera); see :mod:`vggt_init.geometry` for the conversions.
"""

from __future__ import annotations

import contextlib
import time
from typing import Iterable

import torch
from torch import nn

from vggt_init.model.aggregator import Aggregator
from vggt_init.model.config import HEAD_NAMES, VGGTConfig
from vggt_init.model.heads import CameraHead, DPTHead

__all__ = ["VGGT", "TRACK_HEAD_PREFIX"]

TRACK_HEAD_PREFIX = "track_head."


def _now(device: torch.device) -> float:
    """``time.perf_counter()`` once the device's queued work is done: CUDA runs asynchronously,
    so without the sync the per-part timings measure kernel launches."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


class VGGT(nn.Module):
    """Weight-compatible VGGT (inference path).

    Args:
        config: sizes; VGGT-1B by default.
        heads: which of "camera", "depth", "point" to build. A head not built has no
            parameters and is not run.
    """

    def __init__(self, config: VGGTConfig | None = None, heads: Iterable[str] = HEAD_NAMES) -> None:
        super().__init__()
        self.config = config or VGGTConfig()
        heads = tuple(heads)
        unknown = set(heads) - set(HEAD_NAMES)
        if unknown:
            raise ValueError(f"unknown heads {sorted(unknown)}; choose from {HEAD_NAMES} (the track head is not implemented)")
        self.heads = tuple(h for h in HEAD_NAMES if h in heads)
        depth = self.config.aggregator.depth
        self.aggregator = Aggregator(self.config)
        self.camera_head = CameraHead(self.config.camera_head) if "camera" in heads else None
        self.depth_head = DPTHead(self.config.depth_head, depth) if "depth" in heads else None
        self.point_head = DPTHead(self.config.point_head, depth) if "point" in heads else None

    def cast_trunk_weights(self, dtype: torch.dtype) -> "VGGT":
        """Store the aggregator's Linear/Conv2d weights and biases in ``dtype`` (bf16/fp16).

        The forward then runs the trunk under autocast to ``dtype``. Autocast would cast
        these same fp32 tensors to ``dtype`` on every call, so the numbers are identical;
        casting once saves the per-call conversion and half of the trunk's weight memory.
        LayerNorms, LayerScale, tokens and position embeddings stay fp32, as under autocast.
        """
        for m in self.aggregator.modules():
            if isinstance(m, (nn.Linear, nn.Conv2d)):
                m.to(dtype)
        self._trunk_weight_dtype = dtype
        return self

    @property
    def layers_needed(self) -> list[int]:
        """Aggregator outputs the built heads read (the only ones kept in memory)."""
        return self.config.layers_needed(self.heads)

    def forward(
        self,
        images: torch.Tensor,
        trunk_dtype: torch.dtype | None = None,
        frames_chunk_size: int | None = None,
        debug: dict | None = None,
        timings: dict | None = None,
    ) -> dict:
        """Run the model.

        Args:
            images: [S, 3, H, W] or [B, S, 3, H, W] RGB in [0, 1]; H, W multiples of the
                patch size (14), at least one patch each.
            trunk_dtype: None runs everything in the parameters' dtype; torch.bfloat16 (or
                float16) runs the aggregator under autocast (implied after
                :meth:`cast_trunk_weights`). The heads always run in the
                parameters' dtype with autocast disabled, as the reference does.
            frames_chunk_size: frames per DPT chunk (default: the head config's value).
            debug: if a dict, intermediates are stored in it (``dino.*``, ``camera_head.*``,
                ``depth_head.fused``, ``point_head.fused``).
            timings: if a dict, wall seconds per component are stored in it.

        Returns:
            dict of the outputs listed in the module docstring.
        """
        if images.dim() == 4:
            images = images[None]
        if images.dim() != 5 or images.shape[2] != 3:
            raise ValueError(f"images must be [S,3,H,W] or [B,S,3,H,W], got {tuple(images.shape)}")
        B, S, _, H, W = images.shape
        p = self.config.patch_size
        if H % p or W % p or H < p or W < p:
            raise ValueError(f"image size {H}x{W} must be a positive multiple of the {p} px patch size")
        timings = {} if timings is None else timings
        param_dtype = self.aggregator.camera_token.dtype  # the model's (and heads') dtype
        cast = getattr(self, "_trunk_weight_dtype", None)
        if cast is not None:
            if trunk_dtype not in (None, cast):
                raise ValueError(f"trunk weights are stored in {cast}; trunk_dtype {trunk_dtype} is not possible")
            trunk_dtype = cast
        device_type = images.device.type

        t0 = _now(images.device)
        if trunk_dtype is not None and trunk_dtype != param_dtype:
            ctx = torch.autocast(device_type=device_type, dtype=trunk_dtype)
        else:
            ctx = contextlib.nullcontext()
        with ctx:
            tokens = self.aggregator(images.to(param_dtype), keep=self.layers_needed, debug=debug, concat=False)
        timings["aggregator"] = _now(images.device) - t0

        out: dict = {}
        psi = self.aggregator.patch_start_idx
        with torch.autocast(device_type=device_type, enabled=False):
            # The kept layers stay as the trunk made them (their frame and global halves); each
            # head joins and casts to its dtype only the slice it reads (see heads.take_tokens).
            if self.camera_head is not None:
                t0 = _now(images.device)
                ch_debug = {} if debug is not None else None
                pose_list = self.camera_head(tokens[self.config.camera_head.token_layer % self.config.aggregator.depth],
                                             debug=ch_debug)
                out["pose_enc"] = pose_list[-1]
                out["pose_enc_list"] = pose_list
                if debug is not None:
                    debug.update(ch_debug)
                timings["camera_head"] = _now(images.device) - t0
            for name, head, keys in (("depth", self.depth_head, ("depth", "depth_conf")),
                                     ("point", self.point_head, ("world_points", "world_points_conf"))):
                if head is None:
                    continue
                t0 = _now(images.device)
                value, conf = head(tokens, (H, W), psi, frames_chunk_size, debug, f"{name}_head")
                out[keys[0]], out[keys[1]] = value, conf
                timings[f"{name}_head"] = _now(images.device) - t0
        return out
