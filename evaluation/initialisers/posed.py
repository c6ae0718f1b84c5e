"""The ground-truth-pose initialiser (``posed``): reference cameras + triangulated points.

On any scene with reference cameras (``sparse/0`` of a prepared scene) it takes the reference
cameras of the *training views only*, triangulates points from those views with pycolmap (SIFT,
exhaustive matching, triangulation with the poses and intrinsics held fixed;
:func:`evaluation.initialisers.triangulate.triangulate_known_poses`) and, when asked, applies the oracle's seeded
noise model (:class:`evaluation.initialisers.oracle.OracleNoise`):

* poses: :func:`evaluation.initialisers.oracle.perturb_cameras` (RMS rotation ``rot_deg``, centre noise
  ``trans_frac`` of the trajectory radius);
* points: each point's depth along the ray of the first training view that observes it becomes
  z (1 + e), e ~ N(0, depth_rel^2), a fraction ``outlier_frac`` with e ~ U(-0.5, 0.5); the point
  then moves with that view's pose noise (as the oracle unprojects with the noisy camera), so
  each view stays self-consistent and views disagree as much as their pose noise says.

This is the paper's Table II "full-dataset poses" row: the reference cameras were estimated
from *all* images of the scene (e.g. COLMAP on the full set, or the dataset's calibration),
so the row is an upper bound no sparse-view method can reach from n views alone. The
synthetic oracle (:mod:`evaluation.initialisers.oracle`) is its special case with exact geometry (dense
ground-truth depth instead of triangulated points).

Output (docs/contracts.md): ``DIR/sparse/0`` (COLMAP text: the cameras, the points with their
observations) and ``DIR/status.json`` (``success_paper``, ``aligned_ok``, ``registered``,
``points``, ``reason``, ``noise``, ``triangulation`` statistics, ``reference_source``, and
``fallback``: the CLI's random-point fallback when triangulation leaves fewer than
``--fallback-min-points``, :func:`evaluation.initialisers.random_init.apply_fallback`). The Bridge reads it
like the COLMAP baseline's model (uniform opacity: no confidence).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_dir, write_json
from camio.colmap import SparseModel, read_model, write_text_model
from evaluation.initialisers.oracle import OracleNoise, add_noise_args, perturb_cameras
from evaluation.metrics.pose import paper_success
from evaluation.initialisers.random_init import add_fallback_args, apply_fallback
from evaluation.initialisers.views import add_view_args, parse_training_args
from runtime.checks import check_folder, flag
from runtime.cliargs import add_log_flags, plain

__all__ = ["apply_noise", "run_posed", "REFERENCE_SOURCE"]

log = logging.getLogger(__name__)

REFERENCE_SOURCE = ("the scene's reference cameras, estimated from all of its images (not only the "
                    "n training views): the paper's Table II full-dataset-poses row")


def apply_noise(model: SparseModel, noise: OracleNoise, rng: np.random.Generator) -> SparseModel:
    """The oracle's noise model on a posed model with points (module docstring)."""
    if not any((noise.rot_deg, noise.trans_frac, noise.depth_rel, noise.outlier_frac)):
        return model
    noisy = perturb_cameras(model.cameras, noise, rng)
    by_name = {c.name: i for i, c in enumerate(model.cameras)}
    owner = np.full(len(model.points), -1)
    for name in sorted(model.observations, key=lambda n: by_name.get(n, 1 << 30)):
        _, idx = model.observations[name]
        free = idx[owner[idx] < 0]
        owner[free] = by_name[name]
    pts = model.points.copy()
    e = rng.normal(0, noise.depth_rel, len(pts))
    out = rng.random(len(pts)) < noise.outlier_frac
    e = np.where(out, rng.uniform(-0.5, 0.5, len(pts)), e)
    for i, (cam, ncam) in enumerate(zip(model.cameras, noisy)):
        sel = owner == i
        if not sel.any():
            continue
        p_cam = pts[sel] @ cam.R.T + cam.t  # exact camera frame
        p_cam *= (1 + e[sel])[:, None]  # depth noise along the ray
        pts[sel] = (p_cam - ncam.t) @ ncam.R  # back out through the noisy camera
    return SparseModel(noisy, pts, model.colors, model.observations, model.camera_models)


