"""MP4 video files (H.264, yuv420p) through imageio and its bundled ffmpeg (imageio-ffmpeg).

Both packages are optional (``pip install imageio imageio-ffmpeg``, or the project's ``share``
extra) and imported only when a video is written or read; without them
:class:`VideoUnavailable` names what to install. H.264 in yuv420p needs an even width and
height: :func:`even_size` gives the size to render at.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_path

__all__ = ["VideoUnavailable", "check_video_path", "require_imageio", "even_size", "write_video", "count_frames", "DEFAULT_FPS"]

#: frames per second of a fly-through video unless told otherwise
DEFAULT_FPS = 30


class VideoUnavailable(RuntimeError):
    """imageio or imageio-ffmpeg is not installed."""


def require_imageio():
    """imageio.v2 with its ffmpeg; :class:`VideoUnavailable` naming the missing package otherwise."""
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the encoder imageio's FFMPEG plugin runs)
    except ImportError as exc:
        raise VideoUnavailable(f"writing an mp4 video needs the {exc.name or 'imageio'} package: "
                               "pip install imageio imageio-ffmpeg") from exc
    return imageio


def check_video_path(path: str | Path) -> Path:
    """``path`` as the mp4 file a video is written to: its suffix must be ``.mp4`` (any case);
    ffmpeg picks the container by the suffix, and fails on no suffix or one it cannot hold
    H.264 in (``.gif``). ValueError naming the path and the name to give otherwise."""
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"--video {path}: the video is an H.264 mp4, so its name must end in .mp4 "
                         f"(e.g. {path.with_suffix('.mp4').name})")
    return path


def even_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) rounded down to even numbers (at least 2), as H.264 in yuv420p needs."""
    return max(2, int(width) // 2 * 2), max(2, int(height) // 2 * 2)


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float = DEFAULT_FPS) -> int:
    """Encode ``frames`` as an H.264 mp4 at ``fps``, atomically (nothing at ``path`` on failure).

    Args:
        frames: [H, W, 3] float RGB in [0, 1] (clamped), all one even size.

    Returns:
        The number of frames written.
    """
    check_video_path(path)
    imageio = require_imageio()
    count = 0
    with atomic_path(path) as tmp:
        writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                                    pixelformat="yuv420p", macro_block_size=1, quality=8)
        try:
            for f in frames:
                f = np.asarray(f)
                if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] % 2 or f.shape[1] % 2:
                    raise ValueError(f"video frame {count}: expected [H, W, 3] with even H and W, got {f.shape}")
                writer.append_data(np.round(np.clip(f, 0.0, 1.0) * 255.0).astype(np.uint8))
                count += 1
        finally:
            writer.close()
    return count


def count_frames(path: str | Path) -> int:
    """The number of frames of a video file, by decoding every frame."""
    imageio = require_imageio()
    reader = imageio.get_reader(str(path), format="FFMPEG")
    try:
        return sum(1 for _ in reader)
    finally:
        reader.close()
