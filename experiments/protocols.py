"""Both evaluation protocols on a real scene's n = 3 cell, for each initialiser, by stage commands.

The strict protocol renders each held-out view at its reference pose mapped into the model frame
by the Sim(3) fitted on the training cameras; the test-pose protocol first optimises that pose
alone against the held-out image with the model frozen (docs/protocols.md). This benchmark runs
both on the cells of config/protocols_fern.yaml (LLFF fern, n = 3, ``posed`` and COLMAP), and a
recovery check: the ``posed`` model's held-out cameras moved by a known rigid error, then
refined, against the PSNR at the unmoved pose.

    python experiments/protocols.py prepare DEST      # on a CPU: snakemake for the CPU stages
                                                     # (scene, initialisers, Bridge, alignment)
    python experiments/protocols.py run DEST --out OUT [--device cuda] [--iterations N]

``run`` calls the commands the workflow's rules call (train_splats, render_test,
testpose_refine, image_metrics, testpose_metrics), so a GPU machine without Snakemake, open3d
or a package index runs it from the carried folder (scripts/gpu_run.sh's setup). It writes
``OUT/protocols.json`` after every step (a run cut short keeps what it measured) and
``OUT/protocols.md``. LPIPS needs weights that a bare machine does not have: PSNR and SSIM.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script too
from experiments._proc import run_logged  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "protocols_fern.yaml"
SCENE = "llff/fern"
N = 3
MODE = "uniform"
INITS = ("posed", "colmap")
#: The recovery check's known error of each held-out camera: a rotation of this many degrees
#: about a random axis and a camera-centre shift of this fraction of the scene depth.
PERTURB_DEG = 1.0
PERTURB_FRAC = 0.02


def _scene_images(scene: Path) -> Path:
    """The prepared scene's image folder (undistorted/ or converted/)."""
    for kind in ("undistorted", "converted", "synth"):
        if (scene / kind / "images").is_dir():
            return scene / kind / "images"
    raise FileNotFoundError(f"no prepared images under {scene}")


def prepare(dest: Path, results: Path | None = None) -> Path:
    """Run config/protocols_fern.yaml's CPU stages with Snakemake and copy what ``run`` reads
    (images, held-out images, the training list, each initialiser's bridge/ and align/)."""
    if dest.exists():
        raise FileExistsError(f"{dest} exists; remove it or choose another folder")
    with tempfile.TemporaryDirectory(prefix="protocols_") as tmp:
        res = (results or Path(tmp) / "results").resolve()
        cells = [res / SCENE / f"n{N}" / init / MODE for init in INITS]
        targets = [str(c / "align" / "align.json") for c in cells]
        if not all(Path(t).is_file() for t in targets):
            run_logged([shutil.which("snakemake") or "snakemake", "--cores", "2", "--configfile", str(CONFIG),
                  "--config", f"results={res}", "--", *targets], Path(tmp) / "snakemake.log")
        staging = dest.with_name(dest.name + ".partial")
        shutil.rmtree(staging, ignore_errors=True)
        scene = res / SCENE
        (staging / "images").mkdir(parents=True)
        train_list = scene / f"n{N}" / "train.txt"
        for name in train_list.read_text().split():  # only the training views: the carried folder stays small
            shutil.copy2(_scene_images(scene) / name, staging / "images" / name)
        shutil.copytree(scene / "test_images", staging / "test_images")
        shutil.copy2(train_list, staging / "train.txt")
        for init, cell in zip(INITS, cells):
            for part in ("bridge", "align"):
                shutil.copytree(cell / part, staging / init / part, ignore=shutil.ignore_patterns("*.log"))
        (staging / "prepared.json").write_text(json.dumps(
            {"config": str(CONFIG.relative_to(ROOT)), "scene": SCENE, "n": N, "mode": MODE, "inits": list(INITS),
             "made_on": os.uname().nodename, "made_at": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=2) + "\n")
        staging.rename(dest)
    return dest


def _metrics(pred: Path, gt: Path, out: Path, log: Path) -> dict:
    run_logged([sys.executable, "-m", "evaluation", "images", "--pred", str(pred), "--gt", str(gt), "--out", str(out),
          "--lpips-nets"], log)
    m = json.loads(out.read_text())
    return {k: m.get(k) for k in ("psnr", "ssim", "n_images", "per_image")}


def _perturb(cam_from_world: np.ndarray, depth: float, rng: np.random.Generator) -> np.ndarray:
    """[3, 4] pose moved by PERTURB_DEG about a random axis and PERTURB_FRAC * depth along a
    random direction (left-multiplied, camera frame)."""
    axis = rng.normal(size=3)
    k = axis / np.linalg.norm(axis)
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = math.radians(PERTURB_DEG)
    R = np.eye(3) + math.sin(a) * Kx + (1.0 - math.cos(a)) * Kx @ Kx  # Rodrigues
    d = rng.normal(size=3)
    t = PERTURB_FRAC * depth * d / np.linalg.norm(d)
    out = np.asarray(cam_from_world, dtype=np.float64)[:3].copy()
    return np.concatenate([R @ out[:, :3], (R @ out[:, 3] + t)[:, None]], 1)


def recovery(model: Path, cameras: Path, images: Path, device: str, steps: int, seed: int = 0) -> dict:
    """Held-out PSNR at the aligned pose (exact), at a known moved pose (what the strict protocol
    charges for that error) and after the test-pose refinement from the moved pose."""
    import torch

    from camio.ply import read_gaussian_ply
    from splat_train.data import load_views
    from splat_train.export import camera_tensors, render_params
    from splat_train.gaussians import params_from_cloud
    from splat_train.losses import psnr
    from splat_train.render.rasterize import resolve_backend
    from splat_train.testpose import refine_test_pose, scene_depth

    cloud = read_gaussian_ply(model)
    params = {k: v.requires_grad_(False) for k, v in params_from_cloud(cloud, sh_degree=cloud.sh_degree,
                                                                          device=device).items()}
    backend = resolve_backend("auto", device)
    bg = torch.zeros(3, device=device)
    rng = np.random.default_rng(seed)
    rows = {}
    for v in load_views(cameras, images, None):
        cw, K = camera_tensors(v.camera, device)
        target = torch.as_tensor(v.image, device=device)

        def score(pose):
            with torch.no_grad():
                rgb = render_params(params, cloud.sh_degree, pose, K, v.camera.width, v.camera.height, bg, backend)["rgb"]
            return psnr(rgb.clamp(0.0, 1.0), target)

        moved_np = _perturb(cw.cpu().double().numpy(), scene_depth(params["means"], cw), rng)
        moved = cw.clone()
        moved[:3] = torch.as_tensor(moved_np, dtype=cw.dtype, device=device)
        t0 = time.perf_counter()
        res = refine_test_pose(params, cloud.sh_degree, moved, K, target, steps=steps, backend=backend)
        rows[v.name] = {"exact": score(cw), "moved": score(moved), "refined": score(res["cam_from_world"]),
                        "refine_s": time.perf_counter() - t0}
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in ("exact", "moved", "refined")}
    return {"perturbation": {"rot_deg": PERTURB_DEG, "trans_frac_depth": PERTURB_FRAC, "seed": seed},
            "steps": steps, "views": rows, "mean_psnr": mean,
            "refined_minus_exact_db": mean["refined"] - mean["exact"], "moved_minus_exact_db": mean["moved"] - mean["exact"]}


