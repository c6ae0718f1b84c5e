"""Points from known cameras: SIFT features, exhaustive matching and triangulation with the
poses and intrinsics held fixed, through pycolmap (``colmap point_triangulator``).

Used by the ``posed`` initialiser (:mod:`evaluation.initialisers.posed`). Cameras follow :mod:`camio`
(cam_from_world, OpenCV axes, COLMAP pixel centres, PINHOLE); the images must be the files the
cameras were made for (same size).
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np

from runtime.atomic import scratch_dir
from runtime.native import stoppable
from camio.cameras import Camera, rotmat_to_qvec
from camio.colmap import SparseModel, cpu_matching_options, read_model
from evaluation.initialisers.colmap_run import MAX_IMAGE_SIZE, MAX_NUM_FEATURES

__all__ = ["triangulate_known_poses"]

log = logging.getLogger(__name__)


def _triangulate(rec, db: Path, images: Path, out: Path, opts, model: Path) -> None:
    """``pycolmap.triangulate_points`` in :func:`runtime.native.stoppable`'s child, the result
    written to ``model`` in COLMAP text form (a ``pycolmap.Reconstruction`` does not pickle)."""
    import pycolmap

    tri = pycolmap.triangulate_points(rec, db, images, out, clear_points=True, options=opts,
                                      refine_intrinsics=False)
    tri.write_text(str(model))


def triangulate_known_poses(image_dir: str | Path, cameras: list[Camera], num_threads: int = 1,
                            max_image_size: int = MAX_IMAGE_SIZE, max_num_features: int = MAX_NUM_FEATURES,
                            seed: int = 0) -> tuple[SparseModel, dict]:
    """Triangulate points seen in ``cameras``' images with the cameras held fixed.

    Args:
        image_dir: folder holding every ``camera.name``.
        cameras: the posed pinhole cameras (>= 2).
        num_threads: threads for extraction and triangulation (1 = reproducible); matching
            always runs on :data:`camio.colmap.MATCHING_THREADS`.
        max_image_size, max_num_features: SIFT settings (the COLMAP baseline's defaults).
        seed: pycolmap's PRNG and RANSAC seed.

    Returns:
        (model: the same cameras with the triangulated points, colours and observations;
        stats: ``n_points``, ``mean_track_length``, ``mean_reproj_error_px``,
        ``verified_pairs``, ``wall_time_s``).
    """
    import pycolmap

    t0 = time.perf_counter()
    image_dir = Path(image_dir)
    if len(cameras) < 2:
        raise ValueError("triangulation needs at least 2 posed images")
    missing = [c.name for c in cameras if not (image_dir / c.name).is_file()]
    if missing:
        raise FileNotFoundError(f"images {missing[:5]} are missing from {image_dir}")
    with scratch_dir(".triangulate_") as work:
        images = work / "images"
        for c in cameras:
            dst = images / c.name
            dst.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.symlink((image_dir / c.name).resolve(), dst)
            except OSError:
                shutil.copy2(image_dir / c.name, dst)
        db = work / "database.db"
        pycolmap.set_random_seed(int(seed))
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = max_image_size
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = max_num_features
        # each long pycolmap call runs where a stop signal ends it at once (runtime.native)
        log.info("feature extraction started")
        stoppable("feature extraction", pycolmap.extract_features, db, images, [c.name for c in cameras],
                  camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                  extraction_options=extraction, device=pycolmap.Device.cpu)
        by_name = {c.name: c for c in cameras}
        database = pycolmap.Database.open(str(db))
        try:
            ids = {}
            for im in database.read_all_images():
                cam = by_name[im.name]
                dbcam = database.read_camera(im.camera_id)
                dbcam.width, dbcam.height = cam.width, cam.height
                dbcam.params = [cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]]
                dbcam.has_prior_focal_length = True
                database.update_camera(dbcam)
                ids[im.name] = (im.image_id, im.camera_id)
        finally:
            database.close()
        matching = cpu_matching_options()  # one thread: see camio.colmap.MATCHING_THREADS
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed
        log.info("exhaustive matching started")
        stoppable("exhaustive matching", pycolmap.match_exhaustive, db, matching_options=matching,
                  verification_options=verification, device=pycolmap.Device.cpu)
        database = pycolmap.Database.open(str(db))
        try:
            verified = int(database.num_verified_image_pairs())
        finally:
            database.close()
        # the known model, with the database's image and camera ids, in COLMAP text form
        known = work / "known"
        known.mkdir()
        cam_lines, img_lines = [], []
        for name, (iid, cid) in sorted(ids.items(), key=lambda kv: kv[1][0]):
            c = by_name[name]
            cam_lines.append(f"{cid} PINHOLE {c.width} {c.height} "
                             + " ".join(repr(float(x)) for x in (c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2])))
            img_lines += [f"{iid} " + " ".join(repr(float(x)) for x in (*rotmat_to_qvec(c.R), *c.t))
                          + f" {cid} {name}", ""]
        (known / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
        (known / "images.txt").write_text("\n".join(img_lines) + "\n")
        (known / "points3D.txt").write_text("")
        rec = pycolmap.Reconstruction()
        rec.read(str(known))
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = num_threads
        opts.random_seed = seed
        opts.triangulation.random_seed = seed
        # sparse views: most tracks span two images; COLMAP's default drops those (it expects
        # a dense capture), which leaves a handful of points from 3 wide-baseline views
        opts.triangulation.ignore_two_view_tracks = False
        out = work / "triangulated"
        out.mkdir()
        (work / "model").mkdir()
        log.info("triangulation started")
        stoppable("triangulation", _triangulate, rec, db, images, out, opts, work / "model")
        model = read_model(work / "model")
    # the poses must not have moved (fixed in the triangulator); keep the caller's exactly
    got = {c.name: c for c in model.cameras}
    for c in cameras:
        d = np.abs(got[c.name].cam_from_world - c.cam_from_world).max()
        if d > 1e-6 * max(1.0, np.abs(c.cam_from_world).max()):
            raise RuntimeError(f"triangulation moved camera {c.name} by {d:g}; expected fixed poses")
    model = SparseModel(list(cameras), model.points, model.colors, model.observations)
    tracks = np.bincount(np.concatenate([idx for _, idx in model.observations.values()] or [np.zeros(0, int)]),
                         minlength=len(model.points)) if len(model.points) else np.zeros(0)
    errs = []
    for c in cameras:
        xy, idx = model.observations.get(c.name, (np.zeros((0, 2)), np.zeros(0, int)))
        if len(idx):
            from camio.cameras import project_points

            uv, _ = project_points(model.points[idx], c.K, c.cam_from_world)
            errs.append(np.linalg.norm(uv - xy, axis=1))
    stats = {
        "n_points": int(len(model.points)),
        "mean_track_length": float(tracks.mean()) if len(tracks) else None,
        "mean_reproj_error_px": float(np.concatenate(errs).mean()) if errs else None,
        "verified_pairs": verified,
        "wall_time_s": time.perf_counter() - t0,
    }
    log.info("triangulated %d points from %d fixed cameras (%d verified pairs, track %.2f, reproj %.3f px) "
             "in %.1f s", stats["n_points"], len(cameras), verified, stats["mean_track_length"] or 0,
             stats["mean_reproj_error_px"] or 0, stats["wall_time_s"])
    return model, stats
