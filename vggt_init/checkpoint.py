"""Finding, safely reading and strictly checking VGGT checkpoints.

Resolution order (first hit wins):
1. an explicit path (CLI ``--checkpoint``, or ``checkpoint`` in the model-config JSON);
2. the environment variable ``VGGT_CHECKPOINT``;
3. the local Hugging Face cache for ``facebook/VGGT-1B`` (``model.safetensors``, then
   ``model.pt``);
4. a download with huggingface_hub, unless offline: ``HF_HUB_OFFLINE=1``, or the hub's host
   cannot be reached within 3 s (one probe, no retries), or the download fails.
Otherwise :class:`CheckpointNotFoundError` says where to put the file.

Reading: ``.safetensors`` with safetensors; ``.pt``/``.pth``/``.bin`` with
``torch.load(weights_only=True)`` only, which refuses arbitrary pickled objects.

Checking: every key and shape of the file is compared with our architecture (all three
heads, built on the meta device). ``track_head.*`` keys are skipped by name; any other
missing or unexpected key, or a shape mismatch, is an error.
"""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable

if TYPE_CHECKING:
    import torch

    from vggt_init.model.config import VGGTConfig
    from vggt_init.model.vggt import VGGT

# torch and the model are imported where a checkpoint is read: finding one (resolve_checkpoint,
# skip_reason) imports neither, since the workflow asks at every Snakefile parse

__all__ = [
    "HF_REPO_ID",
    "HF_FILENAMES",
    "ENV_VAR",
    "CheckpointNotFoundError",
    "CheckpointFormatError",
    "StateDictMismatchError",
    "resolve_checkpoint",
    "skip_reason",
    "hub_unreachable_reason",
    "read_state_dict",
    "expected_shapes",
    "check_state_dict",
    "load_model",
]

log = logging.getLogger(__name__)

HF_REPO_ID = "facebook/VGGT-1B"
HF_FILENAMES = ("model.safetensors", "model.pt")
ENV_VAR = "VGGT_CHECKPOINT"


class CheckpointNotFoundError(FileNotFoundError):
    """No checkpoint could be found or downloaded."""


class CheckpointFormatError(ValueError):
    """A checkpoint file that cannot be read safely (unknown format, pickled objects)."""


class StateDictMismatchError(ValueError):
    """A checkpoint whose keys or shapes do not fit the architecture."""


def _hf_cache_lookup(repo_id: str, filenames: Iterable[str], cache_dir: str | os.PathLike | None = None) -> Path | None:
    """The first of ``filenames`` present in the local Hugging Face cache, or None."""
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:  # pragma: no cover - huggingface_hub is a dependency
        return None
    for name in filenames:
        hit = try_to_load_from_cache(repo_id, name, cache_dir=cache_dir)
        if isinstance(hit, str) and Path(hit).is_file():
            return Path(hit)
    return None


HUB_PROBE_TIMEOUT_S = 3.0


def hub_unreachable_reason(env: dict | None = None, timeout: float = HUB_PROBE_TIMEOUT_S) -> str | None:
    """Why the Hugging Face Hub cannot be reached (None when a TCP connection opens).

    One name lookup and one TCP connect to the hub's host (``HF_ENDPOINT``, default
    huggingface.co) within ``timeout`` seconds. Without it, huggingface_hub retries each file
    five times with back-off (about 48 s for the two file names) before giving up offline.
    """
    import socket
    from urllib.parse import urlparse

    env = dict(os.environ) if env is None else env
    url = urlparse(env.get("HF_ENDPOINT") or "https://huggingface.co")
    host = url.hostname or "huggingface.co"
    port = url.port or (80 if url.scheme == "http" else 443)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as exc:
        return f"{host}:{port} cannot be reached ({exc.__class__.__name__}: {exc})"


def _hf_download(repo_id: str, filenames: Iterable[str]) -> Path | None:
    from huggingface_hub import hf_hub_download

    reason = hub_unreachable_reason()
    if reason is not None:
        log.warning("not downloading %s: the Hugging Face Hub at %s (offline?)", repo_id, reason)
        return None
    log.info("downloading %s from the Hugging Face Hub (about 5 GB) ...", repo_id)
    last: Exception | None = None
    for name in filenames:
        try:
            return Path(hf_hub_download(repo_id, name))
        except Exception as exc:  # network errors, missing file, gated repo: try the next
            last = exc
            log.debug("download of %s/%s failed: %s", repo_id, name, exc)
    if last is not None:
        log.warning("could not download %s from the Hugging Face Hub: %s", repo_id, last)
    return None


def _offline(env: dict) -> bool:
    return str(env.get("HF_HUB_OFFLINE", "")).lower() in ("1", "true", "yes", "on")