def run(folder: Path, out: Path, device: str = "cuda", iterations: int | None = None, steps: int | None = None,
        inits: tuple[str, ...] = INITS) -> dict:
    """Train, and score under both protocols, every prepared initialiser's cell on ``device``."""
    from splat_train.testpose import DEFAULT_STEPS

    steps = DEFAULT_STEPS if steps is None else steps
    folder, out = folder.resolve(), out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    report = {"prepared": json.loads((folder / "prepared.json").read_text()), "device": device,
              "iterations": iterations, "testpose_steps": steps, "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "cells": {}}
    try:
        import torch

        if device == "cuda":
            report["gpu"] = torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001  (the record only)
        pass

    def save():
        (out / "protocols.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
        (out / "protocols.md").write_text(table(report))

    for init in inits:
        cell, work = folder / init, out / init
        work.mkdir(parents=True, exist_ok=True)
        row: dict = {}
        report["cells"][init] = row
        try:
            train = [sys.executable, "-m", "splat_train", "--seed-ply", str(cell / "bridge" / "seed.ply"),
                     "--cameras", str(cell / "bridge" / "sparse" / "0"), "--images", str(folder / "images"),
                     "--image-list", str(folder / "train.txt"), "--out", str(work / "train"), "--seed", "0",
                     "--device", device, "--test-cameras", str(cell / "align" / "sparse" / "0"),
                     "--test-images", str(folder / "test_images"), "--no-eval-lpips"]
            if iterations is not None:
                train += ["--iterations", str(iterations)]
            row["train_s"] = run_logged(train, work / "train.log")
            summary = json.loads((work / "train" / "train.json").read_text())
            row["train"] = {k: summary.get(k) for k in ("iterations", "recipe", "num_gaussians", "test_psnr",
                                                        "wall_time_s", "rasterizer", "peak_cuda_mb")}
            curve = summary.get("test_curve") or {}
            row["train"].update({k: curve.get(k) for k in ("best_iteration", "best_test_psnr")})
            model = work / "train" / "model.ply"
            row["render_s"] = run_logged([sys.executable, "-m", "splat_train", "render", "--model", str(model), "--cameras",
                                    str(cell / "align" / "sparse" / "0"), "--images", str(folder / "test_images"),
                                    "--out", str(work / "renders"), "--device", device], work / "render.log")
            row["strict"] = _metrics(work / "renders", folder / "test_images", work / "metrics.json",
                                     work / "metrics.log")
            save()
            row["testpose_s"] = run_logged([sys.executable, "-m", "splat_train", "testpose", "--model", str(model),
                                      "--cameras", str(cell / "align" / "sparse" / "0"), "--images",
                                      str(folder / "test_images"), "--out", str(work / "testpose"), "--steps",
                                      str(steps), "--device", device], work / "testpose.log")
            tp = json.loads((work / "testpose" / "testpose.json").read_text())
            row["testpose_record"] = {k: tp.get(k) for k in ("steps", "backend", "mean_rotation_deg", "max_rotation_deg",
                                                             "mean_translation_rel_depth", "wall_time_s")}
            row["test-pose"] = _metrics(work / "testpose" / "renders", folder / "test_images",
                                        work / "testpose_metrics.json", work / "testpose_metrics.log")
            save()
            if init == "posed":
                row["recovery"] = recovery(model, cell / "align" / "sparse" / "0", folder / "test_images", device, steps)
        except Exception as exc:  # noqa: BLE001  (record and go on with the next cell)
            row["error"] = f"{type(exc).__name__}: {str(exc)[-2000:]}"
        save()
        print(init, json.dumps({k: v for k, v in row.items() if k != "recovery"}, default=str)[:2000], flush=True)
    return report


def _f(x, spec=".2f") -> str:
    return "n/a" if x is None else format(x, spec)


def table(report: dict) -> str:
    """The Markdown summary: a row per initialiser, both protocols' PSNR and SSIM."""
    lines = [f"# Both protocols, {report['prepared']['scene']} n = {report['prepared']['n']}",
             "", f"Device {report.get('gpu', report['device'])}; training iterations "
             f"{report['iterations'] or 'the device default'}; test-pose {report['testpose_steps']} Adam steps per view.",
             "", "| init | Gaussians | PSNR [strict] | SSIM [strict] | PSNR [test-pose] | SSIM [test-pose] | "
             "mean pose change (deg) | train s | test-pose s |", "|---|---|---|---|---|---|---|---|---|"]
    for init, r in report["cells"].items():
        s, t = r.get("strict", {}), r.get("test-pose", {})
        lines.append(f"| {init} | {r.get('train', {}).get('num_gaussians', 'n/a')} | {_f(s.get('psnr'))} | "
                     f"{_f(s.get('ssim'), '.3f')} | {_f(t.get('psnr'))} | {_f(t.get('ssim'), '.3f')} | "
                     f"{_f(r.get('testpose_record', {}).get('mean_rotation_deg'), '.3f')} | {_f(r.get('train_s'), '.0f')} | "
                     f"{_f(r.get('testpose_s'), '.1f')} |" + (f" error: {r['error'][:200]}" if "error" in r else ""))
    rec = report["cells"].get("posed", {}).get("recovery")
    if rec:
        m = rec["mean_psnr"]
        lines += ["", f"Recovery (posed model; held-out cameras moved by {rec['perturbation']['rot_deg']} deg and "
                      f"{rec['perturbation']['trans_frac_depth']} x scene depth): exact {m['exact']:.2f} dB, moved "
                      f"{m['moved']:.2f} dB, refined {m['refined']:.2f} dB "
                      f"(refined - exact {rec['refined_minus_exact_db']:+.2f} dB)."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    pp = sub.add_parser("prepare", help="run the CPU stages with snakemake here and keep what `run` reads")
    pp.add_argument("dest", type=Path, help="folder to create")
    pp.add_argument("--results", type=Path, default=None, help="a results folder that already holds the cells")
    pr = sub.add_parser("run", help="train and score both protocols from a prepared folder")
    pr.add_argument("folder", type=Path, help="a folder made by `prepare`")
    pr.add_argument("--out", type=Path, required=True, help="output folder (protocols.json, protocols.md, runs)")
    pr.add_argument("--device", default="cuda", choices=["cpu", "cuda"], help="where to train and score")
    pr.add_argument("--iterations", type=int, default=None, help="training iterations (default: the device's)")
    pr.add_argument("--steps", type=int, default=None, help="test-pose Adam steps per view (default: the protocol's)")
    pr.add_argument("--inits", default=",".join(INITS), help="comma list of prepared initialisers to run")
    args = p.parse_args(argv)
    try:
        if args.command == "prepare":
            print(f"protocols: prepared {prepare(args.dest, args.results)}")
            return 0
        folder, out = args.folder.resolve(), args.out.resolve()
        if not (folder / "prepared.json").is_file():
            raise FileNotFoundError(f"{args.folder} is not a folder made by `protocols.py prepare` (no prepared.json)")
        if out == folder or folder in out.parents or out in folder.parents:
            raise ValueError(f"--out {args.out} overlaps the prepared folder {args.folder}: choose another")
    except (OSError, ValueError) as exc:
        print(f"protocols: error: {exc}", file=sys.stderr)
        return 2
    report = run(args.folder, args.out, args.device, args.iterations, args.steps, tuple(args.inits.split(",")))
    print(table(report))
    return 0 if all("error" not in r for r in report["cells"].values()) else 1


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    raise SystemExit(run_command(main))
