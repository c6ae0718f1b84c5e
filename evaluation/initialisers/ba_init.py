"""Bundle-adjustment refinement of an initialiser's cameras (``vggt_ba``, ``oracle_ba``,
``posed_ba``): the step the official VGGT demo runs before handing its result to gsplat.

From an initialiser's output folder (``sparse/0`` cameras, optionally ``predictions.npz``):

1. SIFT features and exhaustive matching on the training views, triangulation with the
   predicted poses and intrinsics held fixed (:func:`evaluation.initialisers.triangulate.triangulate_known_poses`,
   the COLMAP baseline's feature settings);
2. bundle adjustment of cameras and points with the first camera and the scale fixed, focal
   lengths optional (:func:`evaluation.initialisers.bundle.bundle_adjust`);
3. the seed: ``dense`` (default, when the input has ``predictions.npz``) keeps the dense
   predicted points, each view's points moved rigidly with its refined camera
   (:func:`move_points_with_cameras`); ``triangulated`` keeps the bundle-adjusted points
   (``sparse/0``, read by the Bridge like a COLMAP model).

Fallback: when matching or triangulation fails or yields fewer than ``min_points`` points (as
at n = 3 on hard scenes), or the adjustment is unusable or does not lower the reprojection
error, the unrefined prediction is written unchanged (the base model's training cameras with
all its points and their observations; ``predictions.npz`` as it was) and ``status.json`` records
``ba.fallback: true`` with the reason. Outputs (docs/contracts.md): ``DIR/sparse/0`` (COLMAP
text), ``DIR/predictions.npz`` (dense seed only), ``DIR/status.json``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_dir, save_npz, write_json
from camio.colmap import SparseModel, read_model, write_text_model
from runtime.names import check_name_list
from evaluation.metrics.pose import paper_success
from runtime.checks import flag
from runtime.cliargs import add_log_flags, plain

__all__ = ["SEED_POINTS", "DEFAULT_MIN_POINTS", "move_points_with_cameras", "refine_predictions", "run_ba_init"]

log = logging.getLogger(__name__)

SEED_POINTS = ("dense", "triangulated")
# Fewer triangulated points than this: the matches cannot constrain the cameras; fall back.
DEFAULT_MIN_POINTS = 20


def move_points_with_cameras(points: np.ndarray, old_cam_from_world: np.ndarray,
                             new_cam_from_world: np.ndarray) -> np.ndarray:
    """Move one view's world points rigidly with its camera (their camera-frame coordinates
    are kept): p' = R_new^T (R_old p + t_old - t_new).

    Args:
        points: [..., 3] world points predicted for the view (old world frame).
        old_cam_from_world, new_cam_from_world: [3, 4] the view's camera before and after.

    Returns:
        [..., 3] points in the same dtype.
    """
    old = np.asarray(old_cam_from_world, np.float64)
    new = np.asarray(new_cam_from_world, np.float64)
    p_cam = np.asarray(points, np.float64) @ old[:, :3].T + old[:, 3]
    return ((p_cam - new[:, 3]) @ new[:, :3]).astype(np.asarray(points).dtype)


def refine_predictions(pred: dict, old: dict, new: dict) -> dict:
    """``predictions.npz`` arrays with the refined cameras and each view's points moved.

    Args:
        pred: the arrays of ``predictions.npz`` (docs/contracts.md).
        old, new: image name -> Camera before / after refinement (same frame as ``pred``).

    Returns:
        A new dict: ``cam_from_world`` [S, 3, 4] refined, ``world_points`` [S, H, W, 3] moved,
        ``intrinsics`` / ``intrinsics_original`` focal lengths scaled by the refined focal
        ratio; every other key (``depth`` is camera-frame: unchanged) as given.
    """
    out = dict(pred)
    names = [str(n) for n in pred["image_names"]]
    cfw = np.array(pred["cam_from_world"], copy=True)
    wp = np.array(pred["world_points"], copy=True)
    k_net = np.array(pred["intrinsics"], copy=True)
    k_orig = np.array(pred["intrinsics_original"], copy=True)
    for s, name in enumerate(names):
        if name not in new:
            continue
        wp[s] = move_points_with_cameras(wp[s], old[name].cam_from_world, new[name].cam_from_world)
        cfw[s] = new[name].cam_from_world.astype(cfw.dtype)
        ratio = new[name].K[0, 0] / old[name].K[0, 0]
        for k in (k_net, k_orig):
            k[s, 0, 0] *= ratio
            k[s, 1, 1] *= ratio
    out.update(cam_from_world=cfw, world_points=wp, intrinsics=k_net, intrinsics_original=k_orig)
    return out


def _refine(images: Path, cameras: list, refine_focal: bool, min_points: int, seed: int,
            num_threads: int) -> tuple[SparseModel | None, dict, str | None]:
    """(refined model or None, stats, fallback reason or None)."""
    from evaluation.initialisers.bundle import bundle_adjust
    from evaluation.initialisers.triangulate import triangulate_known_poses

    stats: dict = {"triangulation": None, "bundle_adjustment": None}
    try:
        tri, stats["triangulation"] = triangulate_known_poses(images, cameras, num_threads=num_threads, seed=seed)
    except (RuntimeError, ValueError) as exc:  # pycolmap raises RuntimeError on failed steps
        return None, stats, f"feature matching / triangulation failed: {exc}"
    if len(tri.points) < min_points:
        return None, stats, (f"too few matches: {len(tri.points)} triangulated points "
                             f"({stats['triangulation']['verified_pairs']} verified pairs) < min_points "
                             f"{min_points}")
    try:
        refined, stats["bundle_adjustment"] = bundle_adjust(tri, refine_focal=refine_focal, num_threads=num_threads)
    except (RuntimeError, ValueError) as exc:
        return None, stats, f"bundle adjustment failed: {exc}"
    ba = stats["bundle_adjustment"]
    if not ba["usable"]:
        return None, stats, f"bundle adjustment unusable ({ba['termination']})"
    if ba["reproj_error_px_after"] > ba["reproj_error_px_before"]:
        return None, stats, (f"bundle adjustment raised the reprojection error "
                             f"({ba['reproj_error_px_before']:.3f} -> {ba['reproj_error_px_after']:.3f} px)")
    return refined, stats, None


def run_ba_init(init_dir: str | Path, images: str | Path, names: list[str], out_dir: str | Path,
                refine_focal: bool = False, seed_points: str = "dense", min_points: int = DEFAULT_MIN_POINTS,
                seed: int = 0, num_threads: int = 1) -> dict:
    """Refine the initialiser output in ``init_dir`` and write ``out_dir`` (module docstring).

    Args:
        init_dir: an initialiser's folder with ``sparse/0`` (and ``predictions.npz`` for the
            dense seed).
        images: the scene's images (the sizes of the ``sparse/0`` cameras).
        names: training image names (only these cameras are refined and written).
        refine_focal: also refine focal lengths.
        seed_points: "dense" or "triangulated".
        min_points: fewer triangulated points than this falls back.
        seed, num_threads: pycolmap's seed and threads (1 = reproducible).

    Returns:
        The status.json record.
    """
    if seed_points not in SEED_POINTS:
        raise ValueError(f"seed_points must be one of {SEED_POINTS}, got {seed_points!r}")
    t0 = time.perf_counter()
    init_dir, out_dir = Path(init_dir), Path(out_dir)
    pred_path = init_dir / "predictions.npz"
    if seed_points == "dense" and not pred_path.is_file():
        raise ValueError(f"ba: --seed-points dense needs {pred_path} (a VGGT or oracle output); "
                         "use --seed-points triangulated for a COLMAP-model initialiser")
    if seed_points == "dense":  # its names become file names downstream: refused before anything is written
        with np.load(pred_path, allow_pickle=False) as z:
            check_name_list([str(n) for n in z["image_names"]], pred_path)
    given = read_model(init_dir / "sparse" / "0")
    missing = [n for n in names if n not in given.names]
    if missing:
        raise ValueError(f"ba: training images {missing[:5]} are not in {init_dir / 'sparse' / '0'}")
    cams = [given.camera(n) for n in names]
    refined, stats, reason = _refine(Path(images), cams, refine_focal, min_points, seed, num_threads)
    if refined is None:  # the base model as it came: its training cameras and every point
        log.warning("ba: falling back to the unrefined prediction: %s", reason)
        final = given.subset(names)
    else:
        final = refined
    with atomic_dir(out_dir / "sparse" / "0") as tmp:
        if len(final.points):
            write_text_model(tmp, final.cameras, final.points, final.colors, final.observations)
        else:
            write_text_model(tmp, final.cameras)
    if seed_points == "dense":
        with np.load(pred_path, allow_pickle=False) as z:
            pred = {k: z[k] for k in z.files}
        if refined is not None:
            pred = refine_predictions(pred, {c.name: c for c in cams}, {c.name: c for c in final.cameras})
        save_npz(out_dir / "predictions.npz", **pred)
    reg = len(final.cameras)
    if seed_points == "dense":
        pts = int(np.isfinite(pred["world_points"]).all(-1).sum())
    else:
        pts = len(final.points)
    ok = paper_success(reg, pts)
    status = {
        "success_paper": ok, "aligned_ok": bool(ok and reg >= 3), "registered": reg, "n_images": len(names),
        "points": int(pts), "reason": None if ok else "no seed points",
        "ba": {"applied": refined is not None, "fallback": refined is None, "fallback_reason": reason,
               "refine_focal": bool(refine_focal), "seed_points": seed_points, "min_points": int(min_points),
               **stats},
        "init": str(init_dir), "seed": int(seed), "num_threads": int(num_threads),
        "wall_time_s": time.perf_counter() - t0,
    }
    write_json(out_dir / "status.json", status)
    log.info("ba: %s, %d cameras, seed %s (%d points) -> %s in %.1f s",
             "refined" if refined is not None else f"fallback ({reason})", reg, seed_points, pts, out_dir,
             status["wall_time_s"])
    return status


def main(argv: list[str] | None = None) -> int:
    """CLI: ``python -m evaluation.initialisers.ba_init --init DIR --images DIR --image-list FILE --out DIR
    [--refine-focal] [--seed-points dense|triangulated] [--min-points N] [--seed S] [--threads T]``."""
    import argparse

    from runtime.logs import setup_logging

    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.ba_init", description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--init", required=True, help="initialiser output folder (sparse/0, predictions.npz)")
    p.add_argument("--images", required=True, help="the scene's images folder")
    p.add_argument("--image-list", required=True, help="file with one training image name per line")
    p.add_argument("--out", required=True, help="output folder (sparse/0, predictions.npz, status.json)")
    p.add_argument("--refine-focal", action="store_true", help="also refine focal lengths")
    p.add_argument("--seed-points", choices=SEED_POINTS, default="dense",
                   help="dense predicted points moved with the refined cameras, or the triangulated points")
    p.add_argument("--min-points", type=flag(int, 1), default=DEFAULT_MIN_POINTS,
                   help=f"fewer triangulated points fall back (default {DEFAULT_MIN_POINTS})")
    p.add_argument("--seed", type=flag(int, 0), default=0, help="pycolmap's random seed")
    p.add_argument("--threads", type=flag(int, 1), default=1,
                   help="pycolmap threads of the triangulation (its feature extraction and matching) and of "
                        "the bundle adjustment; 1 (the default) is reproducible")
    add_log_flags(p)
    args = p.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    names = [x.strip() for x in Path(args.image_list).read_text().splitlines() if x.strip()]
    from runtime.outdir import prepare_out, run_stage

    def work() -> None:
        # the stage's name in its .stage marker stays the flat layout's (reruns into older folders)
        prepare_out(args.out, {"--init": args.init, "--images": args.images, "--image-list": args.image_list},
                    "evaluation.ba_init")
        run_ba_init(args.init, args.images, names, args.out, args.refine_focal, args.seed_points,
                    args.min_points, args.seed, args.threads)

    return run_stage(log, work)


if __name__ == "__main__":
    raise SystemExit(main())
