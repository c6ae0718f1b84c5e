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
from vggt_init.model.heads import CameraHead, DPTHead, Projected, take_tokens

__all__ = ["VGGT", "TRACK_HEAD_PREFIX"]

TRACK_HEAD_PREFIX = "track_head."


def _now(device: torch.device) -> float:
    """``time.perf_counter()`` once the device's queued work is done: CUDA runs asynchronously,
    so without the sync the per-part timings measure kernel launches."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


class _HeadsInput:
    """What the heads keep of each aggregator output they read, made as soon as the output exists
    (``Aggregator(on_layer=...)``) so that no [B, S, N, 2C] layer outlives its step.

    The camera head keeps the camera token [B, S, 1, 2C]; a DPT head its LayerNorm + 1x1
    projection of the patch tokens (:class:`~vggt_init.model.heads.Projected`: per frame chunk
    [B*s, out_channels[k], h, w] float32, 256-1024 channels instead of 2C = 2048), made
    ``frames_chunk_size`` frames at a time exactly as its forward would. ``seconds`` holds the
    time spent per head (charged to the head, not the trunk).
    """

    def __init__(self, model: "VGGT", device_type: str, psi: int, image_hw: tuple[int, int],
                 frames_chunk_size: int | None, device: torch.device) -> None:
        self.model, self.device_type, self.psi, self.image_hw = model, device_type, psi, image_hw
        self.chunk, self.device = frames_chunk_size, device
        cfg = model.config
        self.camera_layer = cfg.camera_head.token_layer % cfg.aggregator.depth if model.camera_head is not None else None
        self.dpt = [(n, h) for n, h in (("depth", model.depth_head), ("point", model.point_head)) if h is not None]
        self.projected: dict[str, Projected | None] = {n: None for n, _ in self.dpt}
        self.camera_tokens: torch.Tensor | None = None
        self.seconds = {"camera": 0.0, **{n: 0.0 for n, _ in self.dpt}}

    def __call__(self, i: int, frame: torch.Tensor, glob: torch.Tensor) -> None:
        with torch.autocast(device_type=self.device_type, enabled=False):
            if i == self.camera_layer:
                t0 = _now(self.device)
                head = self.model.camera_head
                self.camera_tokens = take_tokens((frame, glob), slice(None), slice(0, 1), head.token_norm.weight.dtype)
                self.seconds["camera"] += _now(self.device) - t0
            for name, head in self.dpt:
                for k, layer in enumerate(head.layers):
                    if layer == i:
                        t0 = _now(self.device)
                        if self.projected[name] is None:
                            self.projected[name] = Projected(frame.shape[0], frame.shape[1], self.chunk,
                                                             [[] for _ in head.layers])
                        self.projected[name].maps[k] = head.project_all(k, (frame, glob), self.psi, self.image_hw,
                                                                        self.chunk)
                        self.seconds[name] += _now(self.device) - t0


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

        psi = self.aggregator.patch_start_idx
        heads_in = _HeadsInput(self, device_type, psi, (H, W), frames_chunk_size, images.device)
        t0 = _now(images.device)
        if trunk_dtype is not None and trunk_dtype != param_dtype:
            ctx = torch.autocast(device_type=device_type, dtype=trunk_dtype)
        else:
            ctx = contextlib.nullcontext()
        with ctx:
            self.aggregator(images.to(param_dtype), keep=self.layers_needed, debug=debug, on_layer=heads_in)
        timings["aggregator"] = _now(images.device) - t0 - sum(heads_in.seconds.values())

        out: dict = {}
        with torch.autocast(device_type=device_type, enabled=False):
            if self.camera_head is not None:
                t0 = _now(images.device)
                ch_debug = {} if debug is not None else None
                pose_list = self.camera_head(heads_in.camera_tokens, debug=ch_debug)
                heads_in.camera_tokens = None
                out["pose_enc"] = pose_list[-1]
                out["pose_enc_list"] = pose_list
                if debug is not None:
                    debug.update(ch_debug)
                timings["camera_head"] = _now(images.device) - t0 + heads_in.seconds["camera"]
            for name, head, keys in (("depth", self.depth_head, ("depth", "depth_conf")),
                                     ("point", self.point_head, ("world_points", "world_points_conf"))):
                if head is None:
                    continue
                t0 = _now(images.device)
                value, conf = head(None, (H, W), psi, frames_chunk_size, debug, f"{name}_head",
                                   projected=heads_in.projected.pop(name))
                out[keys[0]], out[keys[1]] = value, conf
                timings[f"{name}_head"] = _now(images.device) - t0 + heads_in.seconds[name]
        return out
