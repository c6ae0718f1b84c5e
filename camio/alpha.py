"""Accumulated-opacity images beside renders: ``<renders>/alpha/<stem>.png``.

A render's accumulated opacity (``1 - final transmittance``, [H, W] in [0, 1]) is kept as a
16-bit single-channel PNG, value ``round(alpha * 65535)``, in the folder :data:`ALPHA_FOLDER`
inside the renders folder, under the render's own file name. :func:`camio.images.list_images`
does not descend into it, so every reader of the RGB renders sees the same files as before.
``python -m splat_train render --alpha`` (and ``testpose --alpha``) write it; ``python -m evaluation images
--alpha-dir`` reads it to score the covered pixels (:mod:`imgmetrics.covered`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camio.images import ImageReadError, read_pixels, write_image

__all__ = ["ALPHA_FOLDER", "alpha_path", "write_alpha", "read_alpha"]

#: the alpha images' folder inside a renders folder
ALPHA_FOLDER = "alpha"


def alpha_path(renders: str | Path, render_name: str) -> Path:
    """``renders/alpha/<stem>.png``: where the alpha of the render ``render_name`` is."""
    return Path(renders) / ALPHA_FOLDER / Path(render_name).with_suffix(".png").name


def write_alpha(path: str | Path, alpha: np.ndarray) -> Path:
    """Write an accumulated opacity [H, W] (float in [0, 1], clipped) as a 16-bit gray PNG,
    atomically (:func:`camio.images.write_image`)."""
    a = np.asarray(alpha, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"write_alpha: expected an [H, W] opacity, got shape {a.shape}")
    return write_image(path, a, bits=16)


def read_alpha(path: str | Path) -> np.ndarray:
    """An alpha image as float64 [H, W] in [0, 1] (16-bit: value / 65535; 8-bit: / 255).

    Raises:
        ImageReadError naming the file: missing, unreadable, or not a single-channel image.
    """
    data, spec = read_pixels(path, "float")
    if int(spec.nchannels) != 1:
        raise ImageReadError(f"alpha image {path} has {int(spec.nchannels)} channels, not 1; it is not an "
                             "accumulated-opacity image (write it with `python -m splat_train render`)")
    return np.asarray(data[..., 0], dtype=np.float64)
