"""Image files through OpenImageIO: reading, writing and area downsampling (by an integer
factor, or to a size: a photo folder's working resolution).

Reading (:func:`read_image`) always returns float32 RGB in [0, 1], shape [H, W, 3], in the
image's *display* orientation:

* 8- and 16-bit integer files (PNG, JPEG, TIFF, ...) are scaled by 1/255 or 1/65535; the
  stored (sRGB-encoded) values are kept, no colour-space conversion is applied.
* Float files (EXR, float TIFF) keep their stored linear values (no tone mapping, no sRGB
  encoding) and are clipped to [0, 1]; NaN becomes 0. A debug message reports clipping.
* Grayscale is repeated to RGB. An alpha channel is composited over ``background``
  (``rgb * a + background * (1 - a)`` for straight alpha; associated alpha, as in EXR, is
  composited as ``rgb + background * (1 - a)``).
* The EXIF/TIFF ``Orientation`` tag (1..8) is applied explicitly by :func:`apply_orientation`
  (OpenImageIO reports it but does not apply it).

Unreadable, truncated or missing files raise :class:`ImageReadError` naming the file.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_path
from runtime.checks import check_folder
from runtime.stops import stops_held

__all__ = [
    "IMAGE_EXTENSIONS",
    "MIN_IMAGE_SIDE",
    "ImageReadError",
    "ImageNameError",
    "check_image_name",
    "read_image",
    "read_image_uint8",
    "from_uint8",
    "read_pixels",
    "check_images",
    "write_image",
    "image_size",
    "apply_orientation",
    "exif_orientation",
    "describe_orientation",
    "downsample_area",
    "downsample_folder",
    "resize_area",
    "working_size",
    "list_images",
]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")

#: images with a shorter side give SIFT nothing to find (COLMAP then reports only "no initial pair")
MIN_IMAGE_SIDE = 16


class ImageReadError(OSError):
    """An image file that is missing, unreadable, truncated or has an unusable layout."""


class ImageNameError(ValueError):
    """An image name that the COLMAP text format cannot hold."""


def check_image_name(name: str, folder: str | Path | None = None) -> str:
    """Refuse an image name with whitespace where it enters the pipeline.

    COLMAP's text reader (``ReadImagesText``) takes the NAME field with
    ``std::getline(line_stream, item, ' ')``: everything after the first space is lost, so
    ``my vue 1.png`` comes back as ``my`` and different images collapse into one name. The
    pipeline writes and reads text models, so such a name is refused when it enters.

    Returns:
        ``name`` unchanged.

    Raises:
        ImageNameError: one line naming the file and a suggested rename.
    """
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # bytes that are not UTF-8 (os.fsdecode keeps them as surrogates)
        path = Path(folder) / name if folder is not None else Path(name)
        shown = os.fsencode(name).decode("utf-8", errors="replace")
        raise ImageNameError(f"image {str(path)!r}: the name is not UTF-8 text ({shown!r}), which COLMAP models, "
                             "JSON and the image readers cannot hold; rename the file with UTF-8 "
                             "characters") from None
    if any(ch.isspace() for ch in name):
        path = Path(folder) / name if folder is not None else Path(name)
        suggest = "_".join(name.split())
        raise ImageNameError(f"image {path}: the name contains whitespace, which a COLMAP text model cannot "
                             f"hold (COLMAP reads a name only up to the first space); rename the file, e.g. "
                             f"to {suggest!r}")
    return name


def list_images(folder: str | Path) -> list[str]:
    """Sorted file names (not paths) of the images directly in ``folder``.

    Hidden files (leading '.') are skipped; the extension test is case-insensitive. A name
    with whitespace is refused (:func:`check_image_name`).
    """
    folder = Path(folder)
    check_folder(folder, "image folder")
    return sorted(
        check_image_name(p.name, folder) for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS
    )


def _check_size(spec, path: Path) -> tuple[int, int]:
    """(width, height) of an image's header, within camio.limits' bounds (checked before any
    pixel is read); ImageReadError naming the file, the size and the limit otherwise."""
    from camio.limits import ImageSizeError, check_image_size

    try:
        return check_image_size(int(spec.width), int(spec.height), f"image {path}")
    except ImageSizeError as exc:
        raise ImageReadError(str(exc)) from None


def _open(path: Path):
    import OpenImageIO as oiio

    if not path.is_file():
        raise ImageReadError(f"image {path} does not exist")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # give straight alpha where the file has it
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ImageReadError(f"cannot open image {path}: {oiio.geterror() or 'unknown format'}; "
                             "check that the file is a complete PNG/JPEG/TIFF/EXR")
    return inp


def read_pixels(path: str | Path, fmt: str = "float"):
    """The whole pixel array of ``path`` as stored, checked: the one decoder every stage uses.

    Args:
        path: image file.
        fmt: "float", "uint8" or "uint16" (the type OpenImageIO converts the pixels to).

    Returns:
        (pixels [H, W, C] numpy array, OpenImageIO ImageSpec of the file).

    Raises:
        ImageReadError naming the file: missing, not an image, truncated or corrupt (a JPEG
        or PNG cut short decodes to partly grey pixels in OpenImageIO *with* an error flag;
        that flag, not only a missing result, makes the file unusable here).
    """
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        _check_size(spec, path)
        data = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        err = inp.geterror() if inp.has_error else ""
    finally:
        inp.close()
    if data is None or err:
        raise ImageReadError(f"cannot read image {path}: {(err or 'no pixel data').strip()} "
                             "(truncated or corrupt file? re-export or remove it)")
    data = np.asarray(data)
    if data.ndim == 2:
        data = data[..., None]
    return data.reshape(int(spec.height), int(spec.width), int(spec.nchannels)), spec


def check_images(paths) -> None:
    """Decode every file of ``paths`` fully; raise :class:`ImageReadError` at the first bad one.

    Stages that hand image files to another program (pycolmap) call this first, so that the
    other program only ever sees files :func:`read_image` accepts.
    """
    for path in paths:
        read_pixels(path, "uint8")


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of the image as displayed (after orientation), header only."""
    inp = _open(Path(path))
    try:
        spec = inp.spec()
        w, h = _check_size(spec, path)
        o = int(spec.get_int_attribute("Orientation", 1))
    finally:
        inp.close()
    return (h, w) if o in (5, 6, 7, 8) else (w, h)


