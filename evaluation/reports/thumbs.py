"""The report's thumbnails: a downsampled PNG copy of an image, and the table cell that shows it
(one implementation for the held-out render grids and the photo section)."""

from __future__ import annotations

import html
import logging
from pathlib import Path

from camio.images import IMAGE_EXTENSIONS, ImageReadError, downsample_area, read_image, write_image

__all__ = ["THUMB_WIDTH", "MAX_VIEWS", "images_in", "thumb", "thumb_cell"]

log = logging.getLogger(__name__)

THUMB_WIDTH = 256
#: test views per held-out render grid of the report, at most (``python -m evaluation report --max-views``)
MAX_VIEWS = 4


def images_in(folder: Path | None) -> dict[str, Path]:
    """stem -> path of the images directly in ``folder`` (empty when it is not a folder)."""
    if folder is None or not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_EXTENSIONS}


def thumb(src: Path, dst: Path) -> bool:
    """Write a PNG thumbnail of ``src`` (downsampled by an integer factor to <= THUMB_WIDTH
    pixels wide) to ``dst``; False (logged) when unreadable."""
    try:
        img = read_image(src)
    except (ImageReadError, OSError) as exc:
        log.warning("report: cannot read %s (%s)", src, exc)
        return False
    factor = max(1, -(-img.shape[1] // THUMB_WIDTH))
    if factor > 1 and img.shape[0] >= factor:
        img = downsample_area(img[: img.shape[0] // factor * factor, : img.shape[1] // factor * factor], factor)
    write_image(dst, img)
    return True


def thumb_cell(src: Path | None, images_dir: Path, rel: str, alt: str, caption: str = "") -> str:
    """A table cell: the thumbnail of ``src`` written to ``images_dir/rel`` (with a line of
    ``caption`` text under it), or "missing"."""
    if src is None or not thumb(src, images_dir / rel):
        return '<td class="missing">missing</td>'
    cap = f"<br><small>{html.escape(caption)}</small>" if caption else ""
    return f'<td><img src="images/{html.escape(rel)}" alt="{html.escape(alt)}">{cap}</td>'
