"""Image loading identical to VGGT's ``load_and_preprocess_images`` ('crop' and 'pad'), without
Pillow or torchvision: OpenImageIO decodes, numpy does the rest bit-exactly.

Steps per image (reference behaviour, Pillow 13):
1. Decode to 8 bits as Pillow would present the file: 8-bit data as is; 16-bit RGB(A) by
   its high byte (Pillow's ``RGB;16B`` unpacker); 16-bit grayscale as Pillow's ``I;16`` ->
   RGB conversion, which saturates values above 255 (a warning is logged); float data is
   clipped to [0, 1] and rounded to 8 bits (Pillow cannot open it).
2. RGBA (and 16-bit gray+alpha, which Pillow opens as RGBA) is alpha-composited onto
   opaque white; 8-bit gray+alpha drops its alpha (Pillow's LA -> RGB); gray is replicated.
3. crop: width -> ``target``, height -> round(h * target / w / 14) * 14 (half to even),
   Pillow bicubic, centre-crop rows to ``target`` if taller. pad: the longer side ->
   ``target``, the other rounded the same way, then white padding (top = diff // 2).
4. A batch whose shapes differ is padded with white, centred, to the largest H and W.

:class:`ImageGeometry` records how original pixels map to network-input pixels, so
intrinsics can be carried back to the original resolution exactly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.logs import progress
from vggt_init.defaults import IMAGE_SIZE, MODE
from vggt_init.pillow_compat import alpha_composite_over, resize_bicubic

__all__ = [
    "ImageInputError",
    "ImageGeometry",
    "decode_like_pillow",
    "to_rgb8",
    "resized_size",
    "preprocess_rgb",
    "load_and_preprocess",
    "to_model_input",
]

log = logging.getLogger(__name__)

PATCH = 14


class ImageInputError(ValueError):
    """An input image that cannot be used (unreadable, too small, odd layout)."""


@dataclass
class ImageGeometry:
    """How one original image maps into the network input.

    Network pixel coordinates (continuous, pixel centres at +0.5) relate to original ones by
    ``u_net = scale_x * u + offset_x``, ``v_net = scale_y * v + offset_y``, with
    scale = resized / original size and offset = padding (positive) or crop (negative).

    Attributes:
        name: file name.
        width, height: original size in pixels.
        resized_w, resized_h: size after the bicubic resize.
        offset_x, offset_y: position of the resized image's top-left corner in the input.
        input_w, input_h: network input size (after crop / padding / batch padding).
    """

    name: str
    width: int
    height: int
    resized_w: int
    resized_h: int
    offset_x: int
    offset_y: int
    input_w: int
    input_h: int

    @property
    def scale_x(self) -> float:
        return self.resized_w / self.width

    @property
    def scale_y(self) -> float:
        return self.resized_h / self.height

    def intrinsics_to_original(self, K_net: np.ndarray) -> np.ndarray:
        """K [3,3] in network-input pixels -> K [3,3] float64 in original-image pixels."""
        K = np.asarray(K_net, dtype=np.float64)
        out = np.eye(3)
        out[0, 0] = K[0, 0] / self.scale_x
        out[1, 1] = K[1, 1] / self.scale_y
        out[0, 1] = K[0, 1] / self.scale_x
        out[0, 2] = (K[0, 2] - self.offset_x) / self.scale_x
        out[1, 2] = (K[1, 2] - self.offset_y) / self.scale_y
        return out

    def valid_mask(self) -> np.ndarray:
        """[input_h, input_w] bool: network pixels that show the image (not padding)."""
        m = np.zeros((self.input_h, self.input_w), dtype=bool)
        y0, x0 = max(self.offset_y, 0), max(self.offset_x, 0)
        y1 = min(self.offset_y + self.resized_h, self.input_h)
        x1 = min(self.offset_x + self.resized_w, self.input_w)
        m[y0:y1, x0:x1] = True
        return m


def _read_native(path: Path) -> np.ndarray:
    """[h, w, c] array in the file's own type (uint8/uint16/float), straight alpha.

    Decoded by :func:`camio.images.read_pixels`, the checked reader every stage shares, so a
    truncated or corrupt file is an error naming it here too (not grey pixels).
    """
    import OpenImageIO as oiio

    from camio.images import ImageReadError, _open, read_pixels

    try:
        inp = _open(path)
        try:
            fmt = inp.spec().format.basetype
        finally:
            inp.close()
        if fmt == oiio.UINT8:
            req = "uint8"
        elif fmt in (oiio.UINT16, oiio.INT16):
            req = "uint16"
        else:
            req = "float"
        data, _ = read_pixels(path, req)
    except ImageReadError as exc:
        raise ImageInputError(str(exc)) from None
    return data


def decode_like_pillow(path: str | Path) -> tuple[np.ndarray, str]:
    """Decode to the uint8 array Pillow would hold, and its mode ('L', 'LA', 'RGB', 'RGBA').

    Returns:
        ([h, w, 1|2|3|4] uint8, mode). See the module docstring for the 16-bit rules.
    """
    path = Path(path)
    raw = _read_native(path)
    c = raw.shape[2]
    if c not in (1, 2, 3, 4):
        raise ImageInputError(f"image {path} has {c} channels; expected gray, gray+alpha, RGB or RGBA")
    if raw.dtype == np.uint8:
        data = raw
    elif raw.dtype == np.uint16:
        if c == 1:
            if raw.max(initial=0) > 255:
                log.warning("%s is 16-bit grayscale: like Pillow (I;16 -> RGB), values above 255 "
                            "saturate to white; convert it to 8 bits first for a usable input", path.name)
            data = np.minimum(raw, 255).astype(np.uint8)
        else:
            data = (raw >> 8).astype(np.uint8)  # Pillow's RGB;16B / RGBA;16B / LA;16B unpackers
            if c == 2:  # Pillow opens 16-bit gray+alpha as RGBA
                data = np.concatenate([data[..., :1]] * 3 + [data[..., 1:]], axis=-1)
                c = 4
    else:
        log.warning("%s holds %s samples: clipped to [0, 1] and rounded to 8 bits", path.name, raw.dtype)
        data = np.round(np.clip(np.nan_to_num(raw.astype(np.float64)), 0.0, 1.0) * 255.0).astype(np.uint8)
    mode = {1: "L", 2: "LA", 3: "RGB", 4: "RGBA"}[c]
    return np.ascontiguousarray(data), mode


def to_rgb8(data: np.ndarray, mode: str) -> np.ndarray:
    """Pillow-decoded [h, w, c] uint8 -> [h, w, 3] uint8 RGB (RGBA composited onto white)."""
    if mode == "RGBA":
        return alpha_composite_over(data)[..., :3].copy()
    if mode in ("L", "LA"):
        return np.repeat(data[..., :1], 3, axis=-1)
    return data[..., :3].copy()


def resized_size(width: int, height: int, mode: str, target: int = IMAGE_SIZE) -> tuple[int, int]:
    """(new_w, new_h) of the bicubic resize, with the reference's round-half-to-even."""
    if mode == "crop":
        return target, round(height * (target / width) / PATCH) * PATCH
    if mode == "pad":
        if width >= height:
            return target, round(height * (target / width) / PATCH) * PATCH
        return round(width * (target / height) / PATCH) * PATCH, target
    raise ValueError(f"unknown preprocessing mode {mode!r}; use 'crop' or 'pad'")


