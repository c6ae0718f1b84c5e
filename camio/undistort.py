"""Undistortion of models with distortion (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV; transforms.json and
Strecha distortion as OPENCV) to PINHOLE,
through pycolmap's image undistorter (the same code as ``colmap image_undistorter``).

The undistorter writes new images (resampled, bilinear) and a PINHOLE model whose image size
may differ from the input (it keeps the valid region, COLMAP's default options). If the image
files are a uniformly rescaled copy of what the model was made for (e.g. fern's images_4 for a
4032 px model), the distorted cameras are rescaled to the files first: focal lengths and
principal point scale with the image; radial/tangential coefficients act on normalised
coordinates and stay the same.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

from camio.images import image_size
from runtime.native import stoppable

__all__ = ["undistort_colmap", "undistort_model", "write_camera_model_text"]

log = logging.getLogger(__name__)


def undistort_colmap(model_dir: Path, image_dir: Path, work_dir: Path) -> tuple[Path, Path]:
    """Undistort every registered image of the model in ``model_dir``.

    Args:
        model_dir: folder with cameras/images/points3D (.txt or .bin).
        image_dir: the images the model names.
        work_dir: output folder; must not exist or be empty. Receives ``images/`` and
            ``sparse/`` (binary PINHOLE model). Removed again if the undistorter fails.

    Returns:
        (undistorted image folder, undistorted model folder).
    """
    import pycolmap

    t0 = time.perf_counter()
    work_dir = Path(work_dir)
    if work_dir.exists() and any(work_dir.iterdir()):
        raise FileExistsError(f"undistortion work folder {work_dir} is not empty; choose a new one")
    work_dir.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    rec.read(str(model_dir))
    rescaled = False
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        w, h = image_size(image_dir / image.name)
        if (w, h) != (cam.width, cam.height):
            cam.rescale(w, h)
            rescaled = True
    try:
        in_model = model_dir
        if rescaled:
            in_model = work_dir / "_input_model"
            in_model.mkdir()
            rec.write(str(in_model))
            log.info("rescaled the distorted cameras to the image files before undistortion")
        # in a child a stop ends at once (runtime.native): minutes on a large scene
        stoppable("undistortion", pycolmap.undistort_images, str(work_dir), str(in_model), str(image_dir),
                  output_type="COLMAP")
        if rescaled:
            shutil.rmtree(in_model)
    except Exception:
        shutil.rmtree(work_dir, ignore_errors=True)
        raise
    out_images, out_model = work_dir / "images", work_dir / "sparse"
    if not (out_model / "cameras.bin").is_file() and not (out_model / "cameras.txt").is_file():
        shutil.rmtree(work_dir, ignore_errors=True)
        raise RuntimeError(f"pycolmap's undistorter wrote no model into {work_dir}")
    log.info("undistorted %d images into %s in %.2f s", len(rec.images), work_dir, time.perf_counter() - t0)
    return out_images, out_model


def write_camera_model_text(path: Path, model) -> Path:
    """Write ``model`` (a :class:`camio.colmap.SparseModel`) as a COLMAP text model keeping each
    image's camera model from ``model.camera_models`` (PINHOLE from K where absent), one
    COLMAP camera per image, no points; the input of :func:`undistort_colmap`."""
    import numpy as np

    from camio.cameras import rotmat_to_qvec

    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    cams, imgs = ["# Number of cameras: %d" % len(model.cameras)], ["# Number of images: %d" % len(model.cameras)]
    for i, c in enumerate(model.cameras, 1):
        m, params = model.camera_models.get(c.name, ("PINHOLE", np.r_[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]]))
        if any(ch.isspace() for ch in c.name):
            raise ValueError(f"image name {c.name!r} contains whitespace (COLMAP text cannot store it)")
        cams.append(f"{i} {m} {c.width} {c.height} " + " ".join(repr(float(x)) for x in params))
        imgs.append(f"{i} " + " ".join(repr(float(x)) for x in (*rotmat_to_qvec(c.R), *c.t)) + f" {i} {c.name}")
        imgs.append("")
    (path / "cameras.txt").write_text("\n".join(cams) + "\n")
    (path / "images.txt").write_text("\n".join(imgs) + "\n")
    (path / "points3D.txt").write_text("# Number of points: 0\n")
    return path


def undistort_model(model, image_dir: Path, work_dir: Path) -> tuple[Path, Path]:
    """Undistort a model read from any format (OPENCV entries in ``model.camera_models``):
    its COLMAP text form goes to ``work_dir/model``, the undistorter writes ``work_dir/out``.

    Returns:
        (undistorted image folder, undistorted model folder), as :func:`undistort_colmap`.
    """
    work_dir = Path(work_dir)
    if work_dir.exists() and any(work_dir.iterdir()):
        raise FileExistsError(f"undistortion work folder {work_dir} is not empty; choose a new one")
    src = write_camera_model_text(work_dir / "model", model)
    return undistort_colmap(src, Path(image_dir), work_dir / "out")
