"""The largest image any stage reads: sizes from files are checked against it before allocating.

A camera's or image's width and height come from a file (COLMAP ``cameras.txt`` /
``cameras.bin``, ``transforms.json`` ``w`` / ``h``, a dataset's camera files, an image header)
and decide how much memory a stage allocates: a render, a float32 RGB image, a depth map. A
hostile or damaged file naming a 60000 x 45000 camera made the trainer try to allocate 43 GB
before it had read a pixel. Every reader calls :func:`check_image_size` first, with the file
it read the size from.

The limits are far above any camera the project works with (a 100-megapixel medium-format
photo is 11648 x 8736) and below what one image may cost: at :data:`MAX_PIXELS` a float32
RGB copy is 2.4 GB.
"""

from __future__ import annotations

__all__ = ["MAX_IMAGE_SIDE", "MAX_PIXELS", "check_image_size", "ImageSizeError"]

# The longest side, in pixels, of a camera or image that any stage reads.
MAX_IMAGE_SIDE = 32768
# The most pixels (width x height) of one camera or image.
MAX_PIXELS = 200_000_000


class ImageSizeError(ValueError):
    """A size read from a file is beyond :data:`MAX_IMAGE_SIDE` or :data:`MAX_PIXELS`."""


def check_image_size(width: int, height: int, where: str) -> tuple[int, int]:
    """(width, height) when both are within the limits.

    Args:
        width, height: the size read from ``where``, pixels.
        where: the file (and line or entry) it was read from, for the error.

    Raises:
        ImageSizeError: one line naming ``where``, the size and the limit that it is over.
    """
    if max(width, height) > MAX_IMAGE_SIDE:
        raise ImageSizeError(f"{where}: the image size {width}x{height} is over the limit of {MAX_IMAGE_SIDE} pixels "
                             "a side (camio.limits.MAX_IMAGE_SIDE); a damaged file, or downsample the images first")
    if width * height > MAX_PIXELS:
        raise ImageSizeError(f"{where}: the image size {width}x{height} ({width * height:,} pixels) is over the limit "
                             f"of {MAX_PIXELS:,} pixels (camio.limits.MAX_PIXELS); a damaged file, or downsample the "
                             "images first")
    return width, height
