"""Training data: the seed PLY, a COLMAP camera folder and the images, matched by name.

The cameras (``camio.colmap.read_model``) must be in the frame of the seed PLY (the Bridge
writes both). Images may have another size than the COLMAP cameras (e.g. the cameras at the
original resolution, the images at 1/8): the intrinsics are rescaled to the image size
(:meth:`camio.Camera.scaled`), which is exact in the COLMAP pixel convention. An optional
integer ``downsample`` then area-downsamples each image (remainder rows / columns cropped) and
divides K by the factor.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from camio import Camera
from camio.cameras import scale_intrinsics
from camio.images import downsample_area, image_size, read_image
from camio.colmap import read_model
from runtime.names import check_stems

__all__ = ["View", "load_views", "load_cameras", "read_name_list", "scene_extent"]

log = logging.getLogger(__name__)

# Images whose aspect ratio differs from the camera's by more than this are refused.
ASPECT_TOLERANCE = 0.02


@dataclass
class View:
    """One posed image ready for training or evaluation.

    Attributes:
        camera: pinhole camera at the image's size (K in its pixels, cam_from_world [3, 4]).
        image: [H, W, 3] float32 RGB in [0, 1], or None for render-only views.
    """

    camera: Camera
    image: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.camera.name


def read_name_list(path: str | Path) -> list[str]:
    """Image names from a file: a JSON list, or plain text with one name per line ('#'
    starts a comment, blank lines ignored); every name plain and none twice
    (runtime.names.check_name_list)."""
    from runtime.names import check_name_list

    path = Path(path)
    text = path.read_text()
    if path.suffix.lower() == ".json":
        data = json.loads(text)
        if not isinstance(data, list) or not all(isinstance(x, str) for x in data):
            raise ValueError(f"{path}: a JSON image list must be a list of names")
        return check_name_list(data, path)
    names = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    return check_name_list([n for n in names if n], path)


def load_cameras(cameras_dir: str | Path, names: list[str] | None = None) -> list[Camera]:
    """The posed pinhole cameras of a COLMAP folder, sorted by name, optionally restricted to
    ``names`` (every name must be present)."""
    model = read_model(cameras_dir)
    cams = model.cameras
    if names is not None:
        have = {c.name for c in cams}
        missing = sorted(set(names) - have)
        if missing:
            raise KeyError(f"image names not in the camera model {cameras_dir}: {missing[:5]} "
                           f"({len(missing)} missing); check --image-list against the model")
        wanted = set(names)
        cams = [c for c in cams if c.name in wanted]
    if not cams:
        raise ValueError(f"no cameras to use in {cameras_dir}")
    return cams


def _fit_camera(cam: Camera, width: int, height: int) -> Camera:
    if (width, height) == (cam.width, cam.height):
        return cam
    ra, rb = cam.width / cam.height, width / height
    if abs(ra / rb - 1.0) > ASPECT_TOLERANCE:
        raise ValueError(
            f"image {cam.name!r} is {width}x{height} but its camera is {cam.width}x{cam.height} "
            "(different aspect ratio): the images do not belong to these cameras, or were cropped"
        )
    return cam.scaled(width, height)


def downsample_camera(cam: Camera, factor: int) -> Camera:
    """The camera of ``downsample_area(image, factor)``: size floor-divided, K / factor."""
    if factor == 1:
        return cam
    return Camera(cam.name, cam.width // factor, cam.height // factor,
                  scale_intrinsics(cam.K, 1.0 / factor), cam.cam_from_world.copy())


def load_views(cameras_dir: str | Path, images_dir: str | Path | None, names: list[str] | None = None,
               downsample: int = 1, background: tuple[float, float, float] = (1.0, 1.0, 1.0),
               read_pixels: bool = True) -> list[View]:
    """Cameras matched with their images.

    Args:
        cameras_dir: COLMAP model folder (text or binary).
        images_dir: folder holding the image files named as in the model (None: the views
            keep the camera sizes and have no pixels).
        names: restrict to these image names.
        downsample: integer area-downsampling factor.
        background: composited under transparent pixels of RGBA images.
        read_pixels: False reads only the image sizes (for rendering).

    Returns:
        Views sorted by name; images [H, W, 3] float32 in [0, 1].

    Raises:
        ValueError: two views whose names differ only by their extension (their renders,
            ``<stem>.png``, would be one file; :func:`runtime.names.check_stems`).
    """
    cams = load_cameras(cameras_dir, names)
    check_stems([c.name for c in cams], cameras_dir)  # renders are <stem>.png: v0.png and v0.jpg would be one file
    views: list[View] = []
    for cam in cams:
        img = None
        if images_dir is not None:
            path = Path(images_dir) / cam.name
            if not path.is_file():
                raise FileNotFoundError(f"no image file {path} for camera {cam.name!r}: "
                                        "--images must hold the images named in the camera model")
            if read_pixels:
                img = read_image(path, background)
                h, w = img.shape[:2]
            else:
                w, h = image_size(path)
            cam = _fit_camera(cam, w, h)
        if downsample > 1:
            cam = downsample_camera(cam, downsample)
            if img is not None:
                img = downsample_area(img, downsample)
        views.append(View(cam, img))
    log.info("loaded %d views from %s (%s)", len(views), cameras_dir,
             "x".join(map(str, (views[0].camera.width, views[0].camera.height))))
    return views


def scene_extent(cameras: list[Camera], points: np.ndarray | None = None) -> float:
    """Scene extent that scales the position learning rate and the world-size prune.

    3DGS uses 1.1 x the largest distance of a camera centre from their mean
    (``getNerfppNorm``): right for captures around an object, far too small for a few nearby
    views of a deeper scene (3 views on a short arc gave 0.18 while the scene lay at distance
    1.0, so after the first opacity reset every seed Gaussian exceeded the 0.1 x extent prune and
    the run went black). With ``points`` ([N, 3] world, e.g. the seed means) the extent is the
    larger of that and 1.1 x the median distance of the finite points from the camera mean; for
    an object-centred capture the two agree. 1.0 when both are degenerate.

    Args:
        cameras: the training cameras.
        points: [N, 3] world points or None (the plain 3DGS rule).
    """
    c = np.stack([cam.center for cam in cameras])
    centre = c.mean(0)
    radius = float(np.linalg.norm(c - centre, axis=1).max()) * 1.1
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(1)]
        if len(p):
            radius = max(radius, 1.1 * float(np.median(np.linalg.norm(p - centre, axis=1))))
    return radius if radius > 1e-9 else 1.0


def mean_colour(views: list[View]) -> list[float]:
    """The mean RGB of the views' images, pooled over all their pixels in float64: the constant
    that predicts an unseen pixel best in squared error from these images alone (the config's
    ``background`` "mean"), rounded to 1e-6 (below a 16-bit image's step) so that train.json
    reads it back exactly. Views without pixels are refused."""
    if not views or any(v.image is None for v in views):
        raise ValueError("the mean colour needs the training images' pixels")
    total, count = np.zeros(3), 0
    for v in views:
        img = np.asarray(v.image, dtype=np.float64).reshape(-1, 3)
        total += img.sum(0)
        count += len(img)
    return [round(float(c), 6) for c in total / count]


def has_alpha(path: str | Path) -> bool:
    """Whether the image file has an alpha channel (2 or 4 channels: what
    :func:`camio.images.read_image` composites on a background); read from its header."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return True  # unreadable header: read it again, and let the reader name the problem
    try:
        return int(inp.spec().nchannels) in (2, 4)
    finally:
        inp.close()


def load_views_on_mean(cameras_dir: str | Path, images_dir: str | Path, names: list[str] | None = None,
                       downsample: int = 1) -> tuple[list[View], list[float]]:
    """The views of :func:`load_views` composited on their own mean colour (the config's
    ``background`` "mean"), and that colour (:func:`mean_colour` of the images composited on
    black). Each image is read once; only an image with an alpha channel is read a second time,
    composited on the mean (an image without one reads the same on any background).

    Returns:
        (views sorted by name, images [H, W, 3] float32 in [0, 1]; the mean RGB).
    """
    views = load_views(cameras_dir, images_dir, names, downsample, (0.0, 0.0, 0.0))
    colour = mean_colour(views)
    again = [v.name for v in views if has_alpha(Path(images_dir) / v.name)]
    if again:
        redone = {v.name: v for v in load_views(cameras_dir, images_dir, again, downsample, tuple(colour))}
        views = [redone.get(v.name, v) for v in views]
    return views, colour

