"""Training checkpoints: ``DIR/ckpt/ckpt_<iteration>.pt``, plain tensors and dicts only.

A checkpoint is a ``torch.save`` of a dict of tensors, numbers, strings, lists and dicts, read
back with ``torch.load(..., weights_only=True)`` (no pickled code). It holds everything the
run needs to continue bit for bit on CPU: parameters, Adam state, densification statistics,
pose corrections and their Adam, the random generator state, the log rows so far and the
training wall time. Files are written atomically; older ones beyond ``keep`` are deleted only
after a newer one is complete, so a crash never loses the last good checkpoint.
"""

from __future__ import annotations

import logging
import pickle
import re
from pathlib import Path
from typing import Any

import torch

from runtime.atomic import atomic_path

__all__ = ["checkpoint_path", "list_checkpoints", "latest_checkpoint", "save_checkpoint",
           "load_checkpoint", "CKPT_DIR", "CPU_KEYS"]

log = logging.getLogger(__name__)

CKPT_DIR = "ckpt"
_PATTERN = re.compile(r"^ckpt_(\d+)\.pt$")


def checkpoint_path(out_dir: str | Path, iteration: int) -> Path:
    return Path(out_dir) / CKPT_DIR / f"ckpt_{iteration:07d}.pt"


def list_checkpoints(out_dir: str | Path) -> list[tuple[int, Path]]:
    """(iteration, path) of the complete checkpoints in ``out_dir/ckpt``, oldest first."""
    d = Path(out_dir) / CKPT_DIR
    if not d.is_dir():
        return []
    found = []
    for p in d.iterdir():
        m = _PATTERN.match(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


def latest_checkpoint(out_dir: str | Path) -> Path | None:
    found = list_checkpoints(out_dir)
    return found[-1][1] if found else None


def save_checkpoint(out_dir: str | Path, iteration: int, payload: dict[str, Any], keep: int = 2) -> Path:
    """Write ``payload`` (plus ``iteration``) atomically, then delete all but the newest
    ``keep`` checkpoints."""
    path = checkpoint_path(out_dir, iteration)
    try:
        with atomic_path(path) as tmp:
            torch.save({**payload, "iteration": int(iteration)}, tmp)
    except (OSError, RuntimeError) as exc:  # torch reports a full disk as a RuntimeError from its writer
        import errno
        import shutil

        free = shutil.disk_usage(Path(out_dir)).free if Path(out_dir).is_dir() else -1
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise OSError(getattr(exc, "errno", None) or errno.EIO,
                      f"cannot write the checkpoint {path} ({first}; {free / 2**20:.0f} MiB free): the previous "
                      "checkpoint is intact; free disk space and run the same command again to resume") from exc
    for _, old in list_checkpoints(out_dir)[:-keep]:
        old.unlink(missing_ok=True)
    log.debug("checkpoint %s", path)
    return path


# Entries that stay on the CPU whatever the training device: the random generator state (the
# trainer's torch.Generator is a CPU one; set_state refuses a CUDA tensor).
CPU_KEYS = ("rng",)


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; tensors mapped to ``device``, except the
    top-level :data:`CPU_KEYS` (read onto the CPU)."""
    data = _read(path)
    return {k: (v if k in CPU_KEYS else _to(v, torch.device(device))) for k, v in data.items()}


def _to(obj: Any, device: torch.device) -> Any:
    """``obj`` with every tensor in it (through dicts, lists and tuples) moved to ``device``."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: _to(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to(v, device) for v in obj)
    return obj


def _read(path: str | Path) -> dict[str, Any]:
    """The checkpoint's dict, every tensor on the CPU."""
    try:
        return torch.load(Path(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's message suggests weights_only=False: never do that for a file that holds
        # pickled code; only our own plain-tensor checkpoints are accepted.
        raise ValueError(f"cannot read checkpoint {path}: refused, it holds pickled objects other than tensors, "
                         "so it was not written by splat_train and is not loaded. Delete it to resume "
                         "from an older one or start again") from exc
    except Exception as exc:  # torch raises several types for a damaged file
        raise ValueError(f"cannot read checkpoint {path}: {exc}; delete it to resume from an "
                         "older one or start again") from exc
