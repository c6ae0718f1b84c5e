"""Bundle adjustment of a posed sparse model with pycolmap, the gauge held fixed.

Input and output are :class:`camio.colmap.SparseModel` (cameras cam_from_world in OpenCV axes,
PINHOLE, COLMAP pixel centres; points [N, 3] in the same world frame; observations per image:
pixel xy [M, 2] and point indices [M]). The model goes to pycolmap through a COLMAP text model
(the tracks are the observations), :func:`pycolmap.create_default_bundle_adjuster` solves

    min over {R_c, t_c (c > 0), X_p, (f_c)} sum_(c, p) rho(|| pi(K_c, R_c X_p + t_c) - x_cp ||^2),

(rho: soft-L1 with a 1-pixel scale by default, robust to wrong matches) and the result is read
back into a SparseModel in the same frame.

Gauge (7 degrees of freedom that reprojection cannot see): the first camera of the model (as
given, e.g. sorted by name) is held constant (6: rotation and position) and, during the solve,
one translation coordinate of another camera (pycolmap's ``TWO_CAMS_FROM_WORLD`` gauge; COLMAP
picks that camera). That coordinate of cam_from_world's t is not a length of the scene, so the
solution's scale can drift (15 % measured on the synthetic scene); afterwards the whole solution
is scaled about the first camera's centre so that the RMS distance of the camera centres from it
equals the input's (:func:`rescale_about_first_camera`, a similarity: reprojection errors are
unchanged). The first camera is therefore unchanged and the scale is the input's, so a seed in
the input's units (dense predicted depths) stays valid. This is the gauge of the training-time
refinement too (:mod:`splat_train.parts.pose`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from runtime.atomic import scratch_dir
from runtime.native import stoppable
from camio.cameras import project_points
from camio.colmap import SparseModel, read_model, write_text_model

__all__ = ["reprojection_errors", "rescale_about_first_camera", "bundle_adjust"]

log = logging.getLogger(__name__)


def reprojection_errors(model: SparseModel) -> np.ndarray:
    """Pixel distance between every observation and its point's projection.

    Args:
        model: cameras, points [N, 3] (world) and observations.

    Returns:
        [M] float64 errors over all observations of all cameras (pixels).
    """
    errs = []
    for cam in model.cameras:
        xy, idx = model.observations.get(cam.name, (np.zeros((0, 2)), np.zeros(0, int)))
        if len(idx):
            uv, _ = project_points(model.points[idx], cam.K, cam.cam_from_world)
            errs.append(np.linalg.norm(uv - xy, axis=1))
    return np.concatenate(errs) if errs else np.zeros(0)


def rescale_about_first_camera(model: SparseModel, ref_cameras: list) -> tuple[SparseModel, float]:
    """Scale ``model`` about its first camera's centre C_0 to the spread of ``ref_cameras``:

        s = sqrt(sum_c ||C_ref_c - C_ref_0||^2 / sum_c ||C_c - C_0||^2),
        X' = C_0 + s (X - C_0) for every point and camera centre, rotations unchanged.

    Args:
        model: cameras (first one = the fixed camera) and points [N, 3], world frame.
        ref_cameras: the cameras whose spread to restore, same order.

    Returns:
        (the rescaled model, s).
    """
    from camio.cameras import Camera

    c = np.stack([cam.center for cam in model.cameras])  # [C, 3] world
    r = np.stack([cam.center for cam in ref_cameras])
    den, num = float(((c - c[0]) ** 2).sum()), float(((r - r[0]) ** 2).sum())
    s = float(np.sqrt(num / den)) if den > 1e-24 and num > 1e-24 else 1.0
    cams = []
    for cam, ci in zip(model.cameras, c):
        new_c = c[0] + s * (ci - c[0])
        cams.append(Camera(cam.name, cam.width, cam.height, cam.K.copy(),
                           np.concatenate([cam.R, (-cam.R @ new_c)[:, None]], axis=1)))
    pts = c[0] + s * (np.asarray(model.points, np.float64) - c[0]) if len(model.points) else model.points
    return SparseModel(cams, pts, model.colors, model.observations, model.camera_models), s


def _solve(options, config, rec, out: Path) -> dict:
    """The bundle adjustment in :func:`runtime.native.stoppable`'s child: ``rec`` refined and
    written to ``out`` in COLMAP text form; returns ``termination`` and ``usable`` (a solver
    summary does not pickle)."""
    import pycolmap

    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    rec.write_text(str(out))
    return {"termination": str(summary.termination_type).split(".")[-1], "usable": bool(summary.is_solution_usable())}


def bundle_adjust(model: SparseModel, refine_focal: bool = False, loss_scale_px: float | None = 1.0,
                  max_iterations: int = 100, num_threads: int = 1) -> tuple[SparseModel, dict]:
    """Refine the cameras and points of ``model`` by bundle adjustment (module docstring).

    Args:
        model: >= 2 cameras with points and observations.
        refine_focal: also refine the focal length of each COLMAP camera (cameras with identical
            intrinsics share one); the principal point is never refined.
        loss_scale_px: soft-L1 scale in pixels; None: plain least squares.
        max_iterations: Ceres iterations.
        num_threads: Ceres threads.

    Returns:
        (refined model, same names and order; stats: ``reproj_error_px_before`` / ``after``
        (means), ``n_points``, ``n_observations``, ``termination``, ``usable``, ``wall_time_s``,
        ``gauge``, ``gauge_rescale`` (the scale s applied after the solve), ``refine_focal``).
    """
    import pycolmap

    if len(model.cameras) < 2 or not len(model.points):
        raise ValueError(f"bundle adjustment needs >= 2 cameras and >= 1 point, got "
                         f"{len(model.cameras)} cameras and {len(model.points)} points")
    t0 = time.perf_counter()
    before = reprojection_errors(model)
    with scratch_dir(".bundle_") as work:
        write_text_model(work / "in", model.cameras, model.points, model.colors, model.observations)
        rec = pycolmap.Reconstruction()
        rec.read(str(work / "in"))
        options = pycolmap.BundleAdjustmentOptions()
        options.refine_focal_length = bool(refine_focal)
        options.refine_principal_point = False
        options.refine_extra_params = False
        options.print_summary = False
        if loss_scale_px is not None:
            options.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
            options.ceres.loss_function_scale = float(loss_scale_px)
        options.ceres.solver_options.max_num_iterations = int(max_iterations)
        options.ceres.solver_options.num_threads = int(num_threads)
        config = pycolmap.BundleAdjustmentConfig()
        first = model.cameras[0].name
        for image_id, image in rec.images.items():
            config.add_image(image_id)
            if image.name == first:
                config.set_constant_rig_from_world_pose(image.frame_id)
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        (work / "out").mkdir()
        # a long solve runs where a stop signal ends it at once (runtime.native)
        summary = stoppable("bundle adjustment", _solve, options, config, rec, work / "out")
        out = read_model(work / "out")
    by_name = {c.name: c for c in out.cameras}
    cams = [by_name[c.name] for c in model.cameras]
    refined, scale = rescale_about_first_camera(
        SparseModel(cams, out.points, out.colors, out.observations, out.camera_models), model.cameras)
    after = reprojection_errors(refined)
    stats = {
        "reproj_error_px_before": float(before.mean()) if len(before) else None,
        "reproj_error_px_after": float(after.mean()) if len(after) else None,
        "n_points": int(len(refined.points)), "n_observations": int(len(after)),
        "termination": summary["termination"], "usable": summary["usable"],
        "gauge": f"first camera {first!r} constant; scale: RMS centre distance from it restored "
                 "(solved with pycolmap's TWO_CAMS_FROM_WORLD gauge)",
        "gauge_rescale": scale,
        "refine_focal": bool(refine_focal), "wall_time_s": time.perf_counter() - t0,
    }
    log.info("bundle adjustment: %d cameras, %d points, %d observations, reprojection %.3f -> %.3f px (%s) "
             "in %.2f s", len(cams), stats["n_points"], stats["n_observations"],
             stats["reproj_error_px_before"] or 0, stats["reproj_error_px_after"] or 0,
             stats["termination"], stats["wall_time_s"])
    return refined, stats