def exif_orientation(path: str | Path) -> int:
    """The EXIF/TIFF ``Orientation`` of ``path`` (1..8; 1 where the file has none or an invalid
    one), header only: what :func:`read_image` applies."""
    inp = _open(Path(path))
    try:
        o = int(inp.spec().get_int_attribute("Orientation", 1))
    finally:
        inp.close()
    return o if 1 <= o <= 8 else 1


#: what :func:`apply_orientation` does to a stored image, for the log
ORIENTATION_WORDS = {1: "as stored", 2: "mirrored left-right", 3: "turned 180 degrees",
                     4: "mirrored top-bottom", 5: "transposed", 6: "turned 90 degrees clockwise",
                     7: "transversed", 8: "turned 90 degrees counter-clockwise"}


def describe_orientation(folder: str | Path, names: list[str]) -> str | None:
    """One line naming the images of ``names`` that :func:`read_image` turns upright from their
    EXIF orientation (None: every one is stored upright)."""
    turned = [(n, o) for n in names if (o := exif_orientation(Path(folder) / n)) != 1]
    if not turned:
        return None
    shown = ", ".join(f"{n} ({ORIENTATION_WORDS[o]})" for n, o in turned[:6])
    more = f" and {len(turned) - 6} more" if len(turned) > 6 else ""
    return f"EXIF orientation applied: {len(turned)} of {len(names)} image(s) turned upright: {shown}{more}"


def apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Turn a stored image into its display orientation (EXIF semantics).

    Args:
        img: [H, W, C] (or [H, W]) array as stored in the file.
        orientation: EXIF Orientation 1..8 (1 = as stored, 3 = rotate 180, 6 = rotate 90
            clockwise to display, 8 = rotate 90 counter-clockwise; 2, 4, 5, 7 mirror).

    Returns:
        The displayed image, [H', W', C]; H' and W' are swapped for 5..8.
    """
    o = int(orientation)
    if o == 1:
        return img
    if o == 2:
        out = img[:, ::-1]
    elif o == 3:
        out = img[::-1, ::-1]
    elif o == 4:
        out = img[::-1, :]
    elif o == 5:
        out = np.swapaxes(img, 0, 1)
    elif o == 6:
        out = np.rot90(img, k=-1)
    elif o == 7:
        out = np.swapaxes(img, 0, 1)[::-1, ::-1]
    elif o == 8:
        out = np.rot90(img, k=1)
    else:
        raise ValueError(f"EXIF orientation must be 1..8, got {orientation}")
    return np.ascontiguousarray(out)


def read_image(path: str | Path, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1], shape [H, W, 3], display orientation.

    Args:
        path: PNG / JPEG / TIFF / EXR file (anything OpenImageIO reads).
        background: RGB in [0, 1] under transparent pixels (alpha images only).

    Raises:
        ImageReadError: missing, unreadable or truncated file, or an unsupported channel count.
    """
    path = Path(path)
    data, spec = read_pixels(path, "float")
    orientation = int(spec.get_int_attribute("Orientation", 1))
    alpha_ch = int(spec.alpha_channel)
    unassociated = bool(spec.get_int_attribute("oiio:UnassociatedAlpha", 0))
    is_float = spec.format.basetype in (_float_types())
    nch = int(spec.nchannels)
    img = np.asarray(data, dtype=np.float32)
    if nch in (2, 4) and alpha_ch < 0:
        alpha_ch = nch - 1
    if nch == 1:
        rgb, alpha = np.repeat(img, 3, axis=2), None
    elif nch == 2:
        rgb, alpha = np.repeat(img[..., :1], 3, axis=2), img[..., alpha_ch:alpha_ch + 1]
    elif nch == 3:
        rgb, alpha = img, None
    elif nch == 4:
        rgb, alpha = img[..., :3], img[..., alpha_ch:alpha_ch + 1]
    else:
        raise ImageReadError(f"image {path} has {nch} channels; expected 1 (gray), 2 (gray+alpha), "
                             "3 (RGB) or 4 (RGBA)")
    if is_float:
        bad = ~np.isfinite(rgb)
        if bad.any():
            rgb = np.where(bad, 0.0, rgb)
        if rgb.min() < 0 or rgb.max() > 1:
            log.debug("%s: float values outside [0, 1] (%.3g..%.3g) clipped", path, rgb.min(), rgb.max())
    if alpha is not None:
        a = np.clip(np.nan_to_num(alpha), 0.0, 1.0)
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        rgb = (rgb * a if unassociated else rgb) + bg * (1.0 - a)
    rgb = np.clip(rgb, 0.0, 1.0).astype(np.float32, copy=False)
    return apply_orientation(rgb, orientation if 1 <= orientation <= 8 else 1)


def _float_types():
    import OpenImageIO as oiio

    return (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)


