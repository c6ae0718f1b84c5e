"""The oracle initialiser: ground-truth cameras and points with controlled, seeded noise.

For scenes with ground-truth geometry (the synthetic scene: reference cameras in
``sparse/0`` and z-depth maps in ``gt/depth/<stem>.npy``) it writes the same
``predictions.npz`` as ``vggt_init`` (docs/contracts.md), so the Bridge and everything after
it can be studied with known errors:

* Poses: each training camera's rotation is perturbed by a random axis-angle vector with
  i.i.d. N(0, (rot_deg / sqrt 3)^2) components (RMS angle ``rot_deg``); its centre moves by
  i.i.d. N(0, (trans_frac * r / sqrt 3)^2) per axis, r = RMS distance of the training-camera
  centres from their mean (the trajectory radius; the scene's depth scale for one camera).
* Depth: z' = z (1 + e), e ~ N(0, depth_rel^2) per pixel; a fraction ``outlier_frac`` of the
  pixels gets e ~ U(-0.5, 0.5) instead.
* Points: every pixel centre is unprojected with the *noisy* camera and the noisy depth, so
  each view is self-consistent and views disagree as much as their pose noise says (as a
  feed-forward predictor's per-view errors do). Background pixels (depth 0) are placed on
  their ray at the scene's far depth with the lowest confidence.
* Confidence (VGGT's is always > 1): c = 1 + conf_scale * exp(-|e| / s + N(0, conf_noise^2)),
  s = max(depth_rel, 1e-3): large injected errors get low confidence; ``conf_noise`` makes
  the confidence an imperfect indicator. Background: c = 1.
* Confidence informativeness, ``conf_mode`` (the one definition; the values c above are only
  re-assigned among one view's foreground pixels, so every mode has the same distribution of
  confidence values and differs only in what it says about the error):

  - ``ranked``: c as above (decreases with |e|: it ranks the injected error correctly);
  - ``noise``: the view's foreground values in a random order (independent of the error);
  - ``anti``: the view's foreground values in reversed rank order (the pixel whose ``ranked``
    confidence is the k-th lowest gets the k-th highest: confidence grows with |e|).

  The permutation for ``noise`` uses its own generator (seeded by ``seed``), so the cameras,
  depths and outliers of a seed are the same in every mode. Only the depth error is ranked:
  camera noise is not reflected in the confidence, in any mode.

Everything is deterministic given ``seed``. Frames: cameras are cam_from_world in the
reference (world) frame, OpenCV axes; pixels follow the COLMAP centre convention (camio).
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from runtime.atomic import save_npz, write_json
from camio.cameras import Camera, scale_intrinsics
from camio.colmap import read_model, write_text_model
from evaluation.initialisers.views import add_view_args, parse_training_args
from runtime.checks import flag
from runtime.cliargs import add_log_flags

__all__ = ["CONF_MODES", "MAX_POINTS", "OracleNoise", "add_noise_args", "rotation_from_axis_angle", "perturb_cameras",
           "unproject_depth", "reassign_confidence", "make_oracle_predictions", "run_oracle"]

log = logging.getLogger(__name__)

CONF_MODES = ("ranked", "noise", "anti")
#: points kept in sparse/0 at most: VGGT's cap (vggt_init.defaults.MAX_POINTS), so that the two
#: seed the same number of points (evaluation does not import vggt_init: the value is restated here)
MAX_POINTS = 100_000


@dataclass
class OracleNoise:
    """Noise levels of the oracle (all zero = exact ground truth).

    Attributes:
        rot_deg: RMS rotation noise per camera, degrees.
        trans_frac: RMS camera-centre noise as a fraction of the trajectory radius.
        depth_rel: relative depth noise (standard deviation of e in z (1 + e)).
        outlier_frac: fraction of pixels with e ~ U(-0.5, 0.5).
        conf_scale: confidence range above 1.
        conf_noise: log-normal noise on the confidence (0 = confidence ranks errors exactly).
        conf_mode: confidence informativeness, one of :data:`CONF_MODES` (module docstring).
    """

    rot_deg: float = 0.0
    trans_frac: float = 0.0
    depth_rel: float = 0.0
    outlier_frac: float = 0.0
    conf_scale: float = 10.0
    conf_noise: float = 0.0
    conf_mode: str = "ranked"

    def __post_init__(self) -> None:
        if self.conf_mode not in CONF_MODES:
            raise ValueError(f"conf_mode must be one of {CONF_MODES}, got {self.conf_mode!r}")
        for key, val in asdict(self).items():
            if key == "conf_mode":
                continue
            if not np.isfinite(val) or val < 0:
                raise ValueError(f"oracle noise {key} must be finite and >= 0, got {val}")
        if self.outlier_frac > 1:
            raise ValueError(f"outlier_frac must be in [0, 1], got {self.outlier_frac}")


def rotation_from_axis_angle(v: np.ndarray) -> np.ndarray:
    """Rodrigues: axis-angle vectors [..., 3] (radians) -> rotation matrices [..., 3, 3]."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1, keepdims=True)[..., None]  # [..., 1, 1]
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    safe = np.where(theta < 1e-12, 1.0, theta)
    a = np.where(theta < 1e-12, 1.0, np.sin(safe) / safe)
    b = np.where(theta < 1e-12, 0.5, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def perturb_cameras(cameras: list[Camera], noise: OracleNoise,
                    rng: np.random.Generator) -> list[Camera]:
    """Cameras with rotation and centre noise (see module docstring); K unchanged.

    The rotation noise is applied in the camera frame: R' = dR R. The centre C' = C + dC,
    so t' = -R' C'.
    """
    centers = np.stack([c.center for c in cameras])  # [S, 3] world
    radius = float(np.sqrt(np.mean(np.sum((centers - centers.mean(0)) ** 2, axis=1))))
    if radius < 1e-12:  # one camera (or coincident ones): use its distance to the origin
        radius = float(np.linalg.norm(centers[0])) or 1.0
    out = []
    for cam, c in zip(cameras, centers):
        dr = rotation_from_axis_angle(rng.normal(0, np.deg2rad(noise.rot_deg) / np.sqrt(3), 3))
        dc = rng.normal(0, noise.trans_frac * radius / np.sqrt(3), 3)
        r_new = dr @ cam.R
        c_new = c + dc
        pose = np.concatenate([r_new, (-r_new @ c_new)[:, None]], axis=1)
        out.append(Camera(cam.name, cam.width, cam.height, cam.K.copy(), pose))
    return out


def unproject_depth(depth: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                    rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """World points of pixel centres with a given z-depth.

    Args:
        depth: [h, w] z-depth (camera frame) at the sampled pixels.
        K: [3, 3] intrinsics of the full-resolution image (COLMAP pixel centres).
        cam_from_world: [3, 4] extrinsics (OpenCV axes).
        rows, cols: [h], [w] full-resolution pixel indices sampled (centres at +0.5).

    Returns:
        [h, w, 3] float64 world points.
    """
    u = (np.asarray(cols, np.float64) + 0.5)[None, :]
    v = (np.asarray(rows, np.float64) + 0.5)[:, None]
    z = np.asarray(depth, np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z - K[0, 1] / K[0, 0] * (v - K[1, 2]) / K[1, 1] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    p_cam = np.stack([x, y, z], axis=-1)  # [h, w, 3]
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    return (p_cam - t) @ R  # R^T (p - t), row-vector form


def reassign_confidence(conf: np.ndarray, valid: np.ndarray, mode: str,
                        rng: np.random.Generator) -> np.ndarray:
    """One view's confidence re-assigned among its foreground pixels (``conf_mode``, module
    docstring): ``ranked`` unchanged, ``noise`` a random permutation, ``anti`` reversed ranks.

    Args:
        conf: [h, w] ``ranked`` confidence of the view.
        valid: [h, w] bool, foreground pixels (background keeps its value).
        mode: one of :data:`CONF_MODES`.
        rng: generator of the ``noise`` permutation (not drawn from otherwise).

    Returns:
        [h, w] confidence with the same multiset of foreground values.
    """
    if mode not in CONF_MODES:
        raise ValueError(f"conf_mode must be one of {CONF_MODES}, got {mode!r}")
    if mode == "ranked":
        return conf
    out = np.array(conf, copy=True)
    vals = conf[valid]
    if mode == "noise":
        out[valid] = rng.permutation(vals)
    else:  # anti: the k-th lowest gets the k-th highest value
        order = np.argsort(vals, kind="stable")
        flipped = np.empty_like(vals)
        flipped[order] = np.sort(vals)[::-1]
        out[valid] = flipped
    return out


def make_oracle_predictions(scene: str | Path, names: list[str], noise: OracleNoise,
                            seed: int = 0, downsample: int = 1) -> tuple[dict, list[Camera]]:
    """Build the predictions arrays for the training ``names`` of a ground-truth scene.

    Args:
        scene: prepared scene folder (images/, sparse/0, gt/depth/).
        names: training image names.
        noise: noise levels.
        seed: RNG seed (numpy PCG64).
        downsample: integer stride of the prediction grid (1 = every pixel). The grid cell
            (i, j) holds the point of full-resolution pixel (i k + k // 2, j k + k // 2).

    Returns:
        (arrays for predictions.npz, the noisy cameras at full resolution).
    """
    from camio.images import read_image_uint8

    scene = Path(scene)
    k = int(downsample)
    if k < 1:
        raise ValueError(f"downsample must be >= 1, got {downsample}")
    ref = read_model(scene / "sparse" / "0")
    missing = [n for n in names if n not in ref.names]
    if missing:
        raise ValueError(f"oracle: images {missing[:5]} have no reference camera in "
                         f"{scene / 'sparse' / '0'}; the oracle needs ground-truth cameras")
    depth_dir = scene / "gt" / "depth"
    gt_cams = [ref.camera(n) for n in names]
    rng = np.random.default_rng(seed)
    perm_rng = np.random.default_rng([seed, 1])  # conf_mode "noise" only: keeps rng's stream
    noisy = perturb_cameras(gt_cams, noise, rng)

    depths = []
    for n in names:
        f = depth_dir / f"{Path(n).stem}.npy"
        if not f.is_file():
            raise FileNotFoundError(f"oracle: no ground-truth depth {f}; the oracle needs a "
                                    "scene with gt/depth (e.g. `python -m camio synth`)")
        depths.append(np.load(f).astype(np.float64))
    fg = np.concatenate([d[d > 0].ravel() for d in depths])
    far = float(fg.max()) if fg.size else 1.0

    pts, confs, cols, dep, K_net = [], [], [], [], []
    s = max(noise.depth_rel, 1e-3)
    for cam, z in zip(noisy, depths):
        if z.shape != (cam.height, cam.width):
            raise ValueError(f"oracle: depth of {cam.name} is {z.shape[::-1]} (w, h) but its "
                             f"camera is {cam.width}x{cam.height}")
        rows = np.arange(cam.height // k) * k + k // 2
        colsi = np.arange(cam.width // k) * k + k // 2
        zs = z[np.ix_(rows, colsi)]
        valid = zs > 0
        e = rng.normal(0, noise.depth_rel, zs.shape)
        out_mask = rng.random(zs.shape) < noise.outlier_frac
        e = np.where(out_mask, rng.uniform(-0.5, 0.5, zs.shape), e)
        zn = np.where(valid, zs * (1 + e), far)
        log_c = -np.abs(e) / s
        if noise.conf_noise:
            log_c = log_c + rng.normal(0, noise.conf_noise, zs.shape)
        conf = 1 + noise.conf_scale * np.exp(log_c)
        conf = np.where(valid, conf, 1.0)
        conf = reassign_confidence(conf, valid, noise.conf_mode, perm_rng)
        pts.append(unproject_depth(zn, cam.K, cam.cam_from_world, rows, colsi))
        confs.append(conf)
        dep.append(np.where(valid, zn, 0.0))
        img = read_image_uint8(scene / "images" / cam.name)
        if img.shape[:2] != (cam.height, cam.width):
            raise ValueError(f"oracle: image {cam.name} is {img.shape[1]}x{img.shape[0]} but its "
                             f"camera is {cam.width}x{cam.height}")
        cols.append(img[np.ix_(rows, colsi)])
        K_net.append(scale_intrinsics(cam.K, 1.0 / k))
    arrays = {
        "image_names": np.array(names),
        "cam_from_world": np.stack([c.cam_from_world for c in noisy]).astype(np.float32),
        "intrinsics": np.stack(K_net).astype(np.float32),
        "intrinsics_original": np.stack([c.K for c in noisy]).astype(np.float32),
        "image_sizes_original": np.array([[c.width, c.height] for c in noisy], dtype=np.int64),
        "world_points": np.stack(pts).astype(np.float32),
        "world_points_conf": np.stack(confs).astype(np.float32),
        "colors": np.stack(cols).astype(np.uint8),
        "depth": np.stack(dep).astype(np.float32),
        "depth_conf": np.stack(confs).astype(np.float32),
    }
    return arrays, noisy


def run_oracle(scene: str | Path, names: list[str], out_dir: str | Path, noise: OracleNoise,
               seed: int = 0, downsample: int = 1, max_points: int = MAX_POINTS) -> dict:
    """Write ``out_dir/predictions.npz``, ``out_dir/sparse/0`` (noisy cameras and the
    confidence-ranked top ``max_points`` foreground points) and ``out_dir/status.json``.

    Returns:
        The status record (success is always true: the oracle registers every view).
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    names = list(dict.fromkeys(names))
    if not names:
        raise ValueError("oracle: no training image names given")
    arrays, noisy = make_oracle_predictions(scene, names, noise, seed, downsample)
    save_npz(out_dir / "predictions.npz", **arrays)
    conf = arrays["world_points_conf"].reshape(-1)
    pts = arrays["world_points"].reshape(-1, 3)
    col = arrays["colors"].reshape(-1, 3)
    fg = np.flatnonzero(arrays["depth"].reshape(-1) > 0)
    keep = fg[np.argsort(-conf[fg], kind="stable")[:max_points]]
    write_text_model(out_dir / "sparse" / "0", noisy, pts[keep], col[keep])
    status = {
        "success_paper": True, "aligned_ok": len(names) >= 3, "registered": len(names),
        "n_images": len(names), "points": int(len(keep)), "reason": None,
        "wall_time_s": time.perf_counter() - t0, "seed": int(seed), "noise": asdict(noise),
        "downsample": int(downsample), "grid_size": list(arrays["world_points"].shape[1:3]),
    }
    write_json(out_dir / "status.json", status)
    log.info("oracle: %d views, grid %s, noise %s, %d model points, %.2f s", len(names),
             status["grid_size"], asdict(noise), len(keep), status["wall_time_s"])
    return status


def add_noise_args(p: argparse.ArgumentParser, outliers: str) -> None:
    """The noise flags of an initialiser built on the reference cameras (:class:`OracleNoise`'s
    fields and defaults): ``--rot-deg``, ``--trans-frac``, ``--depth-rel``, ``--outlier-frac``
    (a fraction of the ``outliers``: "pixels" of the oracle's maps, "points" of posed's model)."""
    p.add_argument("--rot-deg", type=flag(float, 0), default=OracleNoise.rot_deg,
                   help="RMS rotation noise (degrees)")
    p.add_argument("--trans-frac", type=flag(float, 0), default=OracleNoise.trans_frac,
                   help="RMS centre noise, fraction of the trajectory radius")
    p.add_argument("--depth-rel", type=flag(float, 0), default=OracleNoise.depth_rel,
                   help="relative depth noise (std)")
    p.add_argument("--outlier-frac", type=flag(float, 0, 1), default=OracleNoise.outlier_frac,
                   help=f"fraction of outlier {outliers}")


def main(argv: list[str] | None = None) -> int:
    """CLI: ``python -m evaluation.initialisers.oracle --scene DIR (--split JSON --n N | --image-list FILE |
    --names ...) --out DIR [noise options] [--seed S]``."""

    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.oracle",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="prepared scene with sparse/0 and gt/depth")
    add_view_args(p)
    p.add_argument("--out", required=True, help="output folder (predictions.npz, sparse/0, status.json)")
    add_noise_args(p, outliers="pixels")
    p.add_argument("--conf-scale", type=flag(float, 0), default=OracleNoise.conf_scale,
                   help="confidence range above 1")
    p.add_argument("--conf-noise", type=flag(float, 0), default=OracleNoise.conf_noise,
                   help="log-normal noise on the confidence (0 = perfect ranking)")
    p.add_argument("--conf-mode", choices=CONF_MODES, default=OracleNoise.conf_mode,
                   help="confidence informativeness: ranked (ranks the depth error), noise "
                   "(random order), anti (reversed ranks); see the module docstring")
    p.add_argument("--downsample", type=flag(int, 1), default=1, help="prediction grid stride")
    p.add_argument("--max-points", type=flag(int, 1), default=MAX_POINTS,
                   help="points kept in sparse/0 at most (default %(default)s)")
    p.add_argument("--seed", type=flag(int, 0), default=0, help="random seed of the noise")
    add_log_flags(p)
    args, names = parse_training_args(p, argv)
    noise = OracleNoise(args.rot_deg, args.trans_frac, args.depth_rel, args.outlier_frac,
                        args.conf_scale, args.conf_noise, args.conf_mode)
    from camio.images import ImageReadError
    from runtime.outdir import prepare_out, run_stage, typed_line

    def work() -> None:
        # the stage's name in its .stage marker stays the flat layout's (reruns into older folders)
        prepare_out(args.out, {"--scene": args.scene, "--split": args.split, "--image-list": args.image_list},
                    "evaluation.oracle")
        run_oracle(args.scene, names, args.out, noise, args.seed, args.downsample, args.max_points)

    # bad input: one line naming the file
    return run_stage(log, work, errors=(ImageReadError, FileNotFoundError), line=typed_line)


if __name__ == "__main__":
    raise SystemExit(main())
