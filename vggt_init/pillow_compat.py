"""Bit-exact numpy reimplementations of the two Pillow operations VGGT's loader uses.

* :func:`resize_bicubic` = ``Image.resize((w, h), Image.BICUBIC)`` on 8-bit images
  (Pillow 13's libImaging/Resample.c): separable, two passes each clipped to 8 bits,
  horizontal first unless the height shrinks by more than twice as many pixels as the
  width (then vertical first; Pillow before 13 always went horizontal first); cubic kernel a = -0.5 with support 2 scaled by the
  downscale factor; coefficients normalised to sum 1 in double precision, converted to
  fixed point with PRECISION_BITS = 22 (rounded half away from zero), accumulated in
  integers from 2^21 and shifted right by 22, clipped to [0, 255].
* :func:`alpha_composite_over` = ``Image.alpha_composite(background, image)`` for RGBA
  (libImaging/AlphaComposite.c, 7 extra bits of precision, rounded divisions by 255).

Both are checked against the fixtures' Pillow output and, in the tests, against Pillow
itself on random images when it is installed. Pillow is not needed at run time.
"""

from __future__ import annotations

import numpy as np

__all__ = ["resize_bicubic", "alpha_composite_over", "bicubic_coefficients"]

_PRECISION_BITS = 32 - 8 - 2
_CHUNK_ELEMS = 1 << 23  # bound the int64 temporaries of one pass (~64 MB)


def _bicubic(x: np.ndarray) -> np.ndarray:
    """Pillow's cubic convolution kernel with a = -0.5, evaluated in the C order."""
    a = -0.5
    x = np.abs(x)
    inner = ((a + 2.0) * x - (a + 3.0)) * x * x + 1
    outer = (((x - 5) * x + 8) * x - 4) * a
    return np.where(x < 1.0, inner, np.where(x < 2.0, outer, 0.0))