def read_image_uint8(path: str | Path, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """:func:`read_image` rounded to uint8 [H, W, 3] (exact for 8-bit RGB files)."""
    return to_uint8(read_image(path, background))


def from_uint8(img: np.ndarray) -> np.ndarray:
    """uint8 [..] -> float32 in [0, 1]: exactly what :func:`read_image` returns for an 8-bit file
    of these values (OpenImageIO scales by the float32 reciprocal of 255, which differs from a
    division by 255 in the last bit for some codes)."""
    a = np.asarray(img)
    if a.dtype != np.uint8:
        raise ValueError(f"from_uint8 takes uint8 values, got {a.dtype}")
    return a.astype(np.float32) * np.float32(1.0 / 255.0)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float [.., 3] in [0, 1] -> uint8 by rounding (clipped); uint8 input is returned as is."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a
    return np.round(np.clip(a.astype(np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


def write_image(path: str | Path, img: np.ndarray, bits: int = 8, jpeg_quality: int = 95) -> Path:
    """Write an RGB (or gray) image atomically; the format follows the file extension.

    Args:
        path: output file (.png default choice; .jpg/.tif/.exr also work).
        img: [H, W, 3] or [H, W] float in [0, 1] (clipped) or uint8.
        bits: 8 or 16 for integer formats (16-bit only for PNG/TIFF); ignored for EXR (half).
        jpeg_quality: JPEG quality 1..100.
    """
    import OpenImageIO as oiio

    path = Path(path)
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"write_image: expected [H, W, 3] or [H, W], got shape {np.shape(img)}")
    ext = path.suffix.lower()
    if ext == ".exr":
        data, fmt = (a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)), "half"
    elif bits == 16:
        if ext not in (".png", ".tif", ".tiff"):
            raise ValueError(f"write_image: 16-bit output needs .png or .tif, not {ext}")
        f = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else np.clip(a.astype(np.float32), 0, 1)
        data, fmt = np.round(f * 65535.0).astype(np.uint16), "uint16"
    elif bits == 8:
        data, fmt = to_uint8(a), "uint8"
    else:
        raise ValueError(f"write_image: bits must be 8 or 16, got {bits}")
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if ext in (".jpg", ".jpeg"):
        spec.attribute("Compression", f"jpeg:{int(jpeg_quality)}")
    with atomic_path(path) as tmp:
        # one image is written whole before a stop acts: a stop between open and close left
        # the codec half-way, and libpng printed "No IDATs written into file" on the way out
        with stops_held():
            out = oiio.ImageOutput.create(str(tmp))
            if out is None:
                raise OSError(f"write_image: no writer for {path}: {oiio.geterror()}")
            ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(data))
            err = out.geterror() if not ok else ""
            out.close()
        if not ok:
            raise OSError(f"write_image: cannot write {path}: {err}")
    return path


def downsample_area(img: np.ndarray, factor: int) -> np.ndarray:
    """Integer area (box) downsampling: each output pixel is the mean of a factor x factor block.

    The remainder rows/columns (H % factor at the bottom, W % factor at the right) are cropped
    first, so the output is [H // factor, W // factor, C] and continuous pixel coordinates
    scale exactly: ``u_new = u_old / factor`` (intrinsics scale by 1/factor, see
    :func:`camio.cameras.scale_intrinsics`). This is how ``images_8`` folders are made
    (LLFF minifies by 1/8 with an area filter).

    Args:
        img: [H, W, C] or [H, W], float or uint8.
        factor: integer >= 1.

    Returns:
        float32 [H // f, W // f, C] (uint8 input -> uint8 output, rounded).
    """
    if int(factor) != factor or factor < 1:
        raise ValueError(f"downsample factor must be a positive integer, got {factor}")
    f = int(factor)
    a = np.asarray(img)
    if f == 1:
        return a.copy()
    h, w = a.shape[0] // f, a.shape[1] // f
    if h == 0 or w == 0:
        raise ValueError(f"image of {a.shape[1]}x{a.shape[0]} is smaller than the factor {f}")
    crop = a[: h * f, : w * f].astype(np.float64)
    out = crop.reshape(h, f, w, f, *a.shape[2:]).mean(axis=(1, 3))
    if a.dtype == np.uint8:
        return np.round(out).astype(np.uint8)
    return out.astype(np.float32)


def working_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """(width, height) with the long side at most ``max_size``, aspect kept (never enlarged;
    ``max_size`` 0 = unchanged)."""
    if max_size < 0:
        raise ValueError(f"max_size must be 0 (full resolution) or a positive number of pixels, got {max_size}")
    f = 1.0 if max_size == 0 else min(1.0, max_size / max(width, height))
    return max(1, round(width * f)), max(1, round(height * f))


def _area_axis(a: np.ndarray, n_out: int, axis: int) -> np.ndarray:
    """Box-filter ``a`` (float64) along ``axis`` to ``n_out`` samples: each output sample is the
    mean of the input over its interval, fractional pixels weighted by the part covered."""
    n_in = a.shape[axis]
    if n_out == n_in:
        return a
    step = n_in / n_out
    edges = np.arange(n_out + 1) * step
    i = np.minimum(np.floor(edges).astype(np.int64), n_in - 1)
    frac = (edges - i).reshape([-1 if d == axis else 1 for d in range(a.ndim)])
    csum = np.concatenate([np.zeros_like(np.take(a, [0], axis)), np.cumsum(a, axis=axis)], axis=axis)
    area = np.take(csum, i, axis) + frac * np.take(a, i, axis)  # the sum of the input up to each edge
    return np.diff(area, axis=axis) / step


def resize_area(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area (box) downsampling to any smaller ``size`` = (width, height): each output pixel is
    the mean of the input pixels it covers, partly covered ones weighted by the part covered
    (antialiased; :func:`downsample_area` for an integer factor that divides the size).
    Continuous pixel coordinates scale by ``width / W`` and ``height / H``.

    Args:
        img: [H, W, C] or [H, W], float or uint8.
        size: (width, height), each at most the input's.

    Returns:
        float32 [height, width, C] (uint8 input -> uint8 output, rounded).
    """
    a = np.asarray(img)
    w, h = int(size[0]), int(size[1])
    if not (1 <= w <= a.shape[1] and 1 <= h <= a.shape[0]):
        raise ValueError(f"resize_area downsamples only: {a.shape[1]}x{a.shape[0]} -> {w}x{h}")
    chans = a[..., None] if a.ndim == 2 else a
    out = np.empty((h, w, chans.shape[2]), np.float64)
    for c in range(chans.shape[2]):  # one channel at a time: float64 sums of a 12 MP photo stay small
        out[..., c] = _area_axis(_area_axis(chans[..., c].astype(np.float64), h, 0), w, 1)
    out = out[..., 0] if a.ndim == 2 else out
    if a.dtype == np.uint8:
        return np.round(out).clip(0, 255).astype(np.uint8)
    return out.astype(np.float32)


def downsample_folder(
    src: str | Path,
    dst: str | Path,
    factor: int,
    names: list[str] | None = None,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    max_size: int = 0,
) -> dict[str, tuple[int, int]]:
    """Read every image of ``src``, downsample by ``factor`` and write it into ``dst``.

    With ``max_size`` > 0 an image whose long side is then still longer is area-resized to
    :func:`working_size` (:func:`resize_area`). Each output keeps its file name (JPEG stays
    JPEG at quality 95, 16-bit stays 16-bit). An 8-bit RGB file with orientation 1 that needs no
    downsampling is copied byte for byte; anything else is decoded (orientation applied, alpha
    composited) and re-encoded. Files are written atomically one by one; on an error nothing
    from this call is left in ``dst``.

    Returns:
        name -> (width, height) written.
    """
    from runtime.logs import progress

    src, dst = Path(src), Path(dst)
    names = list_images(src) if names is None else list(names)
    if not names:
        raise FileNotFoundError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {src}")
    dst.mkdir(parents=True, exist_ok=True)
    sizes: dict[str, tuple[int, int]] = {}
    written: list[Path] = []
    desc = f"downsample x{factor}" + (f", long side <= {max_size}" if max_size else "")
    try:
        for name in progress(names, desc=desc):
            sp, dp = src / name, dst / name
            bits = _bit_depth(sp)
            w, h = image_size(sp)
            target = working_size(w // factor, h // factor, max_size)
            if factor == 1 and target == (w, h) and bits == 8 and _is_plain_rgb(sp):
                img = read_image(sp)  # validates the whole file
                with atomic_path(dp) as tmp:
                    shutil.copyfile(sp, tmp)
            else:
                img = downsample_area(read_image(sp, background), factor)
                if (img.shape[1], img.shape[0]) != target:
                    img = resize_area(img, target)
                write_image(dp, img, bits=16 if bits == 16 and dp.suffix.lower() in (".png", ".tif", ".tiff") else 8)
            written.append(dp)
            sizes[name] = (img.shape[1], img.shape[0])
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        raise
    log.info("wrote %d images (x1/%d%s) to %s", len(names), factor,
             f", long side <= {max_size}" if max_size else "", dst)
    return sizes


def _bit_depth(path: Path) -> int:
    import OpenImageIO as oiio

    inp = _open(path)
    try:
        base = inp.spec().format.basetype
    finally:
        inp.close()
    return 16 if base in (oiio.UINT16, oiio.INT16) else (32 if base in _float_types() else 8)


def _is_plain_rgb(path: Path) -> bool:
    inp = _open(path)
    try:
        spec = inp.spec()
        return spec.nchannels == 3 and int(spec.get_int_attribute("Orientation", 1)) == 1
    finally:
        inp.close()
