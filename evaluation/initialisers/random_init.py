"""The random-point initialiser (``random``): the given cameras and points placed at random.

3DGS's floor: the 3DGS paper starts its synthetic scenes from 100k random points in a cube,
and sparse-view papers report "3DGS, random points" as the row every initialiser must beat.
Here the points fill the volume the training cameras see, not a fixed cube, so the row means
the same on any scene scale.

Volume (the documented choice): a point is kept when at least ``min_views`` training cameras
see it (inside the image, camera depth in [near, far]); ``min_views`` = min(2, n views), the
region the views share. Points are uniform in that volume (rejection sampling from the
bounding box of the frusta between near and far), so every part of it gets points in
proportion to its size, as in 3DGS's cube.

Depth range, from the cameras alone (no point, depth or image content is used):

* the focus point: the point nearest, in least squares, to every training camera's optical
  axis; when the axes converge (the smallest eigenvalue of sum(I - d d^T) is at least
  ``1e-3`` of n) and it lies in front of every camera, the focus depth D is the median of its
  camera depths;
* otherwise (parallel axes, as in forward-facing captures; one camera) D is
  :data:`PARALLEL_DEPTH_BASELINES` times the largest distance between two training centres;
* near = :data:`NEAR_FRAC` D, far = :data:`FAR_FRAC` D; ``--near``/``--far`` override both
  (scene units). One camera, or coincident centres, without ``--near``/``--far`` is an error.

Count: :data:`N_POINTS` (3DGS's 100k), but never more than :data:`POINTS_PER_PIXEL` per training
pixel (summed over the training views at their camera sizes; :func:`default_points`). On the
field's benchmark scenes the 100k stands (LLFF at 1/8, three views: 571k pixels, a limit of
143k); a small scene is not seeded with more points than it has pixels to constrain them (the
bundled 128x96 scene at n = 3: 9,216 points instead of 100k).
``--points`` / ``--fallback-points`` give a count outright.

Colours are 3DGS's: SH DC drawn from U(0, 1/255), i.e. RGB 0.5 + C0 U(0, 1/255), mid grey
(uint8 128) after the 8-bit storage of a COLMAP model.

Output (docs/contracts.md): ``DIR/sparse/0`` (COLMAP text: the given cameras, the random points,
no observations, so the Bridge writes no depth prior) and ``DIR/status.json`` (the COLMAP
baseline's keys: ``success_paper``, ``aligned_ok``, ``registered``, ``n_images``, ``points``,
``reason``, ``wall_time_s``, ``seed``; plus ``random``: ``near``, ``far``, ``depth_source``,
``min_views``, ``n_points``, and ``cameras_source``).

Fallback (:func:`apply_fallback`): when ``posed`` or the COLMAP baseline leaves fewer than
``min_points`` points but at least one registered camera, their CLIs write random points for
those cameras to ``DIR/random_fallback/sparse/0`` and record ``fallback`` in status.json;
``DIR/sparse/0``, ``points`` and both success criteria stay those of the reconstruction.
:func:`seed_model_dir` says which model the Bridge seeds from.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from runtime.atomic import write_json
from camio.cameras import Camera
from camio.colmap import read_model, write_text_model
from camio.ply import SH_C0
from evaluation.metrics.pose import paper_success
from evaluation.initialisers.views import read_image_list
from runtime.checks import flag
from runtime.cliargs import add_log_flags, plain

__all__ = ["N_POINTS", "POINTS_PER_PIXEL", "default_points", "FALLBACK_MIN_POINTS", "NEAR_FRAC", "FAR_FRAC", "PARALLEL_DEPTH_BASELINES",
           "FALLBACK_DIR", "depth_range", "random_points", "run_random", "apply_fallback", "seed_model_dir",
           "add_fallback_args"]

log = logging.getLogger(__name__)

#: points the random initialiser places (3DGS's random initialisation of its synthetic scenes)
N_POINTS = 100_000
#: the most points per training pixel (:func:`default_points`)
POINTS_PER_PIXEL = 0.25
#: posed / COLMAP runs with fewer points than this (and >= 1 camera) train from random points
FALLBACK_MIN_POINTS = 100
#: near and far depth as fractions of the focus depth D (module docstring)
NEAR_FRAC = 0.2
FAR_FRAC = 2.0
#: D in units of the largest distance between training centres when the axes do not converge
PARALLEL_DEPTH_BASELINES = 10.0
#: where the fallback's model goes, inside the initialiser's folder
FALLBACK_DIR = "random_fallback"
_GREY = 128
_BATCH = 65_536
_MAX_DRAWS = 400


def depth_range(cameras: list[Camera]) -> tuple[float, float, str]:
    """(near, far, how D was found) of the training cameras (module docstring).

    Args:
        cameras: the training cameras, ``cam_from_world`` in any one world frame.

    Raises:
        ValueError: no camera, or every centre at one place (no scale to derive a range from).
    """
    if not cameras:
        raise ValueError("random_init: no cameras to place points for")
    centres = np.stack([c.center for c in cameras])  # [S, 3] world
    axes = np.stack([c.R[2] for c in cameras])  # [S, 3] world direction of each camera's +z
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(centres, axes):
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ o
    if len(cameras) >= 2 and np.linalg.eigvalsh(a)[0] >= 1e-3 * len(cameras):
        focus = np.linalg.solve(a, b)
        depths = np.array([(c.R @ focus + c.t)[2] for c in cameras])
        if np.all(depths > 0):
            d = float(np.median(depths))
            return NEAR_FRAC * d, FAR_FRAC * d, "focus point of the optical axes"
    spread = max((float(np.linalg.norm(p - q)) for i, p in enumerate(centres) for q in centres[i + 1:]),
                 default=0.0)
    if spread <= 0:
        raise ValueError("random_init: the training cameras share one centre (or there is one camera), so "
                         "no depth range follows from them; give --near and --far (scene units)")
    d = PARALLEL_DEPTH_BASELINES * spread
    return NEAR_FRAC * d, FAR_FRAC * d, f"{PARALLEL_DEPTH_BASELINES:g} x the largest baseline (axes do not converge)"


def _views_seeing(points: np.ndarray, cameras: list[Camera], near: float, far: float) -> np.ndarray:
    """[N] int: how many cameras see each of ``points`` [N, 3] (world) inside the image at a
    camera depth in [near, far] (pixels in camio's convention: [0, W] x [0, H])."""
    count = np.zeros(len(points), dtype=np.int64)
    for c in cameras:
        pc = points @ c.R.T + c.t  # [N, 3] camera frame
        z = pc[:, 2]
        ok = (z >= near) & (z <= far)
        uv = pc[:, :2] / np.where(ok, z, 1.0)[:, None] @ c.K[:2, :2].T + c.K[:2, 2]
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= c.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= c.height)
        count += ok
    return count