def preprocess_rgb(rgb: np.ndarray, name: str, mode: str = MODE, target: int = IMAGE_SIZE
                   ) -> tuple[np.ndarray, ImageGeometry]:
    """One RGB image -> (network image [H, W, 3] uint8, geometry) before batch padding."""
    if target % PATCH or target < PATCH:
        raise ValueError(f"target size {target} must be a positive multiple of {PATCH}")
    h, w = rgb.shape[:2]
    if h < PATCH or w < PATCH:
        raise ImageInputError(f"image {name} is {w}x{h} px, smaller than one {PATCH} px patch; "
                              "use images at least 14 px on each side")
    new_w, new_h = resized_size(w, h, mode, target)
    if new_w < PATCH or new_h < PATCH:
        raise ImageInputError(f"image {name} ({w}x{h}) is too elongated: it would be resized to "
                              f"{new_w}x{new_h}, less than one {PATCH} px patch; crop it first")
    img = resize_bicubic(rgb, new_w, new_h)
    off_x = off_y = 0
    if mode == "crop" and new_h > target:
        start = (new_h - target) // 2
        img = img[start:start + target]
        off_y = -start
    if mode == "pad":
        img, (dy, dx) = _pad_white(img, target, target)
        off_x, off_y = dx, dy
    geo = ImageGeometry(name, w, h, new_w, new_h, off_x, off_y, img.shape[1], img.shape[0])
    return img, geo


def _pad_white(img: np.ndarray, H: int, W: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Centre ``img`` [h, w, 3] in a white [H, W, 3] canvas; returns it and (top, left)."""
    h, w = img.shape[:2]
    top, left = max(H - h, 0) // 2, max(W - w, 0) // 2
    if (h, w) == (H, W):
        return img, (0, 0)
    out = np.full((H, W, 3), 255, dtype=np.uint8)
    out[top:top + h, left:left + w] = img
    return out, (top, left)


def load_and_preprocess(paths: list[str | Path], mode: str = MODE, target: int = IMAGE_SIZE
                        ) -> tuple[np.ndarray, list[ImageGeometry]]:
    """Load images as VGGT's reference loader does.

    Args:
        paths: image files (any format OpenImageIO reads).
        mode: 'crop' or 'pad'.
        target: the network width (crop) or longer side (pad), a multiple of 14.

    Returns:
        images [S, H, W, 3] uint8 (network input; divide by 255 for the model) and one
        :class:`ImageGeometry` per image.
    """
    if not paths:
        raise ImageInputError("no images given")
    imgs, geos = [], []
    for p in progress(paths, total=len(paths), desc="preprocess"):
        p = Path(p)
        data, pmode = decode_like_pillow(p)
        img, geo = preprocess_rgb(to_rgb8(data, pmode), p.name, mode, target)
        imgs.append(img)
        geos.append(geo)
    H = max(i.shape[0] for i in imgs)
    W = max(i.shape[1] for i in imgs)
    if any(i.shape[:2] != (H, W) for i in imgs):
        log.warning("images have different shapes after preprocessing; padding all to %dx%d with white", W, H)
        for k, img in enumerate(imgs):
            imgs[k], (dy, dx) = _pad_white(img, H, W)
            g = geos[k]
            g.offset_x += dx
            g.offset_y += dy
            g.input_w, g.input_h = W, H
    return np.stack(imgs), geos


def to_model_input(images: np.ndarray):
    """[S, H, W, 3] uint8 -> torch float32 [S, 3, H, W] = uint8 / 255 (as ToTensor)."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(images.transpose(0, 3, 1, 2))).float().div_(255.0)
