"""The floor: a flat image of the training views' mean colour.

A model that learnt nothing but the mean colour of its training views renders this image at
every held-out view; a figure means something only above the score of this image. Its colour
is defined once, here, for every consumer (``python -m evaluation floor``, the sparse-view
benchmark's floor):

    colour = round(mean over training views of (each view's mean RGB))

from 8-bit images (code values 0..255, channel-last ``[H, W, 3]`` uint8), each view weighted
equally whatever its size, in float64, rounded half to even (``numpy.round``) to 0..255
integers. The flat image is that colour at every pixel, 8-bit, as a PNG render is.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

__all__ = ["flat_colour", "flat_image"]


def flat_colour(views: Iterable[np.ndarray]) -> np.ndarray:
    """The floor's colour from the training views.

    Args:
        views: 8-bit RGB images, each uint8 ``[H, W, 3]`` (sizes may differ).

    Returns:
        int64 ``[3]`` in 0..255: the rounded mean over views of each view's mean RGB.

    Raises:
        ValueError: no view, or a view that is not uint8 ``[H, W, 3]``.
    """
    means = []
    for i, v in enumerate(views):
        a = np.asarray(v)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or a.size == 0:
            raise ValueError(f"training view {i}: expected an 8-bit RGB image (uint8 [H, W, 3]), got "
                             f"{a.dtype} {list(a.shape)}; read it with camio.images.read_image_uint8")
        means.append(a.astype(np.float64).reshape(-1, 3).mean(0))
    if not means:
        raise ValueError("no training view: the floor's colour is the mean over the training views")
    return np.round(np.mean(means, axis=0)).astype(np.int64)


def flat_image(colour, height: int, width: int) -> np.ndarray:
    """The flat image: ``colour`` (three 0..255 integers) at every pixel, uint8 ``[H, W, 3]``."""
    c = np.asarray(colour)
    if c.shape != (3,) or not np.all((c >= 0) & (c <= 255)) or not np.all(c == np.round(c)):
        raise ValueError(f"the flat image's colour must be three integers in 0..255, got {c.tolist()}")
    if int(height) < 1 or int(width) < 1:
        raise ValueError(f"the flat image's size must be positive, got {width}x{height} (width x height)")
    return np.broadcast_to(c.astype(np.uint8), (int(height), int(width), 3)).copy()
