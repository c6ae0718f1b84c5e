"""Tiny generated scenes for the splat_train trainer tests (no machine data needed).

A few random Gaussians in front of cameras on an arc; the images are rendered with the
rasterizer itself, so a trainer started from a perturbed copy can fit them exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from camio.cameras import Camera, look_at
from camio.colmap import write_text_model
from camio.images import write_image
from camio.ply import GaussianCloud, write_gaussian_ply


def make_cameras(n: int = 4, width: int = 32, height: int = 24, radius: float = 3.0) -> list[Camera]:
    """n cameras on an arc of ``radius`` around the origin, looking at it (OpenCV axes)."""
    cams = []
    for i, a in enumerate(np.linspace(-0.5, 0.5, n)):
        eye = np.array([radius * np.sin(a), 0.3 * np.cos(3 * a), -radius * np.cos(a)])
        K = np.array([[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1.0]])
        cams.append(Camera(f"view_{i:02d}.png", width, height, K, look_at(eye, np.zeros(3))[:3]))
    return cams


def make_cloud(n: int = 60, seed: int = 0) -> GaussianCloud:
    """Random coloured Gaussians in [-0.8, 0.8]^3 (a plane-ish slab), fairly opaque."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.8, 0.8, (n, 3)) * np.array([1.0, 1.0, 0.3])
    return GaussianCloud.from_points(means, rng.uniform(0.1, 0.9, (n, 3)), np.full(n, 0.8),
                                     np.full(n, 0.15), sh_degree=3)


def render_cloud(cloud: GaussianCloud, cam: Camera, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """[H, W, 3] float32 render of ``cloud`` (SH degree 0) in ``cam``."""
    from splat_train import rasterize

    m = np.eye(4)
    m[:3] = cam.cam_from_world
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    out = rasterize(t(cloud.means), t(cloud.quats), torch.exp(t(cloud.log_scales)),
                    torch.sigmoid(t(cloud.opacity_logit)), t(cloud.sh_dc)[:, None, :], t(m), t(cam.K),
                    cam.width, cam.height, background=t(background), sh_degree=0)
    return out["rgb"].clamp(0, 1).numpy()


def write_scene(root: Path, n_views: int = 4, width: int = 32, height: int = 24, n_test: int = 0,
                seed_noise: float = 0.3) -> dict[str, Path]:
    """Write ``root/{seed.ply, sparse/0, images/}`` (+ ``test_sparse/0``, ``test_images/``).

    The seed is the ground-truth cloud with its colours and opacities perturbed by
    ``seed_noise`` so that training has something to fit.
    """
    cams = make_cameras(n_views + n_test, width, height)
    gt = make_cloud()
    test_idx = set(range(1, len(cams), 2)[:n_test]) if n_test else set()
    train_cams = [c for i, c in enumerate(cams) if i not in test_idx]
    test_cams = [c for i, c in enumerate(cams) if i in test_idx]
    for c in cams:
        folder = "test_images" if c in test_cams else "images"
        write_image(root / folder / c.name, render_cloud(gt, c))
    write_text_model(root / "sparse" / "0", train_cams)
    if test_cams:
        write_text_model(root / "test_sparse" / "0", test_cams)
    rng = np.random.default_rng(1)
    seed = GaussianCloud(means=gt.means, sh_dc=gt.sh_dc + rng.normal(0, seed_noise / 0.28, gt.sh_dc.shape),
                         sh_rest=gt.sh_rest, opacity_logit=gt.opacity_logit - 1.0,
                         log_scales=gt.log_scales + rng.normal(0, seed_noise, gt.log_scales.shape),
                         quats=gt.quats)
    write_gaussian_ply(root / "seed.ply", seed)
    paths = {"seed": root / "seed.ply", "cameras": root / "sparse" / "0", "images": root / "images"}
    if test_cams:
        paths.update(test_cameras=root / "test_sparse" / "0", test_images=root / "test_images")
    return paths


def write_pose_scene(root: Path, n_views: int = 5, width: int = 64, rot_deg: float = 1.5,
                     trans_frac: float = 0.03, seed: int = 1) -> dict:
    """A scene for pose refinement: exact Gaussians (a cube of 150, enough depth range that a
    small rotation and a sideways shift do not look alike), exact images, and training cameras
    perturbed by the oracle's noise model with the first camera left exact (the gauge).

    Returns:
        paths ``seed``, ``cameras`` (perturbed), ``images``, and ``truth`` / ``given``: the
        exact and perturbed camera lists.
    """
    from evaluation.initialisers.oracle import OracleNoise, perturb_cameras

    rng = np.random.default_rng(0)
    n = 150
    gt = GaussianCloud.from_points(rng.uniform(-0.8, 0.8, (n, 3)), rng.uniform(0.05, 0.95, (n, 3)),
                                   np.full(n, 0.9), np.full(n, 0.08), sh_degree=3)
    cams = make_cameras(n_views, width, width * 3 // 4)
    for c in cams:
        write_image(root / "images" / c.name, render_cloud(gt, c))
    noisy = perturb_cameras(cams, OracleNoise(rot_deg=rot_deg, trans_frac=trans_frac), np.random.default_rng(seed))
    noisy[0] = cams[0]
    write_text_model(root / "sparse" / "0", noisy)
    write_gaussian_ply(root / "seed.ply", gt)
    return {"seed": root / "seed.ply", "cameras": root / "sparse" / "0", "images": root / "images",
            "truth": cams, "given": noisy}


def kill_at_loss_call(monkeypatch, call: int):
    """Make the trainer's loss raise KeyboardInterrupt at its ``call``-th call, as a run killed
    inside that iteration; returns a function that puts the real loss back (for the resume)."""
    from splat_train import losses as losses_mod

    real, calls = losses_mod.photometric_loss, {"n": 0}

    def killed(*args):
        calls["n"] += 1
        if calls["n"] == call:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(losses_mod, "photometric_loss", killed)
    return lambda: monkeypatch.setattr(losses_mod, "photometric_loss", real)