def _frusta_box(cameras: list[Camera], near: float, far: float) -> tuple[np.ndarray, np.ndarray]:
    """([3], [3]) world bounding box of every camera's frustum between near and far."""
    corners = []
    for c in cameras:
        pix = np.array([[0, 0], [c.width, 0], [0, c.height], [c.width, c.height]], dtype=np.float64)
        rays = np.c_[(pix - c.K[:2, 2]) / np.diag(c.K)[:2], np.ones(4)]  # [4, 3] camera frame, z = 1
        for z in (near, far):
            corners.append((rays * z - c.t) @ c.R)  # camera -> world: R^T (x - t)
    pts = np.concatenate(corners)
    return pts.min(0), pts.max(0)


def random_points(cameras: list[Camera], n_points: int, rng: np.random.Generator, near: float, far: float,
                  min_views: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n_points`` points uniform in the volume that ``min_views`` cameras see (module docstring).

    Args:
        cameras: training cameras (world frame of their ``cam_from_world``).
        n_points: how many (> 0).
        rng: the generator (seeded by the caller).
        near, far: camera-depth range, 0 < near < far, scene units.
        min_views: views that must see a point; default min(2, number of cameras).

    Returns:
        points [n_points, 3] float64 world, colors [n_points, 3] uint8 (mid grey).

    Raises:
        ValueError: bad arguments, or the shared volume is too small to be sampled (the
            message gives the acceptance seen).
    """
    if n_points <= 0:
        raise ValueError(f"random_init: n_points must be > 0, got {n_points}")
    if not cameras:
        raise ValueError("random_init: no cameras to place points for")
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"random_init: need 0 < near < far, got near={near}, far={far}")
    k = min(2, len(cameras)) if min_views is None else int(min_views)
    if not 1 <= k <= len(cameras):
        raise ValueError(f"random_init: min_views must be in [1, {len(cameras)}], got {min_views}")
    lo, hi = _frusta_box(cameras, near, far)
    kept: list[np.ndarray] = []
    have, drawn = 0, 0
    while have < n_points:
        # refuse once the acceptance seen so far says the points would need over _MAX_DRAWS batches
        if drawn >= 4 * _BATCH and (have == 0 or n_points * drawn / have > _MAX_DRAWS * _BATCH):
            raise ValueError(f"random_init: only {have} of {drawn} candidate points are seen by {k} views; "
                             "the cameras share almost no volume between near and far (lower min_views or "
                             "widen --near/--far)")
        cand = lo + rng.random((_BATCH, 3)) * (hi - lo)
        drawn += _BATCH
        cand = cand[_views_seeing(cand, cameras, near, far) >= k]
        kept.append(cand)
        have += len(cand)
    points = np.concatenate(kept)[:n_points]
    sh_dc = rng.random((n_points, 3)) / 255.0  # 3DGS: shs = random / 255, rgb = 0.5 + C0 * shs
    colors = np.clip(np.rint((0.5 + SH_C0 * sh_dc) * 255.0), 0, 255).astype(np.uint8)
    return points, colors


def default_points(cameras: list[Camera]) -> int:
    """min(N_POINTS, POINTS_PER_PIXEL x the training pixels), at least 1 (module docstring)."""
    pixels = sum(int(c.width) * int(c.height) for c in cameras)
    return max(1, min(N_POINTS, int(POINTS_PER_PIXEL * pixels)))


def _place(cameras: list[Camera], n_points: int | None, seed: int, near: float | None, far: float | None) -> dict:
    if (near is None) != (far is None):
        raise ValueError("random_init: give both --near and --far, or neither")
    source = "given (--near/--far)"
    if near is None:
        near, far, source = depth_range(cameras)
    if n_points is None:
        n_points = default_points(cameras)
    points, colors = random_points(cameras, n_points, np.random.default_rng(seed), near, far)
    return {"points": points, "colors": colors, "near": float(near), "far": float(far), "depth_source": source,
            "min_views": min(2, len(cameras)), "n_points": int(n_points)}


def run_random(cameras_dir: str | Path, names: list[str], out_dir: str | Path, n_points: int | None = None,
               seed: int = 0, near: float | None = None, far: float | None = None) -> dict:
    """Write ``out_dir/sparse/0`` and ``out_dir/status.json`` (module docstring).

    Args:
        cameras_dir: a COLMAP model holding a camera for every training view (e.g. a scene's
            reference cameras, ``<scene>/sparse/0``); only the training views' are used.
        names: the training image names.
        n_points: points to place (None: :func:`default_points` of the training cameras).

    Raises:
        ValueError: a training view without a camera, or the errors of :func:`random_points`.
    """
    t0 = time.perf_counter()
    names = list(dict.fromkeys(names))
    model = read_model(cameras_dir)
    missing = [n for n in names if n not in model.names]
    if missing:
        raise ValueError(f"random_init: training images {missing[:5]} have no camera in {cameras_dir}")
    cams = [model.camera(n) for n in names]
    placed = _place(cams, n_points, seed, near, far)
    out_dir = Path(out_dir)
    write_text_model(out_dir / "sparse" / "0", cams, placed["points"], placed["colors"])
    reg, pts = len(cams), len(placed["points"])
    status = {
        "success_paper": paper_success(reg, pts), "aligned_ok": reg >= 3, "registered": reg,
        "n_images": len(names), "points": pts, "reason": None, "wall_time_s": time.perf_counter() - t0,
        "seed": int(seed), "cameras_source": str(cameras_dir),
        "random": {k: placed[k] for k in ("near", "far", "depth_source", "min_views", "n_points")},
    }
    write_json(out_dir / "status.json", status)
    log.info("random: %d points seen by >= %d of %d views, depth %.3g..%.3g (%s), %.1f s", pts,
             placed["min_views"], reg, placed["near"], placed["far"], placed["depth_source"], status["wall_time_s"])
    return status


def apply_fallback(init_dir: str | Path, min_points: int = FALLBACK_MIN_POINTS, n_points: int | None = None,
                   seed: int = 0) -> dict:
    """Random points for an initialiser that left too few (module docstring), recorded in its
    status.json under ``fallback``: ``applied``, ``min_points``, and when applied ``reason``,
    ``points_found`` (the reconstruction's), ``model`` (relative to ``init_dir``), ``n_points``,
    ``near``, ``far``, ``depth_source``; ``error`` when it was needed but no volume could be
    filled (one registered camera), the run's own result then standing alone. ``min_points`` = 0
    turns the fallback off; ``n_points`` None: :func:`default_points` of the registered cameras.

    Returns:
        The updated status record ({} when ``init_dir`` has no status.json).
    """
    init_dir = Path(init_dir)
    if not (init_dir / "status.json").is_file():  # the initialiser recorded nothing to fall back from
        log.warning("random-point fallback: %s has no status.json; nothing to decide", init_dir)
        return {}
    status = json.loads((init_dir / "status.json").read_text())
    found, reg = int(status.get("points") or 0), int(status.get("registered") or 0)
    model_dir = init_dir / "sparse" / "0"
    fb: dict = {"applied": False, "min_points": int(min_points)}
    if min_points > 0 and found < min_points and reg >= 1 and model_dir.is_dir():
        cams = read_model(model_dir).cameras
        try:
            placed = _place(cams, n_points, seed, None, None)
        except ValueError as exc:  # e.g. one registered camera: no volume to fill; the run's result stands
            fb["error"] = str(exc)
            log.warning("random-point fallback not possible: %s", exc)
            status["fallback"] = fb
            write_json(init_dir / "status.json", status)
            return status
        write_text_model(init_dir / FALLBACK_DIR / "sparse" / "0", cams, placed["points"], placed["colors"])
        fb.update({"applied": True, "points_found": found, "model": f"{FALLBACK_DIR}/sparse/0",
                   "reason": f"{found} points < min_points {min_points} with {reg} registered cameras: "
                             f"trained from {placed['n_points']} random points",
                   **{k: placed[k] for k in ("n_points", "near", "far", "depth_source")}})
        log.warning("random-point fallback: %s", fb["reason"])
    status["fallback"] = fb
    write_json(init_dir / "status.json", status)
    return status


def seed_model_dir(init_dir: str | Path, *, only_without_points: bool = False) -> Path:
    """The COLMAP model the Bridge seeds from: the fallback's when status.json says it applied,
    else ``init_dir/sparse/0``.

    ``only_without_points``: the fallback only when the views triangulated no point at all
    (the sparse-view benchmark's cells keep a few measured points over random ones, and read a
    missing status.json as no fallback)."""
    init_dir = Path(init_dir)
    status_path = init_dir / "status.json"
    if only_without_points and not status_path.is_file():
        return init_dir / "sparse" / "0"
    status = json.loads(status_path.read_text())
    fb = status.get("fallback") or {}
    use = fb.get("applied") and (not only_without_points or (status.get("points") == 0 and fb.get("model")))
    return init_dir / fb["model"] if use else init_dir / "sparse" / "0"


def add_fallback_args(parser) -> None:
    """``--fallback-min-points`` and ``--fallback-points`` (defaults: the constants above)."""
    parser.add_argument("--fallback-min-points", type=flag(int, 0), default=FALLBACK_MIN_POINTS,
                        help="with fewer points than this and >= 1 camera, write random points for the "
                             f"cameras to {FALLBACK_DIR}/sparse/0 and record it (default {FALLBACK_MIN_POINTS}; "
                             "0 = off)")
    parser.add_argument("--fallback-points", type=flag(int, 1), default=None,
                        help=f"random points of the fallback (default: {N_POINTS}, at most {POINTS_PER_PIXEL} "
                             "per training pixel)")


def main(argv: list[str] | None = None) -> int:
    """CLI: ``python -m evaluation.initialisers.random_init --cameras MODEL --image-list FILE --out DIR
    [--points N] [--seed S] [--near Z --far Z]``; ``seed-model DIR`` prints the model the Bridge
    seeds from (:func:`seed_model_dir`)."""
    import argparse
    import sys

    from runtime.outdir import prepare_out, run_stage
    from runtime.logs import setup_logging

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["seed-model"]:
        if len(argv) != 2:
            raise SystemExit("usage: python -m evaluation.initialisers.random_init seed-model INIT_DIR")
        try:
            print(seed_model_dir(argv[1]))
        except (OSError, ValueError, KeyError) as exc:
            print(f"error: cannot read {argv[1]}/status.json: {exc}", file=sys.stderr)
            return 2
        return 0
    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.random_init",
                                description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--cameras", required=True, help="COLMAP model with a camera per training view "
                   "(e.g. the scene's sparse/0)")
    p.add_argument("--image-list", required=True, help="file with one training image name per line")
    p.add_argument("--out", required=True, help="output folder (sparse/0 and status.json)")
    p.add_argument("--points", type=flag(int, 1), default=None,
                   help=f"points to place (default: {N_POINTS}, at most {POINTS_PER_PIXEL} per training pixel)")
    p.add_argument("--seed", type=flag(int, 0), default=0, help="random seed of the points")
    p.add_argument("--near", type=flag(float, 0, lo_open=True),
                   help="near camera depth, scene units (default: from the cameras)")
    p.add_argument("--far", type=flag(float, 0, lo_open=True),
                   help="far camera depth, scene units (default: from the cameras)")
    add_log_flags(p)
    args = p.parse_args(argv)
    setup_logging(args.verbose, args.quiet)

    def work() -> None:
        # the stage's name in its .stage marker stays the flat layout's (reruns into older folders)
        prepare_out(args.out, {"--cameras": args.cameras, "--image-list": args.image_list}, "evaluation.random_init")
        run_random(args.cameras, read_image_list(args.image_list), args.out, args.points, args.seed, args.near, args.far)

    return run_stage(log, work)


if __name__ == "__main__":
    raise SystemExit(main())
