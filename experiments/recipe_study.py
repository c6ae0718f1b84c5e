"""The training-recipe study: ``paper`` against ``sparse`` (and ``mcmc``) and ``sparse`` with each part off, over seeds.

Each cell (scene, n training views, initialiser) is prepared once through the stage CLIs
(docs/contracts.md): scene conversion or synthesis, split, initialiser, Bridge (which writes
the depth prior), alignment of the held-out cameras. Then every variant is trained for every
seed through ``python -m splat_train`` with held-out PSNR / SSIM / LPIPS-alex along the run;
on the synthetic scene the final model's floater measure (``python -m evaluation floaters``)
is taken too. Intervals are the study's (:func:`evaluation.study.stats.t_interval`: mean +- t x sd /
sqrt(k) over seeds); differences against the first variant are paired by seed.

    python experiments/recipe_study.py --scene fern --n 3 --init posed --iterations 10000 \\
        --variants paper sparse --seeds 0 1 2 --work /tmp/rs_fern3
    python experiments/recipe_study.py --scene synthetic --n 3 --init oracle --iterations 3000 \\
        --variants sparse no-dropout no-depth no-cap no-early-stop uniform-depth --seeds 0 1 2

A run whose train.json exists is not trained again (the study resumes). The summary goes to
``--out`` (default experiments/out/recipe_study_<cell>.json) and is printed as a table; real
scenes are read from this project's machine data (SCENES below) and the cell is skipped
cleanly without them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script too
from experiments._proc import run_stage as sh  # noqa: E402
from experiments.sparse_views.cells import bridge_and_align  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
# machine-data: this project's machines keep real scenes in ../shared/data/scenes, beside the
# repository; a clone has none, and the benchmark says so and skips the real cells.
SCENES = REPO.parent / "shared" / "data" / "scenes"
REAL = {"fern": ("llff__fern", ["--images-subdir", "images_8", "--undistort"]),
        "fountain": ("strecha__fountain-P11", [])}
# the initialisation study's simulated VGGT-like error (config/init_study_quick.yaml)
VGGT_LIKE = ["--rot-deg", "1.2", "--trans-frac", "0.1", "--depth-rel", "0.02", "--outlier-frac", "0.02",
             "--conf-noise", "0.3"]
VARIANTS: dict[str, dict] = {
    "paper": {"recipe": "paper"},
    "paper-seedcode": {"recipe": "paper-seedcode"},  # the records' paper runs: paper with the seed code's schedule
    "sparse": {"recipe": "sparse"},
    "no-dropout": {"recipe": "sparse", "dropout_rate": 0.0},
    "no-depth": {"recipe": "sparse", "depth_weight": 0.0},
    "uniform-depth": {"recipe": "sparse", "depth_use_confidence": False},
    "no-cap": {"recipe": "sparse", "gaussians_per_pixel": 0.0},
    "no-early-stop": {"recipe": "sparse", "densify_until": "ITERATIONS"},
    "no-reset": {"recipe": "sparse", "opacity_reset_every": 10**9},
    "sparse-reset": {"recipe": "sparse", "opacity_reset_every": "RESET_30"},
    "cap-0.03": {"recipe": "sparse", "gaussians_per_pixel": 0.03},
    "cap-0.3": {"recipe": "sparse", "gaussians_per_pixel": 0.3},
    "sparse-pose": {"recipe": "sparse", "pose_refine": True},
    "paper-pose": {"recipe": "paper", "pose_refine": True},
    "mcmc": {"recipe": "mcmc"},
}


def prepare(work: Path, scene: str, n: int, init: str, oracle_noise: str = "none") -> dict[str, Path]:
    """Prepare the cell in ``work`` (once): scene, split, views, initialiser, Bridge, alignment."""
    s, logf = work / "scene", work / "prepare.log"
    if not (s / "split.json").is_file():
        if scene == "synthetic":
            sh(["-m", "camio", "synth", "--out", str(s), "--views", "24", "--width", "256"], logf)
        else:
            src, extra = REAL[scene]
            sh(["-m", "camio", "convert", "--src", str(SCENES / src), *extra, "--out", str(s)], logf)
        sh(["-m", "camio", "split", "--scene", str(s), "--n", str(n), "--out", str(s / "split.json")], logf)
    train_txt, test_txt = work / "train.txt", work / "test.txt"
    if not train_txt.is_file():
        sh(["workflow/scripts/views.py", "names", "--split", str(s / "split.json"), "--n", str(n), "--out",
            str(train_txt)], logf)
        test = json.loads((s / "split.json").read_text())["test"]
        test_txt.write_text("\n".join(test) + "\n")
    init_dir = work / init
    if not (work / "bridge" / "bridge.json").is_file():
        if init == "posed":
            sh(["-m", "evaluation.initialisers.posed", "--scene", str(s), "--image-list", str(train_txt),
                "--out", str(init_dir)], logf)
        elif init == "colmap":
            sh(["-m", "evaluation.initialisers.colmap_baseline", "--images", str(s / "images"),
                "--image-list", str(train_txt), "--out", str(init_dir)], logf)
        elif init == "oracle":
            sh(["-m", "evaluation.initialisers.oracle", "--scene", str(s), "--image-list", str(train_txt), "--out",
                str(init_dir), *(VGGT_LIKE if oracle_noise == "vggt_like" else []), "--downsample", "2"], logf)
    return {"scene": s, "train": train_txt, "test": test_txt, **bridge_and_align(work, s, init_dir, n, logf)}


def train_one(cell: dict[str, Path], out: Path, variant: str, seed: int, iterations: int, eval_every: int,
              synthetic: bool, kernel_threads: int = 0) -> dict:
    """Train one (variant, seed) and read its train.json (and floaters.json on synthetic scenes)."""
    if not (out / "train.json").is_file():
        special = {"ITERATIONS": iterations, "RESET_30": max(1, round(0.3 * iterations))}
        cfg = {k: special.get(v, v) if isinstance(v, str) else v for k, v in VARIANTS[variant].items()}
        sh(["-m", "splat_train", "--seed-ply", str(cell["bridge"] / "seed.ply"), "--cameras", str(cell["bridge"]),
            "--images", str(cell["scene"] / "images"), "--image-list", str(cell["train"]),
            "--test-cameras", str(cell["align"]), "--test-images", str(cell["scene"] / "images"),
            "--test-image-list", str(cell["test"]), "--out", str(out), "--iterations", str(iterations),
            "--seed", str(seed), "--eval-every", str(eval_every), "--eval-lpips", "--checkpoint-every",
            str(iterations), "--kernel-threads", str(kernel_threads), "--config", json.dumps(cfg)],
           out.parent / f"{out.name}.log")
    if synthetic and not (out / "floaters.json").is_file():
        sh(["-m", "evaluation", "floaters", "--model", f"final={out / 'model.ply'}", "--align",
            str(cell["align"] / "align.json"), "--scene", str(cell["scene"]), "--out", str(out / "floaters.json")],
           out.parent / f"{out.name}.log")
    tj = json.loads((out / "train.json").read_text())
    c = tj["test_curve"]
    rec = {"variant": variant, "seed": seed, "final_psnr": c["last_test_psnr"], "final_ssim": c["last_test_ssim"],
           "final_lpips": c["last_test_lpips"], "best_psnr": c["best_test_psnr"],
           "best_iteration": c["best_iteration"], "num_gaussians": tj["num_gaussians"],
           "wall_time_s": tj["wall_time_s"], "train_psnr": tj["train_psnr"],
           "curve": {"iterations": c["iterations"], "test_psnr": c["test_psnr"]}}
    its = [i for i in c["iterations"] if i >= 2000]
    if its:  # the best held-out PSNR after iteration 2,000, to see whether the end holds it
        rec["best_psnr_after_2000"] = max(p for i, p in zip(c["iterations"], c["test_psnr"]) if i >= 2000)
    if synthetic:
        rec["floater_frac"] = json.loads((out / "floaters.json").read_text())["final"]["floater_frac"]
    return rec


MEASURES = ("final_psnr", "final_ssim", "final_lpips", "best_psnr", "num_gaussians", "wall_time_s", "floater_frac")


def summarise(runs: list[dict], variants: list[str]) -> dict:
    """Per variant: mean and 95 % half-width of each measure; per variant after the first: the
    paired (same seed) difference against the first variant."""
    from evaluation.study.stats import t_interval

    out: dict = {"variants": {}, "differences": {}}
    by = {v: {r["seed"]: r for r in runs if r["variant"] == v} for v in variants}
    for v in variants:
        rs = list(by[v].values())
        out["variants"][v] = {m: t_interval([r[m] for r in rs if r.get(m) is not None])
                              for m in MEASURES if any(r.get(m) is not None for r in rs)}
    base = variants[0]
    for v in variants[1:]:
        seeds = sorted(set(by[v]) & set(by[base]))
        out["differences"][f"{v} - {base}"] = {
            m: t_interval([by[v][s][m] - by[base][s][m] for s in seeds])
            for m in MEASURES if all(by[v][s].get(m) is not None and by[base][s].get(m) is not None for s in seeds)
            and seeds}
    return out


def _fmt(t) -> str:
    mean, hw, k = t
    if k == 0 or mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "n/a"
    digits = 0 if abs(mean) >= 1000 else (4 if abs(mean) < 1 else 2)
    return f"{mean:.{digits}f}" + ("" if k < 2 else f" ± {hw:.{digits}f}")


def table(summary: dict) -> str:
    cols = [m for m in MEASURES if any(m in s for s in summary["variants"].values())]
    lines = ["| variant | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for v, s in summary["variants"].items():
        lines.append(f"| {v} | " + " | ".join(_fmt(s[m]) if m in s else "" for m in cols) + " |")
    for v, s in summary["differences"].items():
        lines.append(f"| {v} | " + " | ".join(_fmt(s[m]) if m in s else "" for m in cols) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--scene", choices=["synthetic", *REAL], required=True)
    p.add_argument("--n", type=int, default=3)
    p.add_argument("--init", choices=["posed", "colmap", "oracle"], required=True)
    p.add_argument("--iterations", type=int, default=10000)
    p.add_argument("--eval-every", type=int, default=None, help="held-out evaluation period (default iterations/20)")
    p.add_argument("--variants", nargs="+", default=["paper", "sparse"], choices=list(VARIANTS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--work", type=Path, required=True, help="the cell's folder (prepared once, runs inside)")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--oracle-noise", choices=["none", "vggt_like"], default="none",
                   help="the oracle's error: none (exact ground truth) or the study's simulated VGGT-like point")
    p.add_argument("--kernel-threads", type=int, default=0,
                   help="C++ kernel threads per run (0: every core; 1 to run two studies side by side)")
    args = p.parse_args(argv)
    if args.scene in REAL and not (SCENES / REAL[args.scene][0]).is_dir():
        print(f"SKIP: {SCENES / REAL[args.scene][0]} is not here")
        return 0
    t0 = time.perf_counter()
    cell = prepare(args.work, args.scene, args.n, args.init, args.oracle_noise)
    eval_every = args.eval_every or max(1, args.iterations // 20)
    runs = []
    for seed in args.seeds:  # seed-major: an interrupted study has whole seeds of every variant
        for v in args.variants:
            t1 = time.perf_counter()
            runs.append(train_one(cell, args.work / "runs" / f"{v}_i{args.iterations}_s{seed}", v, seed, args.iterations, eval_every,
                                  args.scene == "synthetic", args.kernel_threads))
            r = runs[-1]
            print(f"[{time.perf_counter() - t0:7.0f} s] {v} seed {seed}: final {r['final_psnr']:.2f} dB "
                  f"(best {r['best_psnr']:.2f} at {r['best_iteration']}), {r['num_gaussians']} Gaussians, "
                  f"{r['wall_time_s']:.0f} s training ({time.perf_counter() - t1:.0f} s)", flush=True)
    summary = summarise(runs, args.variants)
    name = f"{args.scene}_n{args.n}_{args.init}_{args.iterations}"
    out = args.out or HERE / "out" / f"recipe_study_{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = {"cell": name, "iterations": args.iterations, "seeds": args.seeds, "variants": args.variants,
           "variant_configs": {v: VARIANTS[v] for v in args.variants}, "runs": runs, "summary": summary,
           "load_avg": os.getloadavg(), "wall_s": time.perf_counter() - t0}
    out.write_text(json.dumps(rec, indent=1))
    print(table(summary))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    sys.exit(run_command(main))
