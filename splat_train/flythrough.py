"""Fly-through videos of a trained model along a camera path (``python -m splat_train render
--path orbit|interpolate --video out.mp4``).

The path comes from the cameras of a COLMAP folder in the model's frame (:mod:`camio.campath`);
every frame is rendered with one intrinsic matrix, the first camera's (by name), scaled to the
video size: that camera's size, or ``width`` x ``height``, rounded down to even numbers for
H.264 (:func:`camio.video.even_size`). The video is written by :func:`camio.video.write_video`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from camio.campath import DEFAULT_FRAMES, PATHS, interpolate_path, orbit_path
from camio.ply import read_gaussian_ply
from camio.video import DEFAULT_FPS, even_size, write_video
from runtime.logs import progress
from splat_train.data import load_cameras, read_name_list
from splat_train.export import background_note, model_background, render_params
from splat_train.gaussians import params_from_cloud

__all__ = ["path_poses", "render_path"]

log = logging.getLogger(__name__)


def path_poses(path: str, cameras: list, frames: int) -> np.ndarray:
    """[F, 4, 4] cam_from_world of ``path`` (one of :data:`camio.campath.PATHS`) over ``cameras``:
    ``frames`` per camera pair for interpolate, per circle for orbit."""
    if path == "interpolate":
        return interpolate_path(cameras, frames)
    if path == "orbit":
        return orbit_path(cameras, frames)
    raise ValueError(f"unknown --path {path!r}: choose one of {', '.join(PATHS)}")


@torch.no_grad()
def render_path(model: str | Path, cameras: str | Path, path: str, video: str | Path, *,
                frames: int | None = None, fps: float = DEFAULT_FPS, width: int | None = None,
                height: int | None = None, names: str | Path | None = None,
                background: tuple[float, float, float] | None = None, device: str = "cpu") -> int:
    """Render ``model`` along ``path`` over the cameras of ``cameras`` into the mp4 ``video``.

    Args:
        frames: frames per camera pair (interpolate) or per circle (orbit); default
            :data:`camio.campath.DEFAULT_FRAMES`.
        width, height: video size (both or neither; default the first camera's), rounded down
            to even numbers.
        names: a file of image names: only these cameras (in name order).
        background: RGB in [0, 1]; None: the one the model was trained against.

    Returns:
        The number of frames written.
    """
    t0 = time.perf_counter()
    if (width is None) != (height is None):
        raise ValueError("give both --width and --height, or neither")
    frames = DEFAULT_FRAMES[path] if frames is None else int(frames)
    if background is None:
        background, source = model_background(model)
        log.info("%s", background_note(background, source))
    cams = load_cameras(cameras, read_name_list(names) if names is not None else None)
    if len(cams) < 2:  # interpolate would be one still frame, orbit has no point to circle
        raise ValueError(f"{cameras}: {len(cams)} camera(s) to fly along: a path needs at least 2; render the "
                         "single view with --out instead of --path/--video")
    try:
        poses = path_poses(path, cams, frames)
    except ValueError as exc:  # e.g. parallel axes: no orbit centre; name the cameras it came from
        raise ValueError(f"{cameras}: {exc}") from None
    w, h = even_size(width or cams[0].width, height or cams[0].height)
    first = cams[0].scaled(w, h)
    cloud = read_gaussian_ply(model)
    params = params_from_cloud(cloud, sh_degree=cloud.sh_degree, device=device)
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    K = torch.as_tensor(first.K, dtype=torch.float32, device=device)

    def rendered():
        for m in progress(poses, desc=f"render {path}"):
            cw = torch.as_tensor(m, dtype=torch.float32, device=device)
            out = render_params(params, cloud.sh_degree, cw, K, w, h, bg, depth=False, stats=False)
            yield out["rgb"].clamp(0.0, 1.0).cpu().numpy()

    n = write_video(video, rendered(), fps=fps)
    log.info("rendered %d frames of %s (%d Gaussians) along the %s path over %d cameras at %dx%d into %s in "
             "%.1f s", n, model, len(cloud), path, len(cams), w, h, video, time.perf_counter() - t0)
    return n
