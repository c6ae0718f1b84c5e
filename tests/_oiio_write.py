"""Test helper: write raw pixel arrays with OpenImageIO (any channel count and bit depth),
independently of camio's writers, so loaders are tested against files made another way."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_raw(path: Path, data: np.ndarray, fmt: str = "uint8") -> None:
    """Write [H, W] or [H, W, C] ``data`` as ``fmt`` (e.g. "uint8", "uint16"); C in 2 or 4
    is stored with unassociated (straight) alpha."""
    import OpenImageIO as oiio

    if data.ndim == 2:
        data = data[..., None]
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if c in (2, 4):
        spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data))
    out.close()
