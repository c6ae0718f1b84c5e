"""The vggt_init stage: images -> VGGT -> predictions.npz + sparse/0 + timing.json.

Only what the run needs is built and run: the camera head always, the point head
(``points_from='point_head'``, default, as in the paper) or the depth head + unprojection
(``points_from='depth'``); never the track head. Only the aggregator layers those heads
read are kept; the DPT heads run over chunks of frames; everything in inference mode.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from runtime.atomic import write_json
from camio.images import list_images
from runtime.logs import peak_rss_mb, timed
from runtime.memory import memory_retained, release_free_memory
from vggt_init.checkpoint import load_model, resolve_checkpoint
from vggt_init.defaults import FRAMES_CHUNK, IMAGE_SIZE, MAX_POINTS, MODE, POINT_SOURCES, POINTS_FROM
from vggt_init.export import select_points, write_colmap, write_predictions
from vggt_init.geometry import pose_encoding_to_extri_intri, unproject_depth
from vggt_init.model.config import VGGTConfig
from vggt_init.model.fastpath import fast_paths_enabled
from vggt_init.preprocess import ImageInputError, load_and_preprocess, to_model_input

__all__ = ["RunOptions", "MemoryBudgetError", "DTYPES", "resolve_device", "resolve_dtype", "estimate_memory_bytes",
           "available_memory_bytes", "run"]

log = logging.getLogger(__name__)


class MemoryBudgetError(MemoryError):
    """The run would not fit in memory; raised before anything large is allocated."""


DTYPES = ("auto", "fp32", "bf16")


@contextlib.contextmanager
def tf32_off():
    """Torch's TF32 switches (CUDA matmuls and cuDNN convolutions) off for the block, then
    restored. ``--dtype fp32`` runs inside it: cuDNN's default (on) rounds the DPT
    heads' convolutions to 10-bit mantissas, which put the point map 1.3e-3 from the CPU's on
    the fixture model (H100, benchmarks/records/gpu-2026-11-26.json) and the fixtures' float32
    outputs 2.5e-3 from their expectation (2.2e-6 with TF32 off). No effect on a CPU."""
    saved = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def resolve_device(name: str) -> torch.device:
    """``"auto"`` = the first CUDA device when torch sees one, else the CPU; ``"cpu"`` and
    ``"cuda[:N]"`` as given (ValueError when CUDA is asked for and absent, or the name is bad)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {name!r}") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name} requested but no CUDA device is available; use --device auto or cpu")
    return device


def resolve_dtype(name: str, device: torch.device) -> str:
    """``"auto"`` = ``"bf16"`` (the trunk under bf16 autocast, heads fp32) on a CUDA device that
    supports bf16 (``torch.cuda.is_bf16_supported()``: Ampere or newer), else ``"fp32"`` (the
    CPU included: bf16 there is slower and not the measured default); explicit names as given."""
    if name not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}, got {name!r}")
    if name != "auto":
        return name
    return "bf16" if device.type == "cuda" and torch.cuda.is_bf16_supported() else "fp32"


@dataclass
class RunOptions:
    """Options of one vggt_init run (the CLI maps 1:1 onto these)."""

    images: Path
    out: Path
    image_list: Path | None = None
    checkpoint: Path | None = None
    model_config: Path | None = None
    dtype: str = "auto"  # one of DTYPES; see resolve_dtype
    device: str = "auto"  # "auto", "cpu" or "cuda[:N]"; see resolve_device
    points_from: str = POINTS_FROM  # one of POINT_SOURCES
    max_points: int = MAX_POINTS
    mode: str = MODE  # one of MODES
    image_size: int = IMAGE_SIZE
    frames_chunk_size: int = FRAMES_CHUNK
    max_memory_gb: float | None = None  # default: what the OS reports as available
    threads: int | None = None
    extra: dict = field(default_factory=dict)


def _image_paths(opts: RunOptions) -> list[Path]:
    folder = Path(opts.images)
    if opts.image_list is not None:
        from runtime.checks import file_problem

        problem = file_problem(opts.image_list, "image list")
        if problem:
            raise ImageInputError(problem)
        names = [ln.strip() for ln in Path(opts.image_list).read_text().splitlines()
                 if ln.strip() and not ln.strip().startswith("#")]
        if not names:
            raise ImageInputError(f"image list {opts.image_list} is empty")
        from runtime.names import check_name_list

        try:
            check_name_list(names, opts.image_list)
        except ValueError as exc:
            raise ImageInputError(str(exc)) from None
    else:
        names = list_images(folder)
        if not names:
            raise ImageInputError(f"no images (png/jpg/tif/exr) in {folder}")
    paths = [folder / n for n in names]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise ImageInputError(f"{len(missing)} listed images do not exist, e.g. {missing[0]}")
    if len(set(p.name for p in paths)) != len(paths):
        raise ImageInputError("image names must be unique (the COLMAP model is keyed by name)")
    return paths


