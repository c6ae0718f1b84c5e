"""Seeded random LPIPS-Alex weights written as a weights file, so that tests need no download."""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors.torch import save_file

from imgmetrics.lpips import LPIPS, WEIGHTS_FORMAT


def random_alex_weights(folder: Path) -> Path:
    """``folder/alex.safetensors`` with seeded random weights and non-negative heads (like the
    trained ones); returns ``folder``."""
    torch.manual_seed(0)
    m = LPIPS("alex")
    with torch.no_grad():
        for lin in m.lins:
            lin.weight.abs_()
    folder.mkdir(parents=True, exist_ok=True)
    save_file(m.state_dict(), str(folder / "alex.safetensors"), metadata={"format": WEIGHTS_FORMAT, "net": "alex"})
    return folder
