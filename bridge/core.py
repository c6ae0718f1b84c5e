"""The Bridge: predicted geometry -> normalised cameras + seed Gaussians (docs/reference.md section 2).

Steps, in this order (each counted in bridge.json):

1. drop rows whose point or confidence is NaN/Inf;
2. Eq. 1 on every remaining row (all views, all pixels: before any subsampling), which
   also scales the camera translations; c_min, c_max of Eq. 2 over the same rows;
3. pixel stride (row stride of the flattened [S, H, W] map; paper: 20);
4. optional confidence-percentile filter (``filtered`` mode: lowest 40 % dropped);
5. optional voxel downsampling, optional statistical outlier removal (normalised units);
6. optional cap on the count (most confident kept);
7. opacity: Eq. 2 (``gated``, ``filtered``) or a constant (``uniform``); scales from the
   3 nearest neighbours; identity rotations; SH DC from the image colours.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np

from bridge.depth_prior import dense_depth_samples, observed_depth_samples
from bridge.equations import ALPHA_MAX, ALPHA_MIN, global_coordinate_normalisation, uncertainty_gated_opacity
from bridge.inputs import BridgeInput
from bridge.selection import (MIN_DIST2, cap_points, knn_scales, percentile_mask, statistical_outlier_mask,
                              stride_mask, voxel_downsample)
from camio.cameras import Camera
from camio.depth_prior import DEPTH_PRIOR_FILE, DepthSamples
from runtime.modes import BRIDGE_MODES
from camio.ply import SH_DEGREE, GaussianCloud
from runtime.checks import Range, check_fields
from runtime.logs import timed

__all__ = ["MODES", "BridgeConfig", "SeedResult", "build_seed", "write_outputs", "run_bridge"]

log = logging.getLogger(__name__)

# An opacity the Bridge gives a seed point: in (0, 1) (0 would be no point, 1 a logit of inf).
OPACITY = Range(0.0, 1.0, lo_open=True, hi_open=True)
MODES = BRIDGE_MODES  # runtime.modes, the one list (evaluation and the workflow read it too)
DEFAULT_PERCENTILE = 40.0
UNIFORM_ALPHA = 0.1
MEDIAN_SET = ("every row with a finite point and a finite confidence, over all pixels of all views, "
              "before the stride and every filter")


@dataclass
class BridgeConfig:
    """Options of the Bridge (the CLI flags).

    Attributes:
        mode: "gated" (Eq. 2), "uniform" (constant ``uniform_alpha``) or "filtered"
            (percentile filter, :data:`DEFAULT_PERCENTILE` by default, then Eq. 2).
        alpha_min, alpha_max: Eq. 2's opacity range.
        uniform_alpha: the constant opacity of ``uniform`` mode (seed code fallback 0.1).
        stride: keep every stride-th flattened pixel (paper 20; 1 keeps all).
        percentile: drop the lowest ``percentile`` % by confidence (any mode that has
            confidence); None = off, except 40 in ``filtered`` mode.
        voxel_size: voxel edge in normalised units (Eq. 1 frame); None = off.
        outlier_removal: open3d statistical outlier removal with ``outlier_neighbors`` and
            ``outlier_std_ratio``.
        max_points: keep at most this many (most confident); None = no cap.
        seed: random seed (only for capping a cloud without confidence).
        sh_degree: SH degree of the seed (higher bands are zero).
        write_points3d: also write the seed points into sparse/0/points3D.txt (off by default:
            the contract's sparse/0 holds the cameras; seed.ply holds the points. Turn on for
            tools that initialise from points3D, e.g. the original 3DGS loader. Costs ~1.5 s
            per 100k points, and readers of the model pay again).
        depth_prior: also write ``depth_prior.npz``, the initialiser's depth of each camera
            (:mod:`bridge.depth_prior`) for the trainer's depth term; off writes none.
        depth_prior_samples: at most this many depth samples per camera.
    """

    mode: str = "gated"
    alpha_min: Annotated[float, OPACITY] = ALPHA_MIN
    alpha_max: Annotated[float, OPACITY] = ALPHA_MAX
    uniform_alpha: Annotated[float, OPACITY] = UNIFORM_ALPHA
    stride: Annotated[int, Range(1, integer=True)] = 20
    percentile: Annotated[float | None, Range(0.0, 100.0, hi_open=True)] = None
    voxel_size: Annotated[float | None, Range(0.0, lo_open=True)] = None
    outlier_removal: bool = False
    outlier_neighbors: Annotated[int, Range(1, integer=True)] = 20
    outlier_std_ratio: Annotated[float, Range(0.0, lo_open=True)] = 2.0
    max_points: Annotated[int | None, Range(1, integer=True)] = None
    # numpy's default_rng takes any integer >= 0
    seed: Annotated[int, Range(0, integer=True)] = 0
    sh_degree: Annotated[int, Range(0, SH_DEGREE, integer=True)] = SH_DEGREE
    write_points3d: bool = False
    depth_prior: bool = True
    depth_prior_samples: Annotated[int, Range(1, integer=True)] = 50000

    def __post_init__(self) -> None:
        check_fields(self)  # each field's type and range, as annotated above
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not self.alpha_min <= self.alpha_max:
            raise ValueError(f"need alpha_min <= alpha_max, got {self.alpha_min}, {self.alpha_max}")

    @property
    def effective_percentile(self) -> float | None:
        if self.percentile is None and self.mode == "filtered":
            return DEFAULT_PERCENTILE
        return self.percentile


@dataclass
class SeedResult:
    """What the Bridge writes.

    Attributes:
        cloud: the seed Gaussians in the normalised frame.
        cameras: the cameras in the normalised frame (translations scaled by s).
        points: [K, 3] float64 seed centres (normalised frame), rows of ``cloud``.
        colors: [K, 3] uint8.
        depth_prior: the depth samples to write as ``depth_prior.npz`` (None: no prior).
        report: the bridge.json record.
    """

    cloud: GaussianCloud
    cameras: list[Camera]
    points: np.ndarray
    colors: np.ndarray
    report: dict = field(default_factory=dict)
    depth_prior: DepthSamples | None = None


def _stats(x: np.ndarray) -> dict:
    if len(x) == 0:
        return {"min": None, "median": None, "max": None, "mean": None}
    return {"min": float(np.min(x)), "median": float(np.median(x)), "max": float(np.max(x)),
            "mean": float(np.mean(x))}


def build_seed(inp: BridgeInput, cfg: BridgeConfig) -> SeedResult:
    """Run the Bridge on ``inp`` in memory (no files written).

    Args:
        inp: the cloud and cameras in the input frame (see :class:`BridgeInput`).
        cfg: options.

    Returns:
        the seed Gaussians and cameras in the normalised frame of Eq. 1, with the report.

    Raises:
        ValueError: zero points (or none valid, or none left after selection), a degenerate
            cloud for Eq. 1, or a confidence-based option on an input without confidence.
    """
    timings: dict[str, float] = {}
    n_in = len(inp.points)
    if n_in == 0:
        raise ValueError(f"{inp.path}: the input has zero points; there is nothing to seed "
                         "(for COLMAP: the model has no points3D; for VGGT: an empty point map)")
    has_conf = inp.conf is not None
    mode = cfg.mode
    mode_note = None
    percentile = cfg.effective_percentile
    if not has_conf:
        if cfg.mode == "filtered" or cfg.percentile is not None:
            raise ValueError(f"{inp.path}: a {inp.source} input has no confidence, so it cannot be "
                             "percentile-filtered; use --mode uniform (or gated, which falls back to it)")
        if mode == "gated":
            mode = "uniform"
            mode_note = "no confidence in the input: uniform opacity (seed code fallback)"
            log.info("%s input has no confidence: gated -> uniform opacity %.3g", inp.source, cfg.uniform_alpha)

    dropped = {k: 0 for k in ("nonfinite_point", "nonfinite_conf", "stride", "percentile", "voxel",
                              "outliers", "max_points")}
    with timed("validate and normalise (Eq. 1)", log, timings):
        finite_pt = np.all(np.isfinite(inp.points), axis=1)
        finite_conf = np.isfinite(inp.conf) if has_conf else np.ones(n_in, bool)
        valid = finite_pt & finite_conf
        dropped["nonfinite_point"] = int(np.count_nonzero(~finite_pt))
        dropped["nonfinite_conf"] = int(np.count_nonzero(finite_pt & ~finite_conf))
        n_valid = int(np.count_nonzero(valid))
        if dropped["nonfinite_point"] or dropped["nonfinite_conf"]:
            log.warning("dropped %d rows with a non-finite point and %d with a non-finite confidence",
                        dropped["nonfinite_point"], dropped["nonfinite_conf"])
        if n_valid == 0:
            raise ValueError(f"{inp.path}: all {n_in} points are NaN/Inf (or have a NaN/Inf confidence); "
                             "check the prediction")
        rows = np.flatnonzero(valid)
        ext = np.stack([c.cam_from_world for c in inp.cameras])
        pts, ext_n, s = global_coordinate_normalisation(inp.points[rows], ext)
        conf = inp.conf[rows] if has_conf else None
        c_min = float(np.min(conf)) if has_conf else None
        c_max = float(np.max(conf)) if has_conf else None

    with timed("select points", log, timings):
        on_stride = stride_mask(n_in, cfg.stride)[rows]
        dropped["stride"] = int(np.count_nonzero(~on_stride))
        sel = np.flatnonzero(on_stride)  # indices into rows / pts / conf
        threshold = None
        if percentile is not None:
            keep, threshold = percentile_mask(conf[sel], percentile)
            dropped["percentile"] = int(np.count_nonzero(~keep))
            sel = sel[keep]
        if cfg.voxel_size is not None:
            keep_idx = voxel_downsample(pts[sel], cfg.voxel_size, conf[sel] if has_conf else None)
            dropped["voxel"] = len(sel) - len(keep_idx)
            sel = sel[keep_idx]
        if cfg.outlier_removal:
            keep = statistical_outlier_mask(pts[sel], cfg.outlier_neighbors, cfg.outlier_std_ratio)
            dropped["outliers"] = int(np.count_nonzero(~keep))
            sel = sel[keep]
        if cfg.max_points is not None:
            keep_idx = cap_points(len(sel), cfg.max_points, conf[sel] if has_conf else None, cfg.seed)
            dropped["max_points"] = len(sel) - len(keep_idx)
            sel = sel[keep_idx]
        if len(sel) == 0:
            raise ValueError(f"{inp.path}: no point left after selection ({n_valid} valid, stride "
                             f"{cfg.stride}, dropped {dropped}); lower --stride or relax the filters")

    with timed("seed Gaussians (Eq. 2, 3-NN scales)", log, timings):
        p_sel = pts[sel]
        if mode == "uniform":
            alpha = np.full(len(sel), cfg.uniform_alpha)
        else:
            alpha = uncertainty_gated_opacity(conf[sel], cfg.alpha_min, cfg.alpha_max, c_min, c_max)
        scales, n_floored = knn_scales(p_sel)
        colors = np.asarray(inp.colors[rows[sel]], np.uint8)
        cloud = GaussianCloud.from_points(p_sel, colors.astype(np.float64) / 255.0, alpha, scales,
                                          sh_degree=cfg.sh_degree)
    cameras = [Camera(c.name, c.width, c.height, c.K, ext_n[i]) for i, c in enumerate(inp.cameras)]
    prior = None
    if cfg.depth_prior:
        with timed("depth prior", log, timings):
            if inp.grid_shape is not None and has_conf:
                prior = dense_depth_samples(pts, rows, conf, inp.grid_shape, cameras, c_min, c_max,
                                            cfg.depth_prior_samples, cfg.seed)
            elif inp.observations:
                prior = observed_depth_samples(s * inp.points, inp.observations, cameras, cfg.depth_prior_samples,
                                               cfg.seed)
    kept = len(sel)
    assert kept + sum(dropped.values()) == n_in, (kept, dropped, n_in)

    report = {
        "source": inp.source,
        "input": str(inp.path),
        "mode": mode,
        "mode_requested": cfg.mode,
        "mode_note": mode_note,
        "s": s,
        "median_norm": 1.0 / s,
        "median_set": MEDIAN_SET,
        "c_min": c_min,
        "c_max": c_max,
        "c_range_set": MEDIAN_SET if has_conf else None,
        "alpha_min": cfg.alpha_min,
        "alpha_max": cfg.alpha_max,
        "uniform_alpha": cfg.uniform_alpha if mode == "uniform" else None,
        "alpha_out": _stats(alpha),
        "points_in": n_in,
        "points_valid": n_valid,
        "points_kept": kept,
        "dropped": dropped,
        "stride": cfg.stride,
        "percentile": percentile,
        "percentile_threshold": threshold,
        "voxel_size": cfg.voxel_size,
        "outlier_removal": ({"nb_neighbors": cfg.outlier_neighbors, "std_ratio": cfg.outlier_std_ratio}
                            if cfg.outlier_removal else None),
        "max_points": cfg.max_points,
        "scale": {"rule": "sqrt(mean squared distance to 3 nearest neighbours), normalised frame",
                  "min_dist2": MIN_DIST2, "n_floored": n_floored, **_stats(scales)},
        "sh_degree": cfg.sh_degree,
        "n_cameras": len(cameras),
        "grid_shape": list(inp.grid_shape) if inp.grid_shape else None,
        "depth_prior": None if prior is None else {"file": DEPTH_PRIOR_FILE, "source": prior.source,
                                                   "samples": int(len(prior.z)),
                                                   "weight": "Eq. 2 confidence ratio" if prior.source == "dense"
                                                   else "1 (observed points)"},
        "config": asdict(cfg),
        "timings_s": timings,
    }
    log.info("bridge: %d of %d points kept (s = %.6g, mode %s, alpha %.3g..%.3g), dropped %s",
             kept, n_in, s, mode, float(alpha.min()), float(alpha.max()),
             {k: v for k, v in dropped.items() if v})
    return SeedResult(cloud, cameras, p_sel, colors, report, prior)


def write_outputs(result: SeedResult, out_dir: str | Path, write_points3d: bool = False) -> dict[str, Path]:
    """Write seed.ply, sparse/0 (COLMAP text) and bridge.json (last) into ``out_dir``.

    Each file is written atomically; bridge.json comes last, so its presence means the
    others are complete. ``depth_prior.npz`` is written when the result has a prior (a stale
    one from an earlier run is removed otherwise).
    """
    from runtime.atomic import write_json
    from camio.colmap import write_text_model
    from camio.depth_prior import write_depth_prior
    from camio.ply import write_gaussian_ply

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings = result.report.setdefault("timings_s", {})
    with timed("write seed.ply", log, timings):
        ply = write_gaussian_ply(out / "seed.ply", result.cloud)
    with timed("write sparse/0", log, timings):
        sparse = write_text_model(out / "sparse" / "0", result.cameras,
                                  result.points if write_points3d else None,
                                  result.colors if write_points3d else None)
    prior_path = out / DEPTH_PRIOR_FILE
    if result.depth_prior is not None:
        with timed("write depth prior", log, timings):
            write_depth_prior(prior_path, result.depth_prior)
    elif prior_path.is_file():  # the Bridge's own file from an earlier run: it would describe another seed
        prior_path.unlink()
    result.report["outputs"] = {"seed_ply": "seed.ply", "sparse": "sparse/0",
                                "points3d_written": bool(write_points3d),
                                "depth_prior": DEPTH_PRIOR_FILE if result.depth_prior is not None else None}
    timings["total"] = sum(v for k, v in timings.items() if k != "total")
    # what evaluation.reports.results reads: the stage's work (load .. write), not interpreter start-up
    result.report["wall_time_s"] = timings["total"]
    js = write_json(out / "bridge.json", result.report)
    return {"seed_ply": ply, "sparse": sparse, "bridge_json": js}


def run_bridge(inp: BridgeInput, out_dir: str | Path, cfg: BridgeConfig | None = None,
               timings: dict[str, float] | None = None) -> dict:
    """Build the seed from ``inp`` and write it to ``out_dir``; return the bridge.json record.

    ``timings`` (e.g. {"load": seconds} from the caller) are recorded in bridge.json too and
    count towards its ``timings_s.total``.
    """
    cfg = cfg or BridgeConfig()
    t0 = time.perf_counter()
    result = build_seed(inp, cfg)
    result.report["timings_s"] = {**(timings or {}), **result.report["timings_s"]}
    write_outputs(result, out_dir, cfg.write_points3d)
    log.info("bridge wrote %s in %.2f s (%d Gaussians, %d cameras)", out_dir, time.perf_counter() - t0,
             len(result.cloud), len(result.cameras))
    return result.report