def _not_found_message(repo_id: str) -> str:
    try:
        from huggingface_hub.constants import HF_HUB_CACHE
    except ImportError:  # pragma: no cover
        HF_HUB_CACHE = "~/.cache/huggingface/hub"
    cache = Path(HF_HUB_CACHE) / f"models--{repo_id.replace('/', '--')}"
    return (
        f"no VGGT checkpoint found. Put the weights somewhere and point to them, in this order of "
        f"precedence: (1) --checkpoint /path/to/model.pt (or model.safetensors), or \"checkpoint\" in "
        f"the --model-config JSON; (2) the environment variable {ENV_VAR}=/path/to/model.pt; (3) the "
        f"Hugging Face cache at {cache}/snapshots/<revision>/model.safetensors or model.pt, e.g. via "
        f"`huggingface-cli download {repo_id} model.pt` on a machine with internet "
        f"(https://huggingface.co/{repo_id}/resolve/main/model.pt, about 5 GB)."
    )


def resolve_checkpoint(
    explicit: str | os.PathLike | None = None,
    env: dict | None = None,
    repo_id: str = HF_REPO_ID,
    filenames: tuple[str, ...] = HF_FILENAMES,
    cache_lookup: Callable[[str, Iterable[str]], Path | None] | None = None,
    download: Callable[[str, Iterable[str]], Path | None] | None = None,
    allow_download: bool = True,
) -> Path:
    """The checkpoint file to use (see the module docstring for the order).

    Args:
        explicit: a path given on the command line or in the config; it must exist.
        env: environment mapping (``os.environ`` by default).
        cache_lookup, download: replacements for the Hugging Face cache lookup and download
            (tests); None uses huggingface_hub.
        allow_download: False never downloads.

    Raises:
        CheckpointNotFoundError: nothing found; the message says where to put the file.
    """
    env = dict(os.environ) if env is None else env
    if explicit:
        p = Path(explicit).expanduser()
        if not p.is_file():
            raise CheckpointNotFoundError(f"checkpoint {p} does not exist (given explicitly); fix the path")
        return p
    if env.get(ENV_VAR):
        p = Path(env[ENV_VAR]).expanduser()
        if not p.is_file():
            raise CheckpointNotFoundError(f"{ENV_VAR}={p} does not exist; fix or unset it")
        return p
    cache_lookup = cache_lookup or _hf_cache_lookup
    download = download or _hf_download
    hit = cache_lookup(repo_id, filenames)
    if hit is not None:
        log.info("using the cached checkpoint %s", hit)
        return hit
    if allow_download and not _offline(env):
        hit = download(repo_id, filenames)
        if hit is not None:
            return hit
    raise CheckpointNotFoundError(_not_found_message(repo_id))


def skip_reason(env: dict | None = None, explicit: str | os.PathLike | None = None) -> str | None:
    """Why VGGT cannot run here, in one sentence, or None (a checkpoint is in place, or the hub
    can be reached and the job will download it). ``explicit``: the configured checkpoint
    path, if any. Used by the workflow to skip VGGT up front instead of letting its jobs fail."""
    env = dict(os.environ) if env is None else env
    try:
        resolve_checkpoint(explicit=explicit, env=env, allow_download=False)
        return None
    except CheckpointNotFoundError as exc:
        if explicit or env.get(ENV_VAR):
            return str(exc)
    if _offline(env):
        return ("no VGGT-1B checkpoint (VGGT_CHECKPOINT unset, none in the Hugging Face cache) and "
                "HF_HUB_OFFLINE is set, so it cannot be downloaded")
    unreachable = hub_unreachable_reason(env)
    if unreachable is not None:
        return ("no VGGT-1B checkpoint (VGGT_CHECKPOINT unset, none in the Hugging Face cache) and "
                f"the Hugging Face Hub cannot be reached: {unreachable}")
    return None


