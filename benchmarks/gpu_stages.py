"""One workflow cell's stage commands on CUDA, against the same cell run by Snakemake on a CPU.

A lent GPU machine reaches no package registry and takes 64 MiB of carried files: Snakemake,
open3d and their needs do not fit beside pycolmap and gsplat. So the GPU runs the stage
commands the workflow's rules run for one cell (``python -m splat_train`` and ``python -m
splat_train render`` with ``--device cuda``, ``python -m evaluation images``), plus
``python -m vggt_init`` on the fixture model (tests/data/vggt/shared, tiny, real reference
weights), on inputs that Snakemake made on a CPU; and compares with the CPU run's outputs.

    python benchmarks/gpu_stages.py prepare .gpu_wf      # on a CPU: snakemake --cores 2 for the cell
                                                         # of config.yaml, copies ~1 MB into .gpu_wf
    python -m benchmarks --gpu --stages .gpu_wf ...      # on the GPU (parts workflow_cell, vggt_cli)

The cell: :data:`CELL` of config.yaml (the bundled synthetic scene, oracle initialiser, n = 3,
gated Bridge, 300 iterations). What is compared: the held-out PSNR and SSIM of
``evaluation images`` (LPIPS weights are not carried), the trainer's held-out PSNR and
Gaussian count, training time; for VGGT the largest |CUDA - CPU| of each output array.
"""

from __future__ import annotations

import json
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
FIX = ROOT / "tests" / "data" / "vggt" / "shared"
SCENE = "synthetic/bundled"
CELL = f"{SCENE}/n3/oracle/gated"
CPU_FILE = "cpu.json"  # the CPU run's train.json and metrics.json, and what made them
VGGT_CPU = "vggt_cpu"
# What the train, render and metrics rules read, relative to the results folder
_INPUTS = (f"{SCENE}/synth/images", f"{SCENE}/test_images", f"{SCENE}/n3/train.txt", f"{CELL}/bridge",
           f"{CELL}/align")


def train_argv(res: Path, out: Path, cfg: dict, device: str) -> list[str]:
    """``python -m splat_train`` as the train_splats rule runs it for :data:`CELL` (the keys
    the rule passes, from the CPU run's train.json ``config``), on ``device``."""
    cell, scene = res / CELL, res / SCENE
    return [sys.executable, "-m", "splat_train", "--seed-ply", str(cell / "bridge" / "seed.ply"),
            "--cameras", str(cell / "bridge" / "sparse" / "0"), "--images", str(scene / "synth" / "images"),
            "--image-list", str(scene / "n3" / "train.txt"), "--out", str(out), "--iterations", str(cfg["iterations"]),
            "--recipe", cfg["recipe"], "--seed", str(cfg["seed"]), "--eval-every", str(cfg["eval_every"]),
            "--checkpoint-every", str(cfg["checkpoint_every"]), "--device", device, "--threads",
            str(cfg["num_threads"]), "--test-cameras", str(cell / "align" / "sparse" / "0"),
            "--test-images", str(scene / "test_images"), "--no-eval-lpips"]


def vggt_argv(out: Path, device: str) -> list[str]:
    """``python -m vggt_init`` on the fixture model and images (float32, 56 px)."""
    return [sys.executable, "-m", "vggt_init", "--images", str(FIX / "images"), "--out", str(out),
            "--model-config", str(FIX / "config.json"), "--checkpoint", str(FIX / "weights.safetensors"),
            "--image-size", "56", "--max-points", "500", "--dtype", "fp32", "--device", device]


def prepare(dest: Path, results: Path | None = None) -> Path:
    """Run the cell with Snakemake on this CPU (into ``results``, default a temporary folder)
    and keep in ``dest`` what the stage commands read, the CPU run's summaries and the CPU
    run of ``vggt_init`` on the fixture model."""
    if dest.exists():
        raise FileExistsError(f"{dest} exists; remove it or choose another folder")
    with tempfile.TemporaryDirectory(prefix="gpu_stages_") as tmp:
        res = (results or Path(tmp) / "results").resolve()
        target = res / CELL / "metrics.json"
        if not target.is_file():
            t0 = time.perf_counter()
            run_logged([shutil.which("snakemake") or "snakemake", "--cores", "2", "--config", f"results={res}", "--",
                  str(target)], Path(tmp) / "snakemake.log")
            print(f"gpu_stages: snakemake made {target} in {time.perf_counter() - t0:.0f} s", flush=True)
        staging = dest.with_name(dest.name + ".partial")
        shutil.rmtree(staging, ignore_errors=True)
        for part in _INPUTS:
            src, dst = res / part, staging / "results" / part
            dst.parent.mkdir(parents=True, exist_ok=True)
            (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst)
        summary = json.loads((res / CELL / "train" / "train.json").read_text())
        metrics = json.loads((res / CELL / "metrics.json").read_text())
        vg = staging / VGGT_CPU
        wall = run_logged(vggt_argv(Path(tmp) / "vggt", "cpu"), Path(tmp) / "vggt.log")
        vg.mkdir()
        shutil.copy2(Path(tmp) / "vggt" / "predictions.npz", vg / "predictions.npz")
        cpu = {"cell": CELL, "made_on": os.uname().nodename, "made_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
               "train": {k: summary.get(k) for k in ("test_psnr", "train_psnr", "num_gaussians", "wall_time_s",
                                                      "device", "rasterizer", "recipe", "config")},
               "metrics": {k: metrics.get(k) for k in ("psnr", "ssim", "lpips_alex", "lpips_vgg", "n_images")},
               "vggt_cli_s": wall}
        (staging / CPU_FILE).write_text(json.dumps(cpu, indent=2) + "\n")
        staging.rename(dest)
    return dest


