"""Configuration tree of our VGGT implementation. Defaults are VGGT-1B (facebook/VGGT-1B).

Every size lives here; the modules read nothing else. :func:`VGGTConfig.from_fixture_config`
reads the ``config.json`` format of the reference fixtures (a tiny model of the same
architecture), so the same code runs both.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

__all__ = [
    "DinoConfig",
    "AggregatorConfig",
    "CameraHeadConfig",
    "DPTHeadConfig",
    "VGGTConfig",
    "HEAD_NAMES",
]

HEAD_NAMES = ("camera", "depth", "point")


@dataclass
class DinoConfig:
    """The patch embedder: a DINOv2 ViT with register tokens (ViT-L/14 + 4 registers)."""

    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    img_size: int = 518  # the image size the position embedding was built for
    patch_size: int = 14
    num_register_tokens: int = 4
    qkv_bias: bool = True
    proj_bias: bool = True
    ffn_bias: bool = True
    layernorm_eps: float = 1e-6
    interpolate_antialias: bool = True

    @property
    def pos_embed_grid(self) -> int:
        return self.img_size // self.patch_size


@dataclass
class AggregatorConfig:
    """The alternating frame/global attention trunk."""

    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    qkv_bias: bool = True
    proj_bias: bool = True
    ffn_bias: bool = True
    qk_norm: bool = True
    rope_freq: float = 100.0
    aa_order: tuple[str, ...] = ("frame", "global")
    aa_block_size: int = 1
    layernorm_eps: float = 1e-5
    qk_norm_eps: float = 1e-5
    normalize_mean: tuple[float, float, float] = (0.485, 0.456, 0.406)
    normalize_std: tuple[float, float, float] = (0.229, 0.224, 0.225)

    @property
    def patch_start_idx(self) -> int:
        return 1 + self.num_register_tokens


@dataclass
class CameraHeadConfig:
    """The camera head: adaLN-modulated trunk with iterative pose refinement."""

    dim_in: int = 2048
    trunk_depth: int = 4
    num_heads: int = 16
    mlp_ratio: float = 4.0
    target_dim: int = 9
    num_iterations: int = 4
    trans_act: str = "linear"
    quat_act: str = "linear"
    fl_act: str = "relu"
    pose_branch_hidden: int = 1024
    layernorm_eps: float = 1e-5
    adaln_eps: float = 1e-6
    token_layer: int = -1


@dataclass
class DPTHeadConfig:
    """A DPT dense head (depth or point map)."""

    dim_in: int = 2048
    patch_size: int = 14
    features: int = 256
    out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024)
    intermediate_layer_idx: tuple[int, int, int, int] = (4, 11, 17, 23)
    pos_embed: bool = True
    pos_embed_ratio: float = 0.1
    pos_embed_omega_0: float = 100.0
    down_ratio: int = 1
    head_features_2: int = 32
    frames_chunk_size: int = 8
    layernorm_eps: float = 1e-5
    output_dim: int = 4
    activation: str = "inv_log"
    conf_activation: str = "expp1"


def _depth_head_default() -> DPTHeadConfig:
    return DPTHeadConfig(output_dim=2, activation="exp", conf_activation="expp1")


def _point_head_default() -> DPTHeadConfig:
    return DPTHeadConfig(output_dim=4, activation="inv_log", conf_activation="expp1")


def _build(cls, data: dict[str, Any] | None, base):
    """Dataclass ``cls`` from ``base`` overridden by the known keys of ``data``."""
    if not data:
        return base
    kwargs = asdict(base)
    names = {f.name for f in fields(cls)}
    for key, value in data.items():
        if key in names:
            kwargs[key] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)


@dataclass
class VGGTConfig:
    """The whole model. ``VGGTConfig()`` is VGGT-1B."""

    patch_size: int = 14
    dino: DinoConfig = field(default_factory=DinoConfig)
    aggregator: AggregatorConfig = field(default_factory=AggregatorConfig)
    camera_head: CameraHeadConfig = field(default_factory=CameraHeadConfig)
    depth_head: DPTHeadConfig = field(default_factory=_depth_head_default)
    point_head: DPTHeadConfig = field(default_factory=_point_head_default)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ValueError on sizes that cannot go together."""
        a, d, c = self.aggregator, self.dino, self.camera_head
        if d.embed_dim != a.embed_dim:
            raise ValueError(f"dino.embed_dim ({d.embed_dim}) must equal aggregator.embed_dim ({a.embed_dim})")
        if d.patch_size != self.patch_size:
            raise ValueError(f"dino.patch_size ({d.patch_size}) must equal patch_size ({self.patch_size})")
        for name, dim, heads in (("dino", d.embed_dim, d.num_heads), ("aggregator", a.embed_dim, a.num_heads),
                                 ("camera_head", c.dim_in, c.num_heads)):
            if dim % heads:
                raise ValueError(f"{name}: width {dim} is not divisible by num_heads {heads}")
        head_dim = a.embed_dim // a.num_heads
        if head_dim % 4:
            raise ValueError(f"aggregator head dim {head_dim} must be a multiple of 4 for 2D RoPE")
        if a.depth % a.aa_block_size:
            raise ValueError(f"aggregator.depth {a.depth} is not a multiple of aa_block_size {a.aa_block_size}")
        if sorted(a.aa_order) != ["frame", "global"]:
            raise ValueError(f"aggregator.aa_order must hold 'frame' and 'global' once each, got {a.aa_order}")
        if c.dim_in != 2 * a.embed_dim:
            raise ValueError(f"camera_head.dim_in ({c.dim_in}) must be 2 * aggregator.embed_dim")
        for name in ("depth_head", "point_head"):
            h: DPTHeadConfig = getattr(self, name)
            if h.dim_in != 2 * a.embed_dim:
                raise ValueError(f"{name}.dim_in ({h.dim_in}) must be 2 * aggregator.embed_dim")
            if len(h.out_channels) != 4 or len(h.intermediate_layer_idx) != 4:
                raise ValueError(f"{name}: out_channels and intermediate_layer_idx need 4 entries each")
            for i in h.intermediate_layer_idx:
                if not -a.depth <= i < a.depth:
                    raise ValueError(f"{name}: layer index {i} outside the {a.depth} aggregator outputs")
            if h.patch_size != self.patch_size:
                raise ValueError(f"{name}.patch_size must equal patch_size")
        if not -a.depth <= c.token_layer < a.depth:
            raise ValueError(f"camera_head.token_layer {c.token_layer} outside the {a.depth} aggregator outputs")

    def layers_needed(self, heads: tuple[str, ...] | list[str] | set[str]) -> list[int]:
        """Sorted non-negative aggregator output indices that the given heads read."""
        depth = self.aggregator.depth
        need: set[int] = set()
        if "camera" in heads:
            need.add(self.camera_head.token_layer % depth)
        for name in ("depth", "point"):
            if name in heads:
                need.update(i % depth for i in getattr(self, f"{name}_head").intermediate_layer_idx)
        return sorted(need)

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_fixture_config(cls, cfg: dict[str, Any]) -> "VGGTConfig":
        """Build from the fixtures' ``config.json`` dict (missing keys keep VGGT-1B values).

        Understood sections: ``patch_size``, ``aggregator``, ``dino``, ``camera_head``,
        ``depth_head``, ``point_head``; ``track_head`` must be null or absent (not
        implemented). Unknown keys (``init``, ``input``, ``files``...) are ignored.
        """
        if not isinstance(cfg, dict):
            raise ValueError("model config must be a JSON object")
        if cfg.get("track_head") not in (None, {}):
            raise ValueError("model config: track_head is not implemented; set it to null")
        dino_data = dict(cfg.get("dino") or {})
        if "pos_embed_grid" in dino_data and "img_size" not in dino_data:
            dino_data["img_size"] = int(dino_data["pos_embed_grid"]) * int(dino_data.get("patch_size", 14))
        agg_data = dict(cfg.get("aggregator") or {})
        return cls(
            patch_size=int(cfg.get("patch_size", 14)),
            dino=_build(DinoConfig, dino_data, DinoConfig()),
            aggregator=_build(AggregatorConfig, agg_data, AggregatorConfig()),
            camera_head=_build(CameraHeadConfig, cfg.get("camera_head"), CameraHeadConfig()),
            depth_head=_build(DPTHeadConfig, cfg.get("depth_head"), _depth_head_default()),
            point_head=_build(DPTHeadConfig, cfg.get("point_head"), _point_head_default()),
        )

    @classmethod
    def from_json(cls, path: str | Path) -> "VGGTConfig":
        """Read a JSON file in the fixtures' config.json format (see from_fixture_config)."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"cannot read model config {path}: {exc}") from exc
        return cls.from_fixture_config(data)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict that :meth:`from_fixture_config` reads back."""
        return asdict(self)