def read_state_dict(path: str | os.PathLike, keys: Iterable[str] | None = None) -> dict[str, torch.Tensor]:
    """Read tensors from a checkpoint without executing code.

    Args:
        path: ``.safetensors``, or a torch file (``.pt``, ``.pth``, ``.bin``) holding a flat
            dict of tensors (a single nested ``state_dict``/``model`` dict is accepted).
        keys: read only these keys (safetensors reads lazily; others are dropped).

    Raises:
        CheckpointFormatError: unknown suffix, pickled non-tensor objects, or not a dict.
    """
    import torch

    path = Path(path)
    wanted = None if keys is None else set(keys)
    suffix = path.suffix.lower()
    if suffix == ".safetensors":
        from safetensors import safe_open

        try:
            with safe_open(str(path), framework="pt", device="cpu") as f:
                names = [k for k in f.keys() if wanted is None or k in wanted]
                return {k: f.get_tensor(k) for k in names}
        except Exception as exc:
            raise CheckpointFormatError(f"cannot read safetensors file {path}: {exc}") from exc
    if suffix not in (".pt", ".pth", ".bin", ".ckpt"):
        raise CheckpointFormatError(f"unknown checkpoint format {path.name!r}; use .safetensors or .pt")
    try:
        try:
            obj = torch.load(str(path), map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as exc:
            if "mmap" not in str(exc):
                raise
            obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointFormatError(
            f"refusing to load {path}: it contains pickled objects other than tensors "
            f"(torch.load with weights_only=True rejected it: {str(exc).splitlines()[0]}). "
            "Only plain state_dict files are accepted; convert it to .safetensors from a trusted source."
        ) from exc
    if isinstance(obj, dict) and len(obj) == 1 and next(iter(obj)) in ("state_dict", "model"):
        obj = next(iter(obj.values()))
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointFormatError(f"{path} does not hold a flat dict of tensors (a state_dict)")
    return {k: v for k, v in obj.items() if wanted is None or k in wanted}


def _file_shapes(path: Path) -> dict[str, tuple[int, ...]] | None:
    """Key -> shape without reading data (safetensors only)."""
    if path.suffix.lower() != ".safetensors":
        return None
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except Exception as exc:  # SafetensorError: truncated, damaged or not safetensors at all
        raise CheckpointFormatError(
            f"cannot read safetensors file {path}: {exc}; the file is damaged or not a "
            "safetensors checkpoint: download it again"
        ) from exc


def expected_shapes(config: VGGTConfig) -> dict[str, tuple[int, ...]]:
    """Every parameter of our architecture (all heads, no track head) -> shape (meta device)."""
    import torch

    from vggt_init.model.config import HEAD_NAMES
    from vggt_init.model.vggt import VGGT

    with torch.device("meta"):
        model = VGGT(config, heads=HEAD_NAMES)
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def check_state_dict(shapes: dict[str, tuple[int, ...]], config: VGGTConfig) -> list[str]:
    """Compare a checkpoint's key -> shape map with the architecture.

    ``track_head.*`` keys are skipped by name; everything else must match exactly.

    Returns:
        The skipped keys.

    Raises:
        StateDictMismatchError: listing missing keys, unexpected keys and shape mismatches.
    """
    from vggt_init.model.vggt import TRACK_HEAD_PREFIX

    expected = expected_shapes(config)
    skipped = sorted(k for k in shapes if k.startswith(TRACK_HEAD_PREFIX))
    present = {k: tuple(v) for k, v in shapes.items() if not k.startswith(TRACK_HEAD_PREFIX)}
    missing = sorted(set(expected) - set(present))
    unexpected = sorted(set(present) - set(expected))
    wrong = sorted(f"{k}: file {present[k]} vs model {expected[k]}"
                   for k in set(present) & set(expected) if present[k] != expected[k])
    if missing or unexpected or wrong:
        def head(items: list[str]) -> str:
            return ", ".join(items[:8]) + (f" ... (+{len(items) - 8})" if len(items) > 8 else "")

        parts = []
        if missing:
            parts.append(f"{len(missing)} missing: {head(missing)}")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected: {head(unexpected)}")
        if wrong:
            parts.append(f"{len(wrong)} with wrong shape: {head(wrong)}")
        raise StateDictMismatchError(
            "checkpoint does not fit the model configuration (" + "; ".join(parts) + "). "
            "Use the model config that matches the weights (--model-config) or the right checkpoint."
        )
    return skipped


def load_model(config: VGGTConfig, checkpoint: str | os.PathLike, heads: Iterable[str] | None = None,
               device: str | torch.device = "cpu", dtype: torch.dtype | None = None) -> VGGT:
    """Build the model with only ``heads`` (None: every head, ``HEAD_NAMES``) and load the
    checkpoint into it in ``dtype`` (None: float32), strictly checked.

    The model is created on the meta device and the file's tensors are assigned (no second
    copy of the weights). Returns the model in eval mode, parameters frozen.
    """
    import torch

    from vggt_init.model.config import HEAD_NAMES
    from vggt_init.model.vggt import TRACK_HEAD_PREFIX, VGGT

    path = Path(checkpoint)
    heads = tuple(HEAD_NAMES if heads is None else heads)
    dtype = torch.float32 if dtype is None else dtype
    shapes = _file_shapes(path)
    state = None
    if shapes is None:
        state = read_state_dict(path)
        shapes = {k: tuple(v.shape) for k, v in state.items()}
    skipped = check_state_dict(shapes, config)
    if skipped:
        log.info("skipped %d %s* tensors (track head not implemented)", len(skipped), TRACK_HEAD_PREFIX)
    with torch.device("meta"):
        model = VGGT(config, heads=heads)
    needed = set(model.state_dict().keys())
    if state is None:
        state = read_state_dict(path, keys=needed)
    else:
        state = {k: v for k, v in state.items() if k in needed}
    state = {k: v.to(dtype=dtype) for k, v in state.items()}
    model.load_state_dict(state, strict=True, assign=True)
    del state
    model = model.to(device).eval().requires_grad_(False)
    return model