def bicubic_coefficients(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed-point filter taps for one axis (Pillow's precompute_coeffs + normalize_coeffs_8bpc).

    Returns:
        xmin [out] first input index, count [out] number of taps used,
        k [out, ksize] int64 fixed-point coefficients (zero beyond ``count``).
    """
    scale = float(in_size) / out_size
    filterscale = max(scale, 1.0)
    support = 2.0 * filterscale
    ksize = int(np.ceil(support)) * 2 + 1
    center = (np.arange(out_size) + 0.5) * scale
    # C casts with truncation toward zero; values below zero are clamped to 0 anyway.
    xmin = np.trunc(center - support + 0.5).astype(np.int64)
    xmin = np.maximum(xmin, 0)
    xmax = np.minimum(np.trunc(center + support + 0.5).astype(np.int64), in_size)
    count = xmax - xmin
    taps = np.arange(ksize)
    arg = ((taps[None, :] + xmin[:, None]) - center[:, None] + 0.5) * (1.0 / filterscale)
    w = np.where(taps[None, :] < count[:, None], _bicubic(arg), 0.0)
    ww = np.zeros(out_size)
    for x in range(ksize):  # sequential sum, as the C loop
        ww = ww + w[:, x]
    w = np.where(ww[:, None] != 0.0, w / np.where(ww == 0.0, 1.0, ww)[:, None], w)
    scaled = w * float(1 << _PRECISION_BITS)
    k = np.where(w < 0, np.trunc(-0.5 + scaled), np.trunc(0.5 + scaled)).astype(np.int64)
    return xmin, count, k


def _resample_axis(img: np.ndarray, out_size: int, axis: int, row_range: tuple[int, int] | None = None) -> np.ndarray:
    """One 8-bit pass along ``axis`` (0 rows / 1 columns) of img [H, W, C] uint8."""
    in_size = img.shape[axis]
    xmin, count, k = bicubic_coefficients(in_size, out_size)
    ksize = k.shape[1]
    idx = np.minimum(xmin[:, None] + np.arange(ksize)[None, :], in_size - 1)  # k == 0 where clamped
    if axis == 1:
        H, C = img.shape[0], img.shape[2]
        out = np.empty((H, out_size, C), dtype=np.uint8)
        step = max(1, _CHUNK_ELEMS // max(1, out_size * ksize * C))
        for r0 in range(0, H, step):
            g = img[r0:r0 + step][:, idx, :].astype(np.int64)  # [h, out, ksize, C]
            acc = (g * k[None, :, :, None]).sum(axis=2) + (1 << (_PRECISION_BITS - 1))
            out[r0:r0 + step] = np.clip(acc >> _PRECISION_BITS, 0, 255)
        return out
    W, C = img.shape[1], img.shape[2]
    out = np.empty((out_size, W, C), dtype=np.uint8)
    step = max(1, _CHUNK_ELEMS // max(1, W * ksize * C))
    for r0 in range(0, out_size, step):
        sl = slice(r0, r0 + step)
        g = img[idx[sl]].astype(np.int64)  # [rows, ksize, W, C]
        acc = (g * k[sl][:, :, None, None]).sum(axis=1) + (1 << (_PRECISION_BITS - 1))
        out[sl] = np.clip(acc >> _PRECISION_BITS, 0, 255)
    return out


def resize_bicubic(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pillow-exact bicubic resize of an 8-bit image.

    Args:
        img: [H, W, C] (or [H, W]) uint8.
        width, height: output size in pixels (>= 1).

    Returns:
        [height, width, C] (or [height, width]) uint8.
    """
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise ValueError(f"resize_bicubic needs uint8 input, got {img.dtype}")
    if width < 1 or height < 1:
        raise ValueError(f"resize_bicubic: output size must be positive, got {width}x{height}")
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    H, W = img.shape[:2]
    need_h, need_v = width != W, height != H
    # Pillow 13: if the height shrinks by more than twice the width's shrink (in pixels),
    # the vertical pass runs first; otherwise horizontal first, on only the rows the
    # vertical pass reads (the values are the same either way for those rows).
    horizontal_first = not ((H - height) > 0 and (H - height) > (W - width) * 2)
    out = img
    if horizontal_first:
        if need_h:
            if need_v:
                ymin, ycount, _ = bicubic_coefficients(H, height)
                y0, y1 = int(ymin[0]), int(ymin[-1] + ycount[-1])
            else:
                y0, y1 = 0, H
            out = np.zeros((H, width, img.shape[2]), dtype=np.uint8)
            out[y0:y1] = _resample_axis(img[y0:y1], width, axis=1)
        if need_v:
            out = _resample_axis(out, height, axis=0)
    else:
        out = _resample_axis(out, height, axis=0)
        if need_h:
            out = _resample_axis(out, width, axis=1)
    return out[..., 0] if squeeze else out


def alpha_composite_over(rgba: np.ndarray, background: tuple[int, int, int, int] = (255, 255, 255, 255)) -> np.ndarray:
    """Pillow's ``alpha_composite(Image.new('RGBA', size, background), image)``.

    Args:
        rgba: [H, W, 4] uint8 straight (unassociated) alpha.
        background: opaque-or-not RGBA uint8 colour under the image.

    Returns:
        [H, W, 4] uint8 composite.
    """
    src = np.asarray(rgba).astype(np.int64)
    if src.ndim != 3 or src.shape[2] != 4:
        raise ValueError(f"alpha_composite_over needs [H, W, 4], got {src.shape}")
    dst = np.broadcast_to(np.asarray(background, dtype=np.int64), src.shape)
    pb = 7
    sa, da = src[..., 3], dst[..., 3]
    blend = da * (255 - sa)
    outa255 = sa * 255 + blend
    safe = np.where(outa255 == 0, 1, outa255)
    coef1 = sa * 255 * 255 * (1 << pb) // safe
    coef2 = 255 * (1 << pb) - coef1

    def div255(v):
        return ((v >> 8) + v) >> 8

    out = np.empty(src.shape, dtype=np.uint8)
    for c in range(3):
        tmp = src[..., c] * coef1 + dst[..., c] * coef2
        out[..., c] = div255(tmp + (0x80 << pb)) >> pb
    out[..., 3] = div255(outa255 + 0x80)
    transparent = sa == 0
    out[transparent] = dst[transparent].astype(np.uint8)
    return out
