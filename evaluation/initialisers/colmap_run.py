"""The train-only COLMAP baseline, seeded and repeatable.

Settings: SIFT features (one shared PINHOLE camera, or one per image size where the images
differ in size, e.g. portrait and landscape photos; max image size :data:`MAX_IMAGE_SIZE`, at most
:data:`MAX_NUM_FEATURES` features), exhaustive matching with guided matching, incremental mapping, all through
pycolmap 4.x. Only the training images are visible: they are symlinked (copied where links
are not possible) into a private work folder before feature extraction, so a test image can
never leak into the model.

``success_paper`` (docs/contracts.md, :func:`evaluation.metrics.pose.paper_success`): the largest model
loads with >= 1 registered image and >= 1 point. ``aligned_ok``: >= 3 registered images, which
the Sim(3) alignment to the reference frame needs (part of ``success_gated``, decided in
pose.json). A failed reconstruction is a *result* (``success_paper = false`` with a reason in
``status.json``), never an exception.

Reproducibility: pycolmap's global PRNG (:func:`pycolmap.set_random_seed`) and every
``random_seed`` option (mapper, triangulator, RANSAC) are set from ``seed``. ``--threads 0``
makes every stage use every core this process may run on (:func:`available_cores`); the thread count is
recorded in ``status.json`` (``num_threads``). By default (:data:`DEFAULT_THREADS`, 1) two runs
with the same seed on the same input give identical models (tested); with more threads
(``--threads 0``: every core) the feature extraction and matching are the same but the
mapper's parallel steps may order work differently. ``--repeats k`` runs k seeds and reports the spread (:mod:`evaluation.initialisers.colmap_repeats`).
CLI: ``python -m evaluation.initialisers.colmap_baseline`` (:mod:`evaluation.initialisers.colmap_baseline`).

Output (docs/contracts.md): ``DIR/sparse/0/*.txt`` (COLMAP text, PINHOLE) when a model
exists, ``DIR/status.json``; with repeats also ``DIR/repeats/seed<s>/{sparse/0,status.json}``
and the spread in ``DIR/status.json["repeats"]``.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_dir, scratch_dir, write_json
from camio.colmap import MATCHING_THREADS, cpu_matching_options
from camio.images import MIN_IMAGE_SIDE, ImageReadError, check_images
from evaluation.metrics.pose import paper_success
from runtime.logs import peak_rss_mb
from runtime.native import stoppable

__all__ = [
    "ColmapSettings",
    "run_colmap",
    "model_fingerprint",
]

log = logging.getLogger(__name__)

MIN_ALIGN_IMAGES = 3
#: threads of a COLMAP run unless told otherwise: 1 gives the same model on every run (bitwise);
#: 0 = every available core, faster, but the mapper's parallel steps may then order work differently
DEFAULT_THREADS = 1
#: SIFT extraction downsizes larger images to this (pixels, long side): the protocol's setting
MAX_IMAGE_SIZE = 3200
#: SIFT features per image at most: the protocol's setting
MAX_NUM_FEATURES = 16384


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; os.cpu_count() where unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class ColmapSettings:
    """The evaluation protocol's COLMAP settings (defaults) plus the reproducibility knobs.

    Attributes:
        max_image_size: SIFT extraction downsizes larger images to this (pixels, long side).
        max_num_features: SIFT features per image.
        guided_matching: guided matching after geometric verification.
        camera_model: the shared camera model ("PINHOLE"): one camera per image size.
        num_threads: threads for extraction and mapping (default :data:`DEFAULT_THREADS`, 1 =
            bitwise reproducible); None or 0 = every available core (:func:`available_cores`). Matching always runs on
            :data:`camio.colmap.MATCHING_THREADS` (1): pycolmap's bundled OpenBLAS is not safe
            for concurrent matcher threads.
        matching_threads: the matcher's thread count (recorded in ``status.json``).
    """

    def __init__(self, max_image_size: int = MAX_IMAGE_SIZE, max_num_features: int = MAX_NUM_FEATURES,
                 guided_matching: bool = True, camera_model: str = "PINHOLE",
                 num_threads: int | None = DEFAULT_THREADS) -> None:
        self.max_image_size = int(max_image_size)
        self.max_num_features = int(max_num_features)
        self.guided_matching = bool(guided_matching)
        self.camera_model = str(camera_model)
        self.num_threads = available_cores() if not num_threads else int(num_threads)
        self.matching_threads = MATCHING_THREADS

    def to_json(self) -> dict:
        return dict(vars(self))


def _link_images(images_dir: Path, names: list[str], work_images: Path,
                 work_names: dict[str, str] | None = None) -> None:
    """Symlink (or copy) exactly ``names`` from ``images_dir`` into ``work_images``, each as
    ``work_names[name]`` (default: its own name)."""
    missing = [n for n in names if not (images_dir / n).is_file()]
    if missing:
        raise FileNotFoundError(
            f"training images not found in {images_dir}: {missing[:5]}; check the split and "
            "the scene's images/ folder")
    work_images.mkdir(parents=True, exist_ok=True)
    for name in names:
        dst = work_images / (work_names or {}).get(name, name)
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.symlink((images_dir / name).resolve(), dst)
        except OSError:
            shutil.copy2(images_dir / name, dst)


def _check_inputs(images_dir: Path, names: list[str]) -> None:
    """Every training image exists and decodes fully with :func:`camio.images.read_image`'s
    checked decoder, so pycolmap is only ever given images the other stages accept too (it
    would extract features from the grey half of a truncated JPEG without a word).

    Raises:
        FileNotFoundError: names missing from ``images_dir`` (named).
        ImageReadError: the first truncated, corrupt or unreadable image (named).
    """
    from camio.images import check_image_name

    for n in names:
        check_image_name(n, images_dir)
    missing = [n for n in names if not (images_dir / n).is_file()]
    if missing:
        raise FileNotFoundError(
            f"training images not found in {images_dir}: {missing[:5]}; check the split and "
            "the scene's images/ folder")
    check_images(images_dir / n for n in names)




def input_problems(images_dir: Path, names: list[str]) -> list[str]:
    """What in the training images keeps COLMAP from using them all.

    An EXIF rotation changes the stored-vs-displayed size (COLMAP reads the stored pixels;
    ``camio convert`` writes every image upright), and a tiny image has no features. The
    mapper then reports only "no initial image pair". Images of different sizes are no problem:
    each size gets its own camera (:func:`size_groups`).

    Returns:
        One sentence per problem ([] when none): EXIF-rotated images, images smaller than
        :data:`MIN_IMAGE_SIDE` px.
    """
    import OpenImageIO as oiio

    rotated, small = [], []
    for n in names:
        inp = oiio.ImageInput.open(str(images_dir / n))
        if inp is None:
            continue  # _check_inputs has already named unreadable files
        try:
            spec = inp.spec()
            w, h, o = int(spec.width), int(spec.height), int(spec.get_int_attribute("Orientation", 1))
        finally:
            inp.close()
        if o not in (0, 1):
            rotated.append(f"{n} (orientation {o})")
        if min(w, h) < MIN_IMAGE_SIDE:
            small.append(f"{n} ({w}x{h})")
    out = []
    if rotated:
        out.append(f"EXIF-rotated images: {', '.join(rotated[:3])}: COLMAP reads them unrotated")
    if small:
        out.append(f"images too small for features (< {MIN_IMAGE_SIDE} px): {', '.join(small[:3])}")
    return out


def size_groups(images_dir: Path, names: list[str]) -> dict[str, str]:
    """name -> the name COLMAP extracts it under: the name itself where every image has one
    stored size (one shared camera, ``CameraMode.SINGLE``), else ``"<W>x<H>/<name>"``, a folder
    per size, so that ``CameraMode.PER_FOLDER`` gives each size its own camera (COLMAP's
    ``SINGLE`` mode skips every image whose size differs from the first's)."""
    from camio.images import _open

    sizes = {}
    for n in names:
        inp = _open(images_dir / n)
        try:
            sizes[n] = f"{int(inp.spec().width)}x{int(inp.spec().height)}"
        finally:
            inp.close()
    if len(set(sizes.values())) == 1:
        return {n: n for n in names}
    return {n: f"{sizes[n]}/{n}" for n in names}


def _options(settings: ColmapSettings, seed: int):
    """pycolmap option objects for one seeded run."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = settings.camera_model

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = settings.max_image_size
    extraction.num_threads = settings.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = settings.max_num_features

    matching = cpu_matching_options()  # one matcher thread: camio.colmap.MATCHING_THREADS
    matching.guided_matching = settings.guided_matching

    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    verification.ransac.num_threads = 1

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = settings.num_threads
    mapping.random_seed = seed
    mapping.mapper.num_threads = settings.num_threads
    mapping.mapper.random_seed = seed
    mapping.triangulation.random_seed = seed
    # min_model_size stays COLMAP's default (10); COLMAP itself lowers it to 80% of the
    # image count for small sets, which is the behaviour the paper's baseline had.
    return reader, extraction, matching, verification, mapping


def _map(db: Path, images: Path, sparse: Path, options) -> list[int]:
    """Incremental mapping in :func:`runtime.native.stoppable`'s child: every model written to
    ``sparse/<i>`` (COLMAP binary, read back exactly), their keys returned (a
    ``pycolmap.Reconstruction`` does not pickle)."""
    import pycolmap

    recs = pycolmap.incremental_mapping(db, images, sparse, options=options)
    for i, rec in recs.items():
        (sparse / str(i)).mkdir(parents=True, exist_ok=True)
        rec.write(str(sparse / str(i)))
    return sorted(recs)


def _largest(recs: dict) -> tuple[int | None, object | None]:
    """The model with the most registered images (ties: most points), or (None, None)."""
    best_key, best = None, None
    for key, rec in sorted(recs.items()):
        score = (rec.num_reg_images(), rec.num_points3D())
        if best is None or score > (best.num_reg_images(), best.num_points3D()):
            best_key, best = key, rec
    return best_key, best


def _fy_over_fx(rec) -> float | None:
    """fy / fx of the first camera of a PINHOLE model (a drifting ratio flags a bad model)."""
    for cam in rec.cameras.values():
        if cam.model.name == "PINHOLE":
            fx, fy = float(cam.params[0]), float(cam.params[1])
            return fy / fx if fx else None
    return None


def run_colmap(images_dir: str | Path, names: list[str], out_dir: str | Path, seed: int = 0,
               settings: ColmapSettings | None = None, keep_work: bool = False) -> dict:
    """Run the train-only COLMAP baseline once and write its result.

    Args:
        images_dir: folder holding the scene's images (test images may be there too; only
            ``names`` are linked into the work folder).
        names: the training image names (relative to ``images_dir``).
        out_dir: output folder; receives ``sparse/0`` (if a model exists) and
            ``status.json``.
        seed: seed for pycolmap's PRNG and every ``random_seed`` option.
        settings: COLMAP settings (the protocol defaults if None).
        keep_work: keep the work folder (database, linked images) as ``out_dir/work``.

    Returns:
        The status record written to ``status.json``: ``success_paper`` (docs/contracts.md),
        ``aligned_ok`` (>= 3 registered), ``registered``, ``n_images``, ``points``,
        ``reason`` (None on success), ``wall_time_s``, ``seed``, ``registered_names``,
        ``num_models``, ``fy_over_fx``, ``mean_reproj_error_px``, ``settings``.
    """
    import pycolmap

    settings = settings or ColmapSettings()
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    names = sorted(dict.fromkeys(names))
    if not names:
        raise ValueError("run_colmap: no training image names given")
    _check_inputs(images_dir, names)  # before anything is written: a bad input leaves nothing
    out_dir.mkdir(parents=True, exist_ok=True)
    status: dict = {
        "success_paper": False, "aligned_ok": False, "registered": 0, "n_images": len(names),
        "points": 0, "reason": None, "wall_time_s": None, "seed": int(seed),
        "registered_names": [], "num_models": 0, "fy_over_fx": None,
        "mean_reproj_error_px": None, "settings": settings.to_json(),
        "num_threads": settings.num_threads, "matching_threads": settings.matching_threads,
    }
    problems = input_problems(images_dir, names)
    for p in problems:
        log.warning("COLMAP baseline input: %s", p)
    t0 = time.perf_counter()
    # removed however the run ends (a stop signal too), unless --keep-work moves it to out/work
    with scratch_dir(".colmap_work.", out_dir) as work:
        try:
            work_names = size_groups(images_dir, names)
            _link_images(images_dir, names, work / "images", work_names)
            reader, extraction, matching, verification, mapping = _options(settings, seed)
            db = work / "database.db"
            # pycolmap's own (glog) lines go to stderr, i.e. the stage log; its INFO chatter
            # (25-60 lines a call) only with -v, its errors always.
            pycolmap.logging.minloglevel = 0 if log.isEnabledFor(logging.DEBUG) else 2
            pycolmap.set_random_seed(int(seed))
            per_size = any(w != n for n, w in work_names.items())
            log.info("COLMAP baseline: %d training images (%s), seed %d, %d threads", len(names),
                     f"a camera for each of {len({w.split('/')[0] for w in work_names.values()})} image sizes"
                     if per_size else "one camera", seed, settings.num_threads)
            # each long pycolmap call runs where a stop signal ends it at once (runtime.native)
            t = time.perf_counter()
            log.info("feature extraction started")
            stoppable("feature extraction", pycolmap.extract_features, db, work / "images",
                      image_names=[work_names[n] for n in names],
                      camera_mode=pycolmap.CameraMode.PER_FOLDER if per_size else pycolmap.CameraMode.SINGLE,
                      reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
            log.info("feature extraction done in %.2f s", time.perf_counter() - t)
            t = time.perf_counter()
            log.info("exhaustive matching started")
            stoppable("exhaustive matching", pycolmap.match_exhaustive, db, matching_options=matching,
                      verification_options=verification, device=pycolmap.Device.cpu)
            log.info("exhaustive matching done in %.2f s", time.perf_counter() - t)
            t = time.perf_counter()
            (work / "sparse").mkdir()
            log.info("incremental mapping started")
            recs = {i: pycolmap.Reconstruction(str(work / "sparse" / str(i)))
                    for i in stoppable("incremental mapping", _map, db, work / "images", work / "sparse", mapping)}
            log.info("incremental mapping done in %.2f s: %d model(s)", time.perf_counter() - t,
                     len(recs))
            status["num_models"] = len(recs)
            _, rec = _largest(recs)
            if rec is not None and per_size:
                original = {w: n for n, w in work_names.items()}
                for image in rec.images.values():
                    image.name = original[image.name]
            sparse = out_dir / "sparse" / "0"
            if rec is None:
                status["reason"] = "no model: the incremental mapper found no initial image pair"
            else:
                reg = rec.num_reg_images()
                pts = rec.num_points3D()
                status["registered"] = int(reg)
                status["points"] = int(pts)
                status["registered_names"] = sorted(rec.images[i].name for i in rec.reg_image_ids())
                status["fy_over_fx"] = _fy_over_fx(rec)
                status["n_cameras"] = len(rec.cameras)
                if pts:
                    status["mean_reproj_error_px"] = float(rec.compute_mean_reprojection_error())
                with atomic_dir(sparse) as tmp:
                    rec.write_text(str(tmp))
                status["success_paper"] = paper_success(reg, pts)
                status["aligned_ok"] = bool(status["success_paper"] and reg >= MIN_ALIGN_IMAGES)
                if not status["success_paper"]:
                    status["reason"] = f"model has {reg} registered images and {pts} points"
            if rec is None and sparse.exists():
                shutil.rmtree(sparse)  # a stale model from an earlier run is not this result
        except Exception as exc:  # noqa: BLE001 - a failed reconstruction is a recorded result
            if isinstance(exc, (FileNotFoundError, ImageReadError)):
                raise
            log.warning("COLMAP baseline failed: %s", exc)
            status["reason"] = f"{type(exc).__name__}: {exc}"
        finally:
            if keep_work:
                dst = out_dir / "work"
                if dst.exists():
                    shutil.rmtree(dst)
                os.replace(work, dst)
    if problems and not status["success_paper"]:
        status["reason"] = "; ".join(problems) + (f" (COLMAP: {status['reason']})" if status["reason"] else "")
    status["input_problems"] = problems
    status["wall_time_s"] = time.perf_counter() - t0
    status["peak_rss_mb"] = peak_rss_mb()
    write_json(out_dir / "status.json", status)
    log.info("COLMAP baseline: success=%s, %d/%d registered, %d points, %.1f s%s",
             status["success_paper"], status["registered"], len(names), status["points"],
             status["wall_time_s"], "" if status["success_paper"] else f" ({status['reason']})")
    return status


def model_fingerprint(model_dir: str | Path) -> dict:
    """A comparable summary of a text model: names, poses, intrinsics, points (float64).

    Used to check that two seeded runs are identical. Returns a dict of sorted names ->
    (qvec, tvec) tuples, the camera parameters and the sorted point coordinates.
    """
    from camio.colmap import read_model

    model = read_model(model_dir)
    return {
        "poses": {c.name: np.round(c.cam_from_world, 12).tolist() for c in model.cameras},
        "K": {c.name: c.K.tolist() for c in model.cameras},
        "points": np.round(model.points[np.lexsort(model.points.T[::-1])], 12).tolist()
        if len(model.points) else [],
    }


if __name__ == "__main__":
    import sys

    from runtime.cliargs import not_a_command

    sys.exit(not_a_command("evaluation.initialisers.colmap_run", "python -m evaluation.initialisers.colmap_baseline"))
