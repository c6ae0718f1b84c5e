"""A small fake results tree with real JSON / Parquet / PNG / TSV files (evaluation tests).

Layout as workflow/rules/common.smk writes it: ``{root}/results/mip360/{scene}/n{n}/{init}/``
holds the initialiser's outputs (status.json, timing.json, pose.json, benchmarks/*.tsv) and one
folder per bridge mode, ``{init}/{mode}/`` (bridge/bridge.json, train/{train.json,log.parquet},
renders/*.png, metrics.json, benchmarks/metrics.tsv). Scenes ``garden`` and ``room`` (with
reference cameras: pose.json) and ``nus`` (none), n in {3, 6}, inits ``colmap`` (mode uniform)
and ``vggt`` (mode gated; on ``room`` also uniform, 0.5 dB worse):

* colmap on garden n=3 failed: only status.json (reason "no initial pair").
* colmap on room n=3 passes the paper's criterion with wrong poses (ATE 40% of the radius).
* colmap on nus n=3 registered only 2 views (paper success; too few views to align, and nus
  has no reference cameras anyway).
* every other run succeeded.

PSNR values are chosen so that the expected table cells can be computed by hand
(:func:`psnr_of`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from camio.images import write_image

SCENES = ("garden", "room", "nus")
NS = (3, 6)
TEST_VIEWS = ("img000", "img008")


def psnr_of(scene: str, n: int, init: str, mode: str | None = None) -> float:
    base = {"garden": 20.0, "room": 24.0, "nus": 16.0}[scene]
    return base + n * 0.5 + (1.0 if init == "vggt" else 0.0) - (0.5 if init == "vggt" and mode == "uniform" else 0.0)


def _write(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _image(path: Path, value: float) -> None:
    img = np.full((24, 32, 3), value, np.float32)
    img[:, :8] = 1.0 - value
    write_image(path, img)


def build(root: Path) -> tuple[Path, Path]:
    """Write the tree; returns (results dir, scenes dir with ground-truth images)."""
    results, scenes = root / "results", root / "scenes"
    for scene in SCENES:
        for v, name in enumerate(TEST_VIEWS):
            _image(scenes / "mip360" / scene / "images" / f"{name}.JPG", 0.2 + 0.1 * v)
        for n in NS:
            for init in ("colmap", "vggt"):
                run = results / "mip360" / scene / f"n{n}" / init
                run.mkdir(parents=True)
                failed = init == "colmap" and n == 3 and scene == "garden"
                two_reg = init == "colmap" and n == 3 and scene == "nus"
                if init == "colmap":
                    _write(run / "status.json", {
                        "success_paper": not failed, "aligned_ok": not (failed or two_reg),
                        "registered": 0 if failed else (2 if two_reg else n), "n_images": n,
                        "points": 0 if failed else 500, "reason": "no initial pair" if failed else None,
                        "wall_time_s": 30.0 + n, "peak_rss_mb": 900.0, "seed": 0,
                        **({"repeats": {"n_runs": 3, "seeds": [0, 1, 2], "success_paper_rate": 2 / 3,
                                        "aligned_ok_rate": 1 / 3,
                                        "registered": {"values": [2, 3, 2], "min": 2.0, "max": 3.0}}}
                           if two_reg else {})})
                    if failed or two_reg:
                        continue
                else:
                    _write(run / "timing.json", {"total_s": 10.0, "peak_gpu_mb": 14000.0, "peak_rss_mb": 3000.0})
                (run / "benchmarks").mkdir()
                (run / "benchmarks" / f"{'colmap_baseline' if init == 'colmap' else 'vggt_init'}.tsv").write_text(
                    "s\th:m:s\tmax_rss\tmax_vms\n12.0\t0:00:12\t700.0\t2000\n")
                wrong = init == "colmap" and scene == "room" and n == 3
                if scene != "nus":
                    _write(run / "pose.json", {
                        "ate_rmse": 0.4 if wrong else 0.01, "ate_rel_radius": 0.4 if wrong else 0.01,
                        "ate_pct_radius": 40.0 if wrong else 1.0, "rpe_rot_deg": 30.0 if wrong else 1.0,
                        "rpe_trans_dir_deg": 20.0 if wrong else 2.0,
                        "rel_rot_err_mean_deg": 30.0 if wrong else 1.0, "rel_rot_err_max_deg": 50.0 if wrong else 2.0,
                        "n_matched": n, "registered": n, "success_paper": True, "has_reference": True,
                        "fy_fx_max_dev": 0.001, "wall_time_s": 0.5})
                modes = ["uniform"] if init == "colmap" else (["gated", "uniform"] if scene == "room" else ["gated"])
                for mode in modes:
                    _mode_run(run / mode, scene, n, init, mode)
    return results, scenes


def _mode_run(d: Path, scene: str, n: int, init: str, mode: str) -> None:
    _write(d / "bridge" / "bridge.json", {"mode": mode, "wall_time_s": 2.0})
    p = psnr_of(scene, n, init, mode)
    _write(d / "metrics.json", {"psnr": p, "ssim": 0.5 + 0.01 * n, "lpips_alex": 0.3, "lpips_vgg": 0.4,
                                "n_images": 2, "per_image": [], "wall_time_s": 1.5})
    if init == "vggt":  # scored under the test-pose protocol too: 1 dB above the strict PSNR
        _write(d / "testpose" / "metrics.json", {"psnr": p + 1.0, "ssim": 0.6, "lpips_alex": 0.25,
                                                 "lpips_vgg": 0.35, "n_images": 2, "per_image": []})
        _write(d / "testpose" / "refine" / "testpose.json", {"protocol": "test-pose", "steps": 500, "patience": 100,
                                                             "mean_rotation_deg": 0.5, "views": {}})
    _write(d / "train" / "train.json", {"wall_time_s": 100.0 + n, "num_gaussians": 1000 * n, "iterations": 1000})
    it = np.arange(0, 1001, 100)
    pd.DataFrame({"iteration": it, "wall_time_s": it * 0.1, "loss": 0.5 / (1 + it / 100.0), "l1": 0.1,
                  "ssim": 0.8, "num_gaussians": 1000 + it,
                  "test_psnr": np.where(it % 500 == 0, p - 3 + it / 500.0, np.nan)}).to_parquet(d / "train" / "log.parquet")
    for v, name in enumerate(TEST_VIEWS):
        _image(d / "renders" / f"{name}.png", 0.25 + 0.1 * v)
        if init == "vggt":  # the test-pose protocol's renders
            _image(d / "testpose" / "refine" / "renders" / f"{name}.png", 0.3 + 0.1 * v)
    (d / "benchmarks").mkdir()
    (d / "benchmarks" / "metrics.tsv").write_text("s\th:m:s\tmax_rss\tmax_vms\n4.0\t0:00:04\t1200.5\t2000\n")
