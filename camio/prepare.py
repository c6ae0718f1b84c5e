"""Prepare a scene for the pipeline: any supported format -> ``OUT/images`` + ``OUT/sparse/0``.

``OUT/images`` holds the images (copied, or area-downsampled by an integer factor, keeping
their names; a photo folder's at its working resolution: the long side at most
:data:`PHOTO_MAX_SIZE` unless ``max_size`` says otherwise); ``OUT/sparse/0`` a COLMAP text model (PINHOLE) with the reference cameras scaled
exactly to the written images (``u_new = u_old / factor``, see
:func:`camio.images.downsample_area`), points and observations when the source has them;
``OUT/split.json`` the PROTOCOL section 4 split; ``OUT/scene.json`` provenance. The output
folder appears atomically: on any error nothing is left.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path


from runtime.atomic import atomic_dir, write_json
from camio.cameras import Camera, scale_intrinsics
from camio.colmap import SparseModel, write_text_model
from camio.images import describe_orientation, downsample_folder, image_size, working_size
from camio.scene import check_same_size, load_scene
from camio.split import make_split, write_split, TEST_EVERY

__all__ = ["PHOTO_MAX_SIZE", "prepare_scene", "scale_model", "photo_max_size", "describe_working_size"]

log = logging.getLogger(__name__)

#: the long side (pixels) of a photo folder's working images: every stage after conversion
#: (COLMAP, VGGT, training) reads these, sized for a CPU or one GPU; 0 = the photos' own size
PHOTO_MAX_SIZE = 1600


def photo_max_size(max_size: int | None, has_cameras: bool, downsample: int = 1) -> int:
    """The size cap in effect: ``max_size`` as given, else :data:`PHOTO_MAX_SIZE` for photos
    (no cameras, no ``downsample``) and 0 (none) for a dataset. A cap on a dataset's images
    is refused (its cameras scale by an integer ``downsample``), as is a cap with a factor."""
    if max_size is None:
        return 0 if has_cameras or downsample != 1 else PHOTO_MAX_SIZE
    if max_size < 0:
        raise ValueError(f"--max-size must be 0 (full resolution) or a number of pixels, got {max_size}")
    if max_size and has_cameras:
        raise ValueError("--max-size sizes a photo folder; a dataset with cameras is downsampled by an "
                         "integer factor: use --downsample K")
    if max_size and downsample != 1:
        raise ValueError("give --downsample or --max-size, not both")
    return max_size


def describe_working_size(sizes: list[tuple[int, int]], max_size: int) -> str:
    """One line: the photos' sizes and the working resolution ``max_size`` gives them
    ("12 photos 4032x3024 -> 1600x1200 working resolution"; photos of several sizes, e.g.
    portrait and landscape, list each size with its count)."""
    n = f"{len(sizes)} photo{'s' if len(sizes) != 1 else ''}"
    why = " (full resolution)" if not max_size else ""
    counts: dict[tuple[int, int], int] = {}
    for s in sizes:
        counts[s] = counts.get(s, 0) + 1
    if len(counts) != 1:
        parts = ", ".join(f"{c} x {w}x{h} -> {'x'.join(map(str, working_size(w, h, max_size)))}"
                          for (w, h), c in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))
        return f"{n} of {len(counts)} sizes ({parts}) working resolution{why or f' (long side at most {max_size} px)'}"
    (w, h) = next(iter(counts))
    ww, wh = working_size(w, h, max_size)
    why = why or (f" (within {max_size} px)" if (ww, wh) == (w, h) else "")
    return f"{n} {w}x{h} -> {ww}x{wh} working resolution{why}"


def scale_model(model: SparseModel, factor: int, sizes: dict[str, tuple[int, int]]) -> SparseModel:
    """The model for images area-downsampled by ``factor`` (intrinsics and observations / factor,
    sizes from ``sizes`` name -> (width, height))."""
    cams = [Camera(c.name, *sizes[c.name], scale_intrinsics(c.K, 1.0 / factor), c.cam_from_world)
            for c in model.cameras]
    obs = {k: (xy / factor, idx) for k, (xy, idx) in model.observations.items()}
    return SparseModel(cams, model.points, model.colors, obs, model.camera_models)


def prepare_scene(
    src: str | Path, out: str | Path, format: str = "auto", images_subdir: str | Path | None = None,
    downsample: int = 1, undistort: bool = False, ns: tuple[int, ...] = (3, 6, 9, 12),
    require_same_size: bool = True, allow_mixed: bool = False, skip_missing: bool = False,
    announce=None, max_size: int | None = None,
) -> Path:
    """Convert the scene at ``src`` into a prepared scene folder ``out`` (module docstring).

    Args:
        src, format, images_subdir, undistort: as :func:`camio.scene.load_scene`.
        downsample: integer area-downsampling factor (1 = copy).
        ns: training-view counts written to split.json (those that do not fit are skipped).
        require_same_size: refuse a dataset (reference cameras) whose images differ in size;
            ``allow_mixed`` turns it off too. A photo folder (no cameras) may mix sizes
            (portrait and landscape photos): every image keeps its own size and camera.
        allow_mixed, skip_missing: as :func:`camio.scene.load_scene`.
        announce: called with :meth:`camio.scene.Scene.describe` once the scene is read, and
            for a photo folder with :func:`describe_working_size` (the CLI prints them).
        max_size: a photo folder's long side at most this (pixels; 0 = full resolution; None =
            :data:`PHOTO_MAX_SIZE`): :func:`photo_max_size`.
    """
    t0 = time.perf_counter()
    out = Path(out)
    with atomic_dir(out) as tmp:
        scene = load_scene(src, format, images_subdir, undistort=undistort,
                           work_dir=tmp / "_undistorted" if undistort else None,
                           allow_mixed=allow_mixed, skip_missing=skip_missing)
        log.info("%s", scene.describe())
        if announce is not None:
            announce(scene.describe())
        has_cameras = scene.model is not None and bool(scene.model.cameras)
        if require_same_size and not allow_mixed and has_cameras:
            check_same_size(scene.image_dir, scene.names)
        turned = describe_orientation(scene.image_dir, scene.names)
        if turned is not None:
            log.info("%s", turned)
            if announce is not None:
                announce(turned)
        cap = photo_max_size(max_size, has_cameras, downsample)
        source_size = image_size(scene.image_path(scene.names[0]))
        if not has_cameras:
            line = describe_working_size([image_size(scene.image_path(n)) for n in scene.names], cap)
            log.info("%s", line)
            if announce is not None:
                announce(line)
        sizes = downsample_folder(scene.image_dir, tmp / "images", downsample, scene.names, max_size=cap)
        n_cams = 0
        if scene.model is not None and scene.model.cameras:
            model = scale_model(scene.model, downsample, sizes) if downsample != 1 else scene.model
            write_text_model(tmp / "sparse" / "0", model.cameras, model.points, model.colors,
                             model.observations)
            n_cams = len(model.cameras)
        pool = len(scene.names) - len(range(0, len(scene.names), TEST_EVERY))
        fits = tuple(n for n in ns if n <= pool)
        if fits:
            write_split(tmp / "split.json", make_split(scene.names, fits))
        else:
            log.warning("%d images: too few for any n in %s; no split.json written", len(scene.names), ns)
        if undistort:
            import shutil

            shutil.rmtree(tmp / "_undistorted", ignore_errors=True)
        w, h = sizes[scene.names[0]]
        write_json(tmp / "scene.json", {
            "source": str(Path(src).resolve()), "format": scene.source_format,
            "images_subdir": None if images_subdir is None else str(images_subdir),
            "downsample": downsample, "max_size": cap, "source_image_size": list(source_size),
            "undistorted": scene.undistorted, "n_images": len(scene.names),
            "n_reference_cameras": n_cams, "camera_models": list(scene.source_models),
            "n_points": 0 if scene.model is None else int(len(scene.model.points)),
            "image_size": [w, h], "image_sizes": {n: list(sizes[n]) for n in scene.names},
            "wall_time_s": time.perf_counter() - t0,
        })
    shown = f"{w}x{h}" if len(set(sizes.values())) == 1 else f"{len(set(sizes.values()))} sizes"
    log.info("prepared %s -> %s (%d images at %s, %d reference cameras) in %.2f s", src, out,
             len(scene.names), shown, n_cams, time.perf_counter() - t0)
    return out