def estimate_memory_bytes(config: VGGTConfig, heads: tuple[str, ...], S: int, H: int, W: int,
                          frames_chunk_size: int, param_bytes: int = 4) -> int:
    """Rough peak memory of one forward pass (weights + activations), in bytes.

    Weights: every parameter of the built model. Trunk: per frame a handful of [N, C]
    and [N, 4C] buffers (qkv, MLP hidden, residual) plus the kept [N, 2C] layers. DPT:
    per chunk frame, the full-resolution F/2-channel maps (3 alive at once) and the
    multi-scale features. Calibrated against the reference measurement (3 x 518^2:
    +1.9 GB over the weights), with a 1.5x margin.
    """
    from vggt_init.checkpoint import expected_shapes

    shapes = expected_shapes(config)
    prefixes = ("aggregator.",) + tuple(f"{h}_head." for h in heads)
    n_params = sum(int(np.prod(s)) for k, s in shapes.items() if k.startswith(prefixes))
    a = config.aggregator
    p = config.patch_size
    N = (H // p) * (W // p) + a.patch_start_idx
    C = a.embed_dim
    trunk = S * N * C * 4 * (3 + 4 + 4) + len(config.layers_needed(heads)) * S * N * 2 * C * 4
    dense = 0
    for h in heads:
        if h in ("depth", "point"):
            hc = getattr(config, f"{h}_head")
            per_frame = H * W * 4 * (3 * hc.features // 2 + hc.head_features_2 + hc.output_dim)
            per_frame += (H // p) * (W // p) * 4 * (16 * hc.out_channels[0] + 4 * hc.out_channels[1]) * 2
            dense = max(dense, min(S, frames_chunk_size) * per_frame)
            dense += S * H * W * 4 * hc.output_dim  # outputs kept
    return int(n_params * param_bytes + 1.5 * (trunk + dense) + 0.3e9)


def available_memory_bytes(device: torch.device) -> int:
    """Free memory: CUDA free memory on a GPU, else MemAvailable from /proc/meminfo."""
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))


def _nonfinite(arrays: dict[str, np.ndarray]) -> dict[str, int]:
    return {k: int((~np.isfinite(v)).sum()) for k, v in arrays.items()
            if isinstance(v, np.ndarray) and v.dtype.kind == "f"}


def run(opts: RunOptions) -> dict:
    """Run the stage; returns the timing/summary dict also written to ``timing.json``."""
    t_start = time.perf_counter()
    if opts.points_from not in POINT_SOURCES:
        raise ValueError(f"points_from must be one of {POINT_SOURCES}, got {opts.points_from!r}")
    device = resolve_device(opts.device)
    dtype = resolve_dtype(opts.dtype, device)
    log.info("device %s (asked: %s), dtype %s (asked: %s)", device, opts.device, dtype, opts.dtype)
    if opts.threads:
        torch.set_num_threads(opts.threads)
    out = Path(opts.out)
    times: dict[str, float] = {}

    config, ckpt_from_config = VGGTConfig(), None
    if opts.model_config is not None:
        import json

        config = VGGTConfig.from_json(opts.model_config)
        ckpt_from_config = json.loads(Path(opts.model_config).read_text()).get("checkpoint")
        if ckpt_from_config and not Path(ckpt_from_config).is_absolute():
            ckpt_from_config = str(Path(opts.model_config).parent / ckpt_from_config)
    heads = ("camera", "point") if opts.points_from == "point_head" else ("camera", "depth")

    paths = _image_paths(opts)
    with timed("preprocess", log, times):
        images_u8, geos = load_and_preprocess(paths, opts.mode, opts.image_size)
    S, H, W = images_u8.shape[:3]
    log.info("%d images -> network input %dx%d (%s mode)", S, W, H, opts.mode)

    need = estimate_memory_bytes(config, heads, S, H, W, opts.frames_chunk_size)
    have = int(opts.max_memory_gb * 1e9) if opts.max_memory_gb else available_memory_bytes(device)
    log.info("estimated peak memory %.1f GB, available %.1f GB", need / 1e9, have / 1e9)
    if need > have:
        raise MemoryBudgetError(
            f"{S} images at {W}x{H} need about {need / 1e9:.1f} GB but only {have / 1e9:.1f} GB are available; "
            "use fewer images, a smaller --image-size, or a machine/GPU with more memory")

    checkpoint = resolve_checkpoint(opts.checkpoint or ckpt_from_config)
    with timed("load_model", log, times):
        model = load_model(config, checkpoint, heads=heads, device=device)
    trunk_dtype = None
    if dtype == "bf16":
        trunk_dtype = torch.bfloat16
        model.cast_trunk_weights(torch.bfloat16)  # same numbers as autocast, half the trunk weights
    if memory_retained():
        release_free_memory()  # the loader's and the cast's freed buffers: back to the system once

    x = to_model_input(images_u8).to(device)
    comp: dict[str, float] = {}
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    with timed("forward", log, times), torch.inference_mode(), \
            (tf32_off() if dtype == "fp32" else contextlib.nullcontext()):
        pred = model(x, trunk_dtype=trunk_dtype, frames_chunk_size=opts.frames_chunk_size, timings=comp)
    del x
    times.update({f"forward.{k}": v for k, v in comp.items()})

    with timed("postprocess", log, times):
        extr, intr = pose_encoding_to_extri_intri(pred["pose_enc"].float(), (H, W))
        extr = extr[0].cpu().numpy()
        intr = intr[0].cpu().numpy()
        arrays: dict[str, np.ndarray] = {
            "image_names": np.array([p.name for p in paths]),
            "cam_from_world": extr,
            "intrinsics": intr,
            "intrinsics_original": np.stack([g.intrinsics_to_original(K) for g, K in zip(geos, intr)]),
            "image_sizes_original": np.array([[g.width, g.height] for g in geos], dtype=np.int64),
            "colors": images_u8,
        }
        if opts.points_from == "point_head":
            arrays["world_points"] = pred["world_points"][0].float().cpu().numpy()
            arrays["world_points_conf"] = pred["world_points_conf"][0].float().cpu().numpy()
        else:
            depth = pred["depth"][0, ..., 0].float().cpu().numpy()
            arrays["depth"] = depth
            arrays["depth_conf"] = pred["depth_conf"][0].float().cpu().numpy()
            arrays["world_points"] = unproject_depth(depth, extr, intr).astype(np.float32)
            arrays["world_points_conf"] = arrays["depth_conf"]
        del pred
    nonfinite = _nonfinite(arrays)
    n_bad = sum(nonfinite.values())
    if n_bad:
        log.warning("the model produced %d non-finite values: %s", n_bad,
                    {k: v for k, v in nonfinite.items() if v})

    with timed("export", log, times):
        write_predictions(out / "predictions.npz", arrays)
        valid = np.stack([g.valid_mask() for g in geos])
        pts, cols, _ = select_points(arrays["world_points"], arrays["world_points_conf"], images_u8, valid,
                                     opts.max_points)
        write_colmap(out / "sparse" / "0", [p.name for p in paths], geos, arrays["cam_from_world"],
                     arrays["intrinsics_original"], pts, cols)
    summary = {
        "num_images": S,
        "input_hw": [H, W],
        "mode": opts.mode,
        "dtype": dtype,
        "device": str(device),
        "points_from": opts.points_from,
        "heads_built": list(model.heads),
        "aggregator_layers_kept": model.layers_needed,
        "checkpoint": str(checkpoint),
        "torch_threads": torch.get_num_threads(),
        "cpu_fast_paths": fast_paths_enabled(),  # oneDNN Linear/attention (vggt_init.model.fastpath)
        "thp_alloc": os.environ.get("THP_MEM_ALLOC_ENABLE", ""),
        "retain_freed_memory": memory_retained(),  # runtime.memory (the CLI turns it on)
        "num_sparse_points": int(len(pts)),
        "estimated_memory_gb": need / 1e9,
        "wall_time_s": {**times, "total": time.perf_counter() - t_start},
        "peak_rss_mb": peak_rss_mb(),
        "peak_cuda_mb": (torch.cuda.max_memory_allocated(device) / 2**20) if device.type == "cuda" else None,
        "nonfinite": nonfinite,
        "nonfinite_total": n_bad,
        "flagged": bool(n_bad),
    }
    write_json(out / "timing.json", summary)
    log.info("vggt_init done: %d images, %d points, %.1f s, peak RSS %.0f MB%s", S, len(pts),
             summary["wall_time_s"]["total"], summary["peak_rss_mb"], " [NON-FINITE VALUES]" if n_bad else "")
    return summary
