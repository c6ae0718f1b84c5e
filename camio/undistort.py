"""Undistortion of COLMAP models with distortion (SIMPLE_RADIAL, RADIAL, OPENCV) to PINHOLE,
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

__all__ = ["undistort_colmap"]

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
        pycolmap.undistort_images(str(work_dir), str(in_model), str(image_dir), output_type="COLMAP")
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
