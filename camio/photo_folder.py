"""A folder of one's own photos, checked whole before anything runs.

:func:`photo_problems` reads every file of the folder once and names every photo that the
pipeline cannot use, all at once, so that one run of ``scripts/photos.py`` lists them all:

* a photo in a format the readers do not take (HEIC/HEIF, AVIF, WebP, GIF, BMP, camera raw:
  :data:`UNSUPPORTED_PHOTO_EXTENSIONS`), which ``camio convert`` would otherwise pass over;
* a file with an image extension (:data:`camio.images.IMAGE_EXTENSIONS`) that does not decode
  whole (missing reader, truncated or corrupt: :func:`camio.images.read_pixels`);
* a name COLMAP's text format cannot hold (:func:`camio.images.check_image_name`);
* a photo whose short side is under :data:`camio.images.MIN_IMAGE_SIDE` pixels (no features).

Other files (sidecars such as ``.xmp`` or ``.json``, hidden files) are not photos and are
passed over, as ``camio convert --format folder`` does; so are the maps a bare folder leaves out
(:func:`camio.datasets.split_photos`). Photos may differ in size and orientation: each keeps
its own (EXIF orientation applied) and gets its own camera.
"""

from __future__ import annotations

from pathlib import Path

from camio.images import (IMAGE_EXTENSIONS, MIN_IMAGE_SIDE, ImageNameError, ImageReadError, check_image_name,
                          image_size, read_pixels)

__all__ = ["UNSUPPORTED_PHOTO_EXTENSIONS", "photo_problems", "describe_problems"]

#: photo formats that cameras and phones write but the readers (OpenImageIO as built) do not take
UNSUPPORTED_PHOTO_EXTENSIONS = (".heic", ".heif", ".avif", ".webp", ".gif", ".bmp", ".dng", ".cr2", ".cr3",
                                ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw")


def photo_problems(folder: str | Path) -> dict[str, str]:
    """Every photo of ``folder`` (its files, not subfolders) that the pipeline cannot use.

    Returns:
        file name -> why, in a few words ({} when every photo can be used), in name order.
    """
    folder = Path(folder)
    problems: dict[str, str] = {}
    for path in sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")):
        ext = path.suffix.lower()
        if ext in UNSUPPORTED_PHOTO_EXTENSIONS:
            problems[path.name] = (f"{ext[1:].upper()} is not read here: export it as JPEG "
                                   f"({'/'.join(e[1:] for e in IMAGE_EXTENSIONS)} are)")
            continue
        if ext not in IMAGE_EXTENSIONS:
            continue
        try:
            check_image_name(path.name, folder)
        except ImageNameError:
            problems[path.name] = f"the name holds whitespace, which COLMAP cannot read: rename it, e.g. to " \
                                  f"{'_'.join(path.name.split())!r}"
            continue
        try:
            read_pixels(path, "uint8")
            w, h = image_size(path)
        except ImageReadError as exc:
            problems[path.name] = _why(str(exc))
            continue
        if min(w, h) < MIN_IMAGE_SIDE:
            problems[path.name] = f"{w}x{h} px: too small (the short side must be at least {MIN_IMAGE_SIDE} px)"
    return problems


def _why(message: str) -> str:
    """An :class:`ImageReadError`'s message without the path it starts with (the name is shown)."""
    text = " ".join(message.split())
    for lead in ("cannot read image ", "cannot open image ", "image "):
        if text.startswith(lead):
            text = text[len(lead):]
            text = text.split(": ", 1)[1] if ": " in text else text
            break
    return f"does not decode ({text[:160]})"


def describe_problems(folder: str | Path, problems: dict[str, str]) -> str:
    """One line naming every unusable photo of ``folder`` and why, and what to do."""
    shown = "; ".join(f"{name}: {why}" for name, why in problems.items())
    return (f"{len(problems)} photo(s) in {folder} cannot be used: {shown}. Fix them or move them out of the "
            "folder, then run again")
