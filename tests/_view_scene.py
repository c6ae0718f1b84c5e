"""A small synthetic trained model and its cameras for the viewer tests and benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camio import Camera
from camio.cameras import look_at
from camio.colmap import write_text_model
from camio.ply import GaussianCloud, write_gaussian_ply

SH_C0 = 0.28209479177387814


def make_model(n: int = 400, seed: int = 0, sh_degree: int = 3) -> GaussianCloud:
    """``n`` Gaussians in a ball of radius 1: SH degree ``sh_degree`` view-dependent colour, a
    third of them with base colours above 1 (DC term alone > 1, pulled back by their SH bands)."""
    rng = np.random.default_rng(seed)
    means = rng.normal(size=(n, 3)) * 0.45
    base = rng.uniform(0.1, 0.9, size=(n, 3))
    base[: n // 3] = rng.uniform(1.05, 1.4, size=(n // 3, 3))
    sh_dc = (base - 0.5) / SH_C0
    k = (sh_degree + 1) ** 2 - 1
    sh_rest = rng.normal(size=(n, k, 3)) * 0.35
    opacity = rng.uniform(0.3, 0.95, size=n)
    log_scales = np.log(rng.uniform(0.03, 0.12, size=(n, 3)))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return GaussianCloud(means=means, sh_dc=sh_dc, sh_rest=sh_rest,
                         opacity_logit=np.log(opacity / (1 - opacity)), log_scales=log_scales, quats=q)


def make_cameras(width: int = 160, height: int = 120, n: int = 4, radius: float = 3.0,
                 prefix: str = "view") -> list[Camera]:
    """Cameras around the origin; the principal point is off centre (by ~12 and ~9 px)."""
    f = 0.9 * width
    K = np.array([[f, 0, width / 2 + 0.075 * width], [0, f * 1.02, height / 2 - 0.075 * height], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        eye = np.array([radius * np.sin(a), -0.6 + 0.3 * i, -radius * np.cos(a)])
        cams.append(Camera(f"{prefix}{i:02d}.png", width, height, K, look_at(eye, np.zeros(3))))
    return cams


def write_view_scene(root: Path, n: int = 400, width: int = 160, height: int = 120) -> dict[str, Path]:
    root = Path(root)
    model = write_gaussian_ply(root / "model.ply", make_model(n))
    seed = write_gaussian_ply(root / "seed.ply", make_model(max(n // 4, 1), seed=1, sh_degree=0))
    train = write_text_model(root / "train", make_cameras(width, height, 4))
    test = write_text_model(root / "test", make_cameras(width, height, 2, radius=3.3, prefix="held"))
    return {"model": model, "seed": seed, "cameras": train, "test_cameras": test, "root": root}
