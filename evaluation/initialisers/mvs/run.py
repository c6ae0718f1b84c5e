"""The dense multi-view-stereo initialiser: posed training views -> dense points with a confidence.

Per training view, at a stated working resolution (the long side at most ``max_size``):

1. Source views: the ``max_sources`` others whose optical axes are closest to its own, among
   those with a baseline (a camera at the same centre gives no depth).
2. Depth bounds: the inverse depths at which the view's pixels are seen by a source (the cameras
   alone, :func:`~evaluation.initialisers.mvs.bounds.overlap_bounds`), swept coarsely at a
   quarter of the resolution; the coarse depths that agree across views then bound the fine
   sweep (:func:`~evaluation.initialisers.mvs.bounds.point_bounds`). Planes are spaced in inverse
   depth so that consecutive ones move a pixel at most ``step_px`` in any source.
3. Plane sweep with NCC (:mod:`evaluation.initialisers.mvs.sweep`): a depth and a matching
   confidence per pixel; textureless windows get none.
4. Geometric consistency across all views and fusion (:mod:`evaluation.initialisers.mvs.fusion`).
   A pixel is kept when its matching confidence is at least ``min_conf`` and ``min_agree``
   other views agree; its confidence, in [0, 1], is the matching confidence times the share of
   the views that see it which agree.

Outputs (docs/contracts.md, "mvs initialiser"): ``predictions.npz`` in vggt_init's schema at the
working resolution (kept pixels' points; NaN elsewhere, which the Bridge drops, with confidence
0), ``sparse/0`` (the cameras, unchanged, and the fused points, at most ``max_points``, the most
confident, with their tracks) and ``status.json``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from camio.cameras import Camera
from camio.images import working_size  # the one rule of a working resolution, as camio convert sizes photo folders
from evaluation.initialisers.oracle import MAX_POINTS
from runtime.checks import Range, check_fields

__all__ = ["MvsConfig", "MAX_POINTS", "working_size", "select_sources", "depth_maps", "run_mvs",
           "predictions_arrays"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MvsConfig:
    """Every value of the initialiser, with its default (the one place of them).

    Attributes:
        max_size: long side of the working resolution, pixels (images are never enlarged).
        max_sources: source views per reference view.
        window: NCC window, pixels (odd).
        top_k: sources averaged per depth hypothesis (0: half of the sources, at least 1).
        step_px: largest move of a pixel in a source between consecutive planes.
        min_planes, max_planes: bounds of the number of planes per view.
        coarse_factor: downsampling of the coarse sweep that bounds the fine one (1: no coarse
            sweep, the cameras' bounds are swept directly).
        min_std: grey-level standard deviation below which a window is textureless.
        margin_scale: the cost margin at which the matching confidence reaches 1 - 1/e.
        min_conf: matching confidence a kept pixel needs.
        min_agree: other views that must agree with a kept pixel.
        tol_px, tol_rel: the consistency check's reprojection and relative depth tolerances.
        plane_families: slanted plane families the fine sweep adds to the fronto-parallel
            planes: the ground (normal: the cameras' mean up), then the dominant planes of the
            coarse points (0: fronto-parallel only).
        chunk: planes warped at once (memory: chunk x H x W per buffer).
        fill_stride: every fill_stride-th pixel (rows and columns) that stereo left without a
            point gets one on its ray with confidence 0 in predictions.npz
            (:mod:`evaluation.initialisers.mvs.fill`; 0: none).
        max_points: fused points written to sparse/0 at most.
        threads: torch CPU threads (0: torch's default).
    """

    max_size: Annotated[int, Range(16, integer=True)] = 640
    max_sources: Annotated[int, Range(1, integer=True)] = 4
    window: Annotated[int, Range(3, integer=True)] = 7
    top_k: Annotated[int, Range(0, integer=True)] = 0
    step_px: Annotated[float, Range(0.0, lo_open=True)] = 1.0
    min_planes: Annotated[int, Range(3, integer=True)] = 32
    max_planes: Annotated[int, Range(3, integer=True)] = 192
    coarse_factor: Annotated[int, Range(1, integer=True)] = 4
    min_std: Annotated[float, Range(0.0)] = 0.01
    margin_scale: Annotated[float, Range(0.0, lo_open=True)] = 0.1
    min_conf: Annotated[float, Range(0.0, 1.0)] = 0.02
    min_agree: Annotated[int, Range(1, integer=True)] = 1
    tol_px: Annotated[float, Range(0.0, lo_open=True)] = 2.0
    tol_rel: Annotated[float, Range(0.0, 1.0, lo_open=True, hi_open=True)] = 0.02
    plane_families: Annotated[int, Range(0, integer=True)] = 2
    chunk: Annotated[int, Range(1, integer=True)] = 16
    fill_stride: Annotated[int, Range(0, integer=True)] = 1
    max_points: Annotated[int, Range(1, integer=True)] = MAX_POINTS
    threads: Annotated[int, Range(0, integer=True)] = 0

    def __post_init__(self) -> None:
        try:
            check_fields(self)  # each field's type and range, as annotated above
        except ValueError as exc:
            raise ValueError(f"mvs: {exc}") from None
        if self.window % 2 != 1 or self.max_planes < self.min_planes:
            raise ValueError(f"mvs: window must be odd (got {self.window}) and max_planes >= min_planes (got "
                             f"{self.max_planes} and {self.min_planes})")


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[H, W, C] float32 -> [h, w, C] (area-weighted: antialiased bilinear)."""
    import torch
    import torch.nn.functional as F

    if img.shape[1] == size[0] and img.shape[0] == size[1]:
        return img
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
    out = F.interpolate(t, size=(size[1], size[0]), mode="bilinear", antialias=True, align_corners=False)
    return out[0].numpy().transpose(1, 2, 0).clip(0, 1)


def _gray(img: np.ndarray) -> np.ndarray:
    return (img @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.float32)


def select_sources(cams: list[Camera], r: int, max_sources: int, min_baseline: float) -> list[int]:
    """The other views of reference ``r`` with a baseline above ``min_baseline``, closest first
    in the angle between optical axes, at most ``max_sources``."""
    axis = cams[r].R[2]
    cand = []
    for j, c in enumerate(cams):
        if j == r or np.linalg.norm(c.center - cams[r].center) <= min_baseline:
            continue
        cand.append((float(np.arccos(np.clip(axis @ c.R[2], -1, 1))), j))
    return [j for _, j in sorted(cand)[:max_sources]]


def _geometry(cams: list[Camera], idx: list[int]) -> list[tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
    """(K, cam_from_world, (width, height)) of the views ``idx``: what the bounds read of a source."""
    return [(cams[j].K, cams[j].cam_from_world, (cams[j].width, cams[j].height)) for j in idx]


def _sweep_level(grays, cams, sources, bounds, cfg: MvsConfig, progress: str,
                 families: list[list] | None = None) -> tuple[list, list[dict]]:
    """Sweep every view with its sources and (rho_min, rho_max) bounds; per view the
    :class:`~evaluation.initialisers.mvs.sweep.SweepResult` (None without bounds) and stats."""
    from evaluation.initialisers.mvs.bounds import epipolar_lengths, plane_count
    from evaluation.initialisers.mvs.sweep import inverse_depth_planes, plane_sweep

    results, stats = [], []
    for r, cam in enumerate(cams):
        t0 = time.perf_counter()
        if bounds[r] is None or not sources[r]:
            results.append(None)
            stats.append({"planes": 0, "rho": None, "sources": [], "seconds": 0.0})
            log.info("%s view %d/%d %s: no source sees it, no depth", progress, r + 1, len(cams), cam.name)
            continue
        lengths = epipolar_lengths(cam.K, cam.cam_from_world, (cam.width, cam.height), _geometry(cams, sources[r]),
                                   *bounds[r])
        # a source in which no depth moves a pixel by two planes' steps tells no depth apart
        use = [j for j, n in zip(sources[r], lengths) if n >= 2 * cfg.step_px]
        if not use:
            results.append(None)
            stats.append({"planes": 0, "rho": None, "sources": [], "seconds": 0.0})
            log.info("%s view %d/%d %s: no source has parallax, no depth", progress, r + 1, len(cams), cam.name)
            continue
        lengths = lengths[[j in use for j in sources[r]]]
        D = plane_count(lengths, cfg.step_px, cfg.min_planes, cfg.max_planes)
        rhos = inverse_depth_planes(bounds[r][0], bounds[r][1], D)
        top_k = cfg.top_k or max(1, len(use) // 2)
        res = plane_sweep(grays[r], cam.K, cam.cam_from_world,
                          [(grays[j], cams[j].K, cams[j].cam_from_world) for j in use], rhos,
                          normals=families[r] if families else (), window=cfg.window, top_k=top_k, min_std=cfg.min_std,
                          margin_scale=cfg.margin_scale, chunk=cfg.chunk)
        dt = time.perf_counter() - t0
        results.append(res)
        stats.append({"planes": D, "rho": [float(b) for b in bounds[r]], "sources": [cams[j].name for j in use],
                      "top_k": top_k, "seconds": dt})
        log.info("%s view %d/%d %s: %d planes over %d sources, %dx%d px, %.1f s", progress, r + 1,
                 len(cams), cam.name, D, len(use), cam.width, cam.height, dt)
    return results, stats


def _consistent(results, cams, cfg: MvsConfig):
    """Consistency of a level's depth maps; per view (consistency, keep mask, confidence)."""
    from evaluation.initialisers.mvs.fusion import check_consistency

    depths = []
    for res, cam in zip(results, cams):
        if res is None:
            depths.append(np.full((cam.height, cam.width), np.nan, np.float32))
        else:
            depths.append(np.where(res.conf >= cfg.min_conf, res.depth, np.nan))
    cons = check_consistency(depths, [c.K for c in cams], [c.cam_from_world for c in cams],
                             cfg.tol_px, cfg.tol_rel)
    keep, conf = [], []
    for res, c, d in zip(results, cons, depths):
        k = np.isfinite(d) & (c.agree >= cfg.min_agree)
        share = np.where(c.sees > 0, c.agree / np.maximum(c.sees, 1), 0.0)
        q = np.where(k, (res.conf if res is not None else 0.0) * share, 0.0).astype(np.float32)
        keep.append(k)
        conf.append(q)
    return cons, keep, conf


def depth_maps(images: list[np.ndarray], cams: list[Camera], cfg: MvsConfig = MvsConfig()) -> dict:
    """Depth, confidence and fusion for posed images at their own resolution.

    Args:
        images: per view [H, W, 3] float32 RGB in [0, 1] (all the same size).
        cams: per view the camera at that size (cam_from_world, OpenCV axes).
        cfg: the initialiser's values.

    Returns:
        ``cons``, ``keep``, ``conf`` (per view: consistency, [H, W] bool, [H, W] float32),
        ``depth`` (per view [H, W] float32, NaN where not kept), ``stats`` (per view dict) and
        ``timings_s``.
    """
    from evaluation.initialisers.mvs.bounds import (camera_up, dominant_planes, overlap_bounds, plane_family_range,
                                                    point_bounds)

    t0 = time.perf_counter()
    centers = np.stack([c.center for c in cams])
    dists = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    scale = float(np.median(dists[np.triu_indices(len(cams), 1)])) if len(cams) > 1 else 0.0
    if not np.isfinite(scale) or scale <= 1e-9 * (1.0 + float(np.abs(centers).max())):
        raise ValueError("mvs: the training cameras share one centre: no baseline, no depth from stereo")
    min_baseline = 1e-6 * scale
    sources = [select_sources(cams, r, cfg.max_sources, min_baseline) for r in range(len(cams))]
    grays = [_gray(im) for im in images]
    geo = []
    for r, cam in enumerate(cams):
        geo.append(overlap_bounds(cam.K, cam.cam_from_world, (cam.width, cam.height), _geometry(cams, sources[r]),
                                  scale) if sources[r] else None)
    timings = {}
    bounds = geo
    planes: list[tuple[np.ndarray, np.ndarray]] = []
    coarse_pts = np.zeros((0, 3))
    coarse_points = 0
    if cfg.coarse_factor > 1:
        t1 = time.perf_counter()
        cw, ch = working_size(cams[0].width, cams[0].height,
                              max(16, max(cams[0].width, cams[0].height) // cfg.coarse_factor))
        ccams = [c.scaled(cw, ch) for c in cams]
        cgrays = [_gray(_resize(im, (cw, ch))) for im in images]
        coarse_cfg = MvsConfig(**{**asdict(cfg), "window": max(3, (cfg.window // 2) | 1)})
        cres, _ = _sweep_level(cgrays, ccams, sources, geo, coarse_cfg, "coarse")
        ccons, ckeep, _ = _consistent(cres, ccams, coarse_cfg)
        pts = np.concatenate([c.points[k] for c, k in zip(ccons, ckeep)]) if ckeep else np.zeros((0, 3))
        coarse_points, coarse_pts = len(pts), pts
        if cfg.plane_families > 0 and len(pts) >= 30:
            depth_scale = float(np.median(np.linalg.norm(pts - centers.mean(0), axis=1)))
            up = camera_up([c.cam_from_world for c in cams])
            if up is not None:  # a ground below the cameras: its family first
                planes.append((up, centers.mean(0) - up * scale))
            planes += dominant_planes(pts, 0.02 * depth_scale, cfg.plane_families - len(planes),
                                      known=[p[0] for p in planes])
        bounds = []
        for r, cam in enumerate(cams):
            pb = point_bounds(pts, cam.cam_from_world) if geo[r] is not None else None
            if pb is not None:  # never beyond what the cameras can see
                pb = (max(pb[0], geo[r][0]), min(pb[1], geo[r][1]))
                pb = pb if pb[1] > pb[0] else None
            bounds.append(pb or geo[r])
        timings["coarse"] = time.perf_counter() - t1
        log.info("coarse sweep at %dx%d: %d consistent points bound the depths; %d dominant plane(s) "
                 "add slanted plane families; %.1f s", cw, ch, coarse_points, len(planes), timings["coarse"])
    t1 = time.perf_counter()
    families = []
    for cam in cams:
        spans = [plane_family_range(coarse_pts, pl, cam.cam_from_world) for pl in planes]
        families.append([f for f in spans if f is not None])
    results, stats = _sweep_level(grays, cams, sources, bounds, cfg, "sweep", families)
    timings["sweep"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    cons, keep, conf = _consistent(results, cams, cfg)
    timings["consistency"] = time.perf_counter() - t1
    depth = []
    for r, (res, k) in enumerate(zip(results, keep)):
        d = np.where(k, res.depth, np.nan).astype(np.float32) if res is not None else \
            np.full(k.shape, np.nan, np.float32)
        depth.append(d)
        n = k.size
        stats[r].update({
            "kept": float(k.mean()),
            "textureless": float(res.textureless.mean()) if res is not None else None,
            "matched": float(np.isfinite(res.depth).mean()) if res is not None else 0.0,
            "bounds_from": "cameras" if bounds[r] is geo[r] else "coarse points",
            "pixels": int(n),
        })
    timings["total"] = time.perf_counter() - t0
    return {"cons": cons, "keep": keep, "conf": conf, "depth": depth, "stats": stats,
            "timings_s": timings, "coarse_points": coarse_points, "scale": scale,
            "planes": [{"normal": n.tolist(), "point": c.tolist()} for n, c in planes]}


def predictions_arrays(names, cams_full, cams, images_u8, dm, fill_stride: int) -> dict:
    """predictions.npz's arrays (vggt_init's schema, docs/contracts.md) at the working size;
    with ``fill_stride``, the unexplained rays' points (confidence 0) beside the kept ones."""
    pts = np.stack([np.where(k[..., None], c.points, np.nan) for c, k in zip(dm["cons"], dm["keep"])])
    if fill_stride:
        from evaluation.initialisers.mvs.fill import fill_unexplained

        pts = fill_unexplained(pts, [c.K for c in cams], [c.cam_from_world for c in cams], fill_stride)
    conf = np.stack(dm["conf"])
    return {
        "image_names": np.array(names),
        "cam_from_world": np.stack([c.cam_from_world for c in cams]).astype(np.float32),
        "intrinsics": np.stack([c.K for c in cams]).astype(np.float32),
        "intrinsics_original": np.stack([c.K for c in cams_full]).astype(np.float64),
        "image_sizes_original": np.array([[c.width, c.height] for c in cams_full], np.int64),
        "world_points": pts.astype(np.float32),
        "world_points_conf": conf.astype(np.float32),
        "colors": np.stack(images_u8).astype(np.uint8),
        "depth": np.nan_to_num(np.stack(dm["depth"]), nan=0.0).astype(np.float32),
        "depth_conf": conf.astype(np.float32),
    }


def _read_cameras(scene: Path | None, cameras: Path | None, names: list[str]) -> tuple[list[Camera], str]:
    from camio.colmap import read_model

    model_dir = Path(cameras) if cameras else Path(scene) / "sparse" / "0"
    if not model_dir.is_dir():
        raise ValueError(f"mvs: no cameras: {model_dir} does not exist (a prepared scene's reference "
                         "cameras in sparse/0, or --cameras MODEL: COLMAP's, VGGT's, bundle adjustment's)")
    ref = read_model(model_dir)
    missing = [n for n in names if n not in ref.names]
    if missing and not cameras:
        raise ValueError(f"mvs: training images {missing[:5]} have no camera in {model_dir}")
    if missing:  # an estimated model (COLMAP's) need not register every photo
        log.warning("mvs: %d of %d training images have no camera in %s and are left out: %s", len(missing),
                    len(names), model_dir, ", ".join(missing[:5]))
    return [ref.camera(n) for n in names if n in ref.names], str(model_dir)


def run_mvs(images_dir: str | Path, names: list[str], out_dir: str | Path, *, scene: str | Path | None = None,
            cameras: str | Path | None = None, cfg: MvsConfig = MvsConfig()) -> dict:
    """Write ``out_dir/predictions.npz``, ``out_dir/sparse/0`` and ``out_dir/status.json``
    (module docstring) for the training ``names`` of ``images_dir``.

    Raises:
        ValueError: fewer than 2 views, missing cameras, views of different sizes, cameras
            with one centre, or views that share no consistent point (one line says which).
    """
    import torch

    from runtime.atomic import save_npz, write_json
    from camio.colmap import write_text_model
    from camio.images import read_image

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    names = list(dict.fromkeys(names))
    if len(names) < 2:
        raise ValueError(f"mvs: needs >= 2 training views, got {len(names)}")
    cams_full, cam_source = _read_cameras(Path(scene) if scene else None, cameras, names)
    names = [c.name for c in cams_full]
    if len(names) < 2:
        raise ValueError(f"mvs: {cam_source} has cameras for {len(names)} of the training images; stereo needs 2")
    sizes = {(c.width, c.height) for c in cams_full}
    if len(sizes) > 1:
        raise ValueError(f"mvs: the training views have {len(sizes)} sizes {sorted(sizes)}; predictions.npz "
                         "holds one grid, so all views must share one size")
    w, h = working_size(cams_full[0].width, cams_full[0].height, cfg.max_size)
    cams = [c.scaled(w, h) for c in cams_full]
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    log.info("mvs: %d views, %dx%d -> working resolution %dx%d (long side <= %d), %d torch threads",
             len(names), cams_full[0].width, cams_full[0].height, w, h, cfg.max_size, torch.get_num_threads())
    images = []
    for c in cams_full:
        img = read_image(Path(images_dir) / c.name)
        if img.shape[:2] != (c.height, c.width):
            raise ValueError(f"mvs: image {c.name} is {img.shape[1]}x{img.shape[0]} but its camera is "
                             f"{c.width}x{c.height}")
        images.append(_resize(img[..., :3].astype(np.float32), (w, h)))
    dm = depth_maps(images, cams, cfg)
    images_u8 = [np.round(im * 255).astype(np.uint8) for im in images]
    from evaluation.initialisers.mvs.fusion import fuse

    fused = fuse(dm["cons"], dm["keep"], dm["conf"], images_u8)
    if len(fused.points) == 0:
        raise ValueError("mvs: no pixel of any view is confirmed by another view (views that do not "
                         "overlap, no texture, or cameras that do not fit the images); nothing to seed")
    arrays = predictions_arrays(names, cams_full, cams, images_u8, dm, cfg.fill_stride)
    kept_total = int(sum(k.sum() for k in dm["keep"]))
    filled = int(np.isfinite(arrays["world_points"]).all(-1).sum()) - kept_total
    save_npz(out_dir / "predictions.npz", **arrays)
    order = np.argsort(-fused.conf, kind="stable")[:cfg.max_points]
    new_id = np.full(len(fused.points), -1)
    new_id[order] = np.arange(len(order))
    obs = {}
    for r, (pix, pid) in fused.observations.items():
        sel = new_id[pid] >= 0
        xy = np.stack([pix[sel] % w + 0.5, pix[sel] // w + 0.5], 1) * [cams_full[r].width / w,
                                                                       cams_full[r].height / h]
        obs[names[r]] = (xy, new_id[pid[sel]])
    write_text_model(out_dir / "sparse" / "0", cams_full, fused.points[order], fused.colors[order], obs)
    kept = float(np.mean([k.mean() for k in dm["keep"]]))
    status = {
        "success_paper": True, "aligned_ok": len(names) >= 3, "registered": len(names),
        "n_images": len(names), "points": int(len(order)), "reason": None, "wall_time_s": None,
        "seed": 0, "cameras_source": cam_source, "working_size": [w, h],
        "original_size": [cams_full[0].width, cams_full[0].height],
        "kept_share": kept, "filled_points": filled, "fused_points": int(len(fused.points)), "coarse_points": dm["coarse_points"],
        "views": {n: s for n, s in zip(names, dm["stats"])}, "timings_s": dm["timings_s"],
        "config": asdict(cfg), "torch_threads": torch.get_num_threads(),
    }
    status["wall_time_s"] = time.perf_counter() - t0
    write_json(out_dir / "status.json", status)
    log.info("mvs: %d views at %dx%d, %.1f %% of pixels kept, %d fused points (%d written), %d unexplained rays "
             "filled (confidence 0), %.1f s", len(names), w, h, 100 * kept, len(fused.points), len(order), filled,
             status["wall_time_s"])
    return status