def run_posed(scene: str | Path, names: list[str], out_dir: str | Path, noise: OracleNoise = OracleNoise(),
              seed: int = 0, num_threads: int = 1) -> dict:
    """Write ``out_dir/sparse/0`` and ``out_dir/status.json`` (module docstring).

    Raises:
        ValueError: the scene has no reference cameras, or not for every training view.
    """
    from evaluation.initialisers.triangulate import triangulate_known_poses

    t0 = time.perf_counter()
    scene, out_dir = Path(scene), Path(out_dir)
    names = list(dict.fromkeys(names))
    if len(names) < 2:
        raise ValueError(f"posed: needs >= 2 training views, got {len(names)}")
    check_folder(scene, "posed: scene")  # NotAFolderError: missing, or a file given for it
    ref_dir = scene / "sparse" / "0"
    if not ref_dir.is_dir():
        raise ValueError(f"posed: {scene} has no reference cameras (sparse/0); the posed initialiser "
                         "needs a scene converted from a posed dataset")
    ref = read_model(ref_dir)
    missing = [n for n in names if n not in ref.names]
    if missing:
        raise ValueError(f"posed: training images {missing[:5]} have no reference camera in {ref_dir}")
    train = [ref.camera(n) for n in names]  # only the training views' cameras are used
    model, stats = triangulate_known_poses(scene / "images", train, num_threads=num_threads, seed=seed)
    model = apply_noise(model, noise, np.random.default_rng(seed))
    reg, pts = len(model.cameras), len(model.points)
    ok = paper_success(reg, pts)
    status = {
        "success_paper": ok, "aligned_ok": bool(ok and reg >= 3), "registered": reg,
        "n_images": len(names), "points": int(pts),
        "reason": None if ok else f"triangulation from the {reg} fixed training cameras gave {pts} points",
        "wall_time_s": None, "seed": int(seed), "noise": asdict(noise), "num_threads": int(num_threads),
        "triangulation": stats, "reference_source": REFERENCE_SOURCE,
    }
    with atomic_dir(out_dir / "sparse" / "0") as tmp:
        if pts:
            write_text_model(tmp, model.cameras, model.points, model.colors, model.observations)
        else:
            write_text_model(tmp, model.cameras)
    status["wall_time_s"] = time.perf_counter() - t0
    write_json(out_dir / "status.json", status)
    log.info("posed: %d training views, %d points (noise %s), success_paper=%s, %.1f s", reg, pts,
             asdict(noise), ok, status["wall_time_s"])
    return status


def main(argv: list[str] | None = None) -> int:
    """CLI: ``python -m evaluation.initialisers.posed --scene DIR (--image-list FILE | --names ...) --out DIR
    [--rot-deg --trans-frac --depth-rel --outlier-frac] [--seed S] [--threads T]``."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.posed", description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--scene", required=True, help="prepared scene with images/ and sparse/0")
    add_view_args(p, split=False)
    p.add_argument("--out", required=True, help="output folder (sparse/0, status.json)")
    add_noise_args(p, outliers="points")
    p.add_argument("--seed", type=flag(int, 0), default=0, help="random seed of the noise and of pycolmap")
    p.add_argument("--threads", type=flag(int, 1), default=1, help="feature extraction / matching threads")
    add_fallback_args(p)
    add_log_flags(p)
    args, names = parse_training_args(p, argv)
    noise = OracleNoise(args.rot_deg, args.trans_frac, args.depth_rel, args.outlier_frac)
    from runtime.outdir import prepare_out, run_stage

    def work() -> None:
        # the stage's name in its .stage marker stays the flat layout's (reruns into older folders)
        prepare_out(args.out, {"--scene": args.scene, "--image-list": args.image_list}, "evaluation.posed")
        run_posed(args.scene, names, args.out, noise, args.seed, args.threads)
        apply_fallback(args.out, args.fallback_min_points, args.fallback_points, args.seed)

    return run_stage(log, work)


if __name__ == "__main__":
    raise SystemExit(main())