def workflow_cell(folder: Path, device: str = "cuda") -> dict:
    """Train, render and score :data:`CELL` on ``device`` from a :func:`prepare` folder;
    the CPU run's figures beside, and the differences."""
    cpu = json.loads((folder / CPU_FILE).read_text())
    res = folder.resolve() / "results"
    with tempfile.TemporaryDirectory(prefix="gpu_stages_cell_") as tmp:
        work = Path(tmp)
        times = {"train": run_logged(train_argv(res, work / "train", cpu["train"]["config"], device), work / "train.log")}
        times["render"] = run_logged([sys.executable, "-m", "splat_train", "render", "--model", str(work / "train" / "model.ply"),
                                "--cameras", str(res / CELL / "align" / "sparse" / "0"), "--images",
                                str(res / SCENE / "test_images"), "--out", str(work / "renders"), "--device", device],
                               work / "render.log")
        times["metrics"] = run_logged([sys.executable, "-m", "evaluation", "images", "--pred", str(work / "renders"),
                                 "--gt", str(res / SCENE / "test_images"), "--out", str(work / "metrics.json")],
                                work / "metrics.log")
        summary = json.loads((work / "train" / "train.json").read_text())
        metrics = json.loads((work / "metrics.json").read_text())
    dev = {"train": {k: summary.get(k) for k in ("test_psnr", "train_psnr", "num_gaussians", "wall_time_s",
                                                 "device", "rasterizer", "recipe", "peak_cuda_mb")},
           "metrics": {k: metrics.get(k) for k in ("psnr", "ssim", "lpips_alex", "lpips_vgg", "n_images")},
           "stage_s": times}
    diff = {f"{k}_device_minus_cpu": dev["metrics"][k] - cpu["metrics"][k] for k in ("psnr", "ssim")
            if dev["metrics"].get(k) is not None and cpu["metrics"].get(k) is not None}
    return {"cell": CELL, "how": "stage commands on the device (snakemake not carried); inputs and the CPU "
            "figures from snakemake --cores 2 on a CPU", "device": device, "device_run": dev,
            "cpu_run": {k: cpu[k] for k in ("train", "metrics")}, "cpu_made_on": cpu.get("made_on"), **diff}


def vggt_cli(folder: Path, device: str = "cuda") -> dict:
    """``python -m vggt_init`` on the fixture model on ``device``; max |device - CPU| per output."""
    cpu = np.load(folder / VGGT_CPU / "predictions.npz")
    with tempfile.TemporaryDirectory(prefix="gpu_stages_vggt_") as tmp:
        wall = run_logged(vggt_argv(Path(tmp) / "out", device), Path(tmp) / "vggt.log")
        dev = np.load(Path(tmp) / "out" / "predictions.npz")
        errs = {k: float(np.abs(dev[k].astype(np.float64) - cpu[k].astype(np.float64)).max())
                for k in dev.files if np.issubdtype(dev[k].dtype, np.number)}
        timing = json.loads((Path(tmp) / "out" / "timing.json").read_text())
    return {"max_abs_diff_vs_cpu": errs, "names_equal": bool((dev["image_names"] == cpu["image_names"]).all()),
            "cli_s": wall, "timing": timing}


def main(argv: list[str] | None = None) -> int:
    import argparse

    from runtime.cliargs import plain

    p = argparse.ArgumentParser(description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    pp = sub.add_parser("prepare", help="run the cell with snakemake here and keep what the GPU needs")
    pp.add_argument("dest", type=Path)
    pp.add_argument("--results", type=Path, default=None, help="a results folder that already holds the cell")
    pr = sub.add_parser("run", help="the stage commands on a device, compared with the prepared CPU run")
    pr.add_argument("folder", type=Path)
    pr.add_argument("--device", default="cuda")
    args = p.parse_args(argv)
    if args.command == "prepare":
        print(f"gpu_stages: prepared {prepare(args.dest, args.results)}")
        return 0
    print(json.dumps({"workflow_cell": workflow_cell(args.folder, args.device),
                      "vggt_cli": vggt_cli(args.folder, args.device)}, indent=1))
    return 0


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    raise SystemExit(run_command(main))
