"""One benchmark run: train a recipe on a prepared cell, score its final model, write one record.

Training is ``python -m splat_train`` with the held-out curve (PSNR, SSIM along the run);
the final model is rendered into the aligned held-out cameras (``python -m splat_train
render``) and scored by ``python -m evaluation images`` (PSNR, SSIM, LPIPS-Alex, LPIPS-VGG),
the same commands the workflow runs. The record holds the keys of the results table
(:data:`RECORD_KEYS`) and the held-out curve.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from benchmarks._proc import run_stage as sh

RECORD_KEYS = ("scene", "role", "n", "recipe", "seed", "iterations", "psnr", "ssim", "lpips_alex", "lpips_vgg",
               "gaussians", "train_s", "backend")


def run_name(scene: str, n: int, recipe: str, seed: int, iterations: int) -> str:
    return f"{scene}_n{n}_{recipe}_s{seed}_i{iterations}"


def train_and_score(cell: dict[str, Path], out: Path, recipe: str, seed: int, iterations: int,
                    eval_every: int, config: dict | None = None, kernel_threads: int = 0) -> dict:
    """Train ``recipe`` (plus ``config`` overrides) on ``cell`` into ``out`` unless its train.json
    exists, then score the final model unless its metrics.json exists; return the measures."""
    logf = out.parent / f"{out.name}.log"
    if not (out / "train.json").is_file():
        cfg = {"recipe": recipe, **(config or {})}
        sh(["-m", "splat_train", "--seed-ply", str(cell["bridge"] / "seed.ply"), "--cameras", str(cell["bridge"]),
            "--images", str(cell["scene"] / "images"), "--image-list", str(cell["train"]),
            "--test-cameras", str(cell["align"]), "--test-images", str(cell["scene"] / "images"),
            "--test-image-list", str(cell["test"]), "--out", str(out), "--iterations", str(iterations),
            "--seed", str(seed), "--eval-every", str(eval_every), "--checkpoint-every", str(iterations),
            "--kernel-threads", str(kernel_threads), "--config", json.dumps(cfg)], logf)
    metrics = out / "final" / "metrics.json"
    if not metrics.is_file():
        renders, gt = out / "final" / "renders", out / "final" / "gt"
        sh(["-m", "splat_train", "render", "--model", str(out / "model.ply"), "--cameras",
            str(cell["align"] / "sparse" / "0"), "--images", str(cell["scene"] / "images"), "--image-list",
            str(cell["test"]), "--out", str(renders), "-q"], logf)
        gt.mkdir(parents=True, exist_ok=True)
        for name in cell["test"].read_text().split():
            link = gt / name
            if not link.exists():
                link.symlink_to((cell["scene"] / "images" / name).resolve())
        sh(["-m", "evaluation", "images", "--pred", str(renders), "--gt", str(gt), "--out", str(metrics),
            "--lpips-nets", "alex", "vgg"], logf)
    tj = json.loads((out / "train.json").read_text())
    m = json.loads(metrics.read_text())
    return {"train": tj, "metrics": m}


def record(scene, role: str, n: int, recipe: str, seed: int, iterations: int, result: dict,
           config: dict | None = None) -> dict:
    """The run's record: :data:`RECORD_KEYS` first, then the held-out curve and what ran."""
    tj, m = result["train"], result["metrics"]
    mean = m.get("mean", m)
    c = tj.get("test_curve", {})
    return {
        "scene": scene, "role": role, "n": n, "recipe": recipe, "seed": seed, "iterations": iterations,
        "psnr": mean.get("psnr"), "ssim": mean.get("ssim"), "lpips_alex": mean.get("lpips_alex"),
        "lpips_vgg": mean.get("lpips_vgg"), "gaussians": tj["num_gaussians"], "train_s": tj["wall_time_s"],
        "backend": tj.get("rasterizer"),
        "best_psnr": c.get("best_test_psnr"), "best_iteration": c.get("best_iteration"),
        "curve": {"iterations": c.get("iterations"), "psnr": c.get("test_psnr")},
        "config": {"recipe": recipe, **(config or {})}, "schedule": tj.get("schedule"),
        "device": tj.get("device"), "recorded": time.strftime("%Y-%m-%d"),
    }
