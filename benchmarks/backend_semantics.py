"""Which of gsplat's semantics moves a trained model? Each one emulated on the CPU kernel, many seeds.

gsplat and this project's CPU backends differ by design in three ways (splat_train/render/_gsplat_backend.py):
gsplat culls a Gaussian of opacity below 1/255 in its projection (not counted as seen by the
densification statistics), clamps each Gaussian's alpha at 0.999 instead of 3DGS's 0.99, and draws
dropout masks on the device. This runs the sparse-view grid's training command on one of its cells
with the CPU kernel and one difference at a time switched to gsplat's:

    cpu           the CPU kernel as it is (the grid's own records, when they exist, are reused)
    visibility    densification visibility as gsplat counts it (training-render opacity >= 1/255)
    clamp999      the C++ kernel built with alpha clamped at 0.999 (a copy of the packages in a
                  temporary folder, the one constant changed; its own kernel cache key)
    clamp999+op   clamp999 with the opacities clamped at 0.99 before every render, what the gsplat
                  adapter does (``splat_train.render._gsplat_backend.OPACITY_MAX``)

    python -m benchmarks.backend_semantics --cell W/llff__fern_n3 --variants visibility clamp999 \
        --seeds $(seq 0 14) --recipe sparse --out backend_semantics.json

Each run is ``python -m splat_train`` with the grid's arguments (3,000 iterations, held-out curve
every 300) in a process of its own; the JSON (rewritten after every run) holds each run's final
held-out PSNR and, per variant, the mean, the standard deviation and the difference to ``cpu``
paired by seed (95 % t). A run of about 80 s on 2 cores at the fern cell's 248x186.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("cpu", "visibility", "clamp999", "clamp999+op")
PACKAGES = ("splat_train", "camio", "runtime", "imgmetrics", "evaluation", "bridge", "vggt_init")
KERNEL_CONSTANT = ("static constexpr T alpha_max = T(0.99);", "static constexpr T alpha_max = T(0.999);")

# The runner each variant's process starts with: the patches, then the trainer's own command line.
RUNNER = r'''
import os, sys
variant = os.environ["BACKEND_SEMANTICS_VARIANT"]
if variant == "visibility":
    import splat_train.training.trainer as T
    _render = T.render_params
    def render_params(params, sh_degree, cam_from_world, K, width, height, background, backend="auto",
                      opacity_fn=None, **kwargs):
        seen = {}
        def capture(op):
            out = opacity_fn(op) if opacity_fn is not None else op
            seen["op"] = out.detach()
            return out
        out = _render(params, sh_degree, cam_from_world, K, width, height, background, backend,
                      opacity_fn=capture, **kwargs)
        out["visible"] = out["visible"] & (seen["op"] >= 1.0 / 255.0)
        if out["radii"] is not None:
            out["radii"] = out["radii"] * out["visible"].to(out["radii"].dtype)
        return out
    T.render_params = render_params
elif variant == "clamp999+op":
    import splat_train.export as E
    from splat_train.render._gsplat_backend import clamp_opacities
    _rasterize = E.rasterize
    E.rasterize = lambda means, quats, scales, opacities, *a, **k: _rasterize(
        means, quats, scales, clamp_opacities(opacities), *a, **k)
from runtime.memory import retain_freed_memory
from splat_train.__main__ import _cli
retain_freed_memory()
sys.exit(_cli())
'''


def patched_tree(dest: Path) -> Path:
    """A copy of the project's packages in ``dest`` with the C++ kernel's alpha clamp at 0.999."""
    for pkg in PACKAGES:
        if (ROOT / pkg).is_dir():
            shutil.copytree(ROOT / pkg, dest / pkg, ignore=shutil.ignore_patterns("__pycache__", "node_modules"))
    src = dest / "splat_train" / "render" / "cpu" / "raster.cpp"
    text = src.read_text()
    if text.count(KERNEL_CONSTANT[0]) != 1:
        raise RuntimeError(f"{src}: the alpha clamp constant is not where this experiment expects it")
    src.write_text(text.replace(*KERNEL_CONSTANT))
    return dest


def _final_psnr(train_json: Path) -> float:
    """The last held-out PSNR of a run's train.json."""
    return json.loads(train_json.read_text())["test_curve"]["last_test_psnr"]


def run(cell: Path, variants: list[str], seeds: list[int], recipe: str, iterations: int, work: Path,
        out: Path, records: Path | None) -> dict:
    """Train every (variant, seed) not done yet in ``work``; the summary JSON into ``out``."""
    from benchmarks.backend_agree import cell_name, cell_paths, curve_end, split_cell_name
    from experiments.sparse_views.runs import run_name, train_args
    from runtime.atomic import write_json

    paths = cell_paths(cell)
    name = cell_name(cell)
    scene, n = split_cell_name(name)
    work.mkdir(parents=True, exist_ok=True)
    runner = work / "runner.py"
    runner.write_text(RUNNER)
    res = {"cell": name, "recipe": recipe, "iterations": iterations, "psnr": {v: {} for v in variants}}
    with tempfile.TemporaryDirectory(prefix="backend_semantics_") as tmp:
        tree = None
        for seed in seeds:
            for v in variants:
                rec = None if records is None else records / f"{run_name(scene, n, recipe, seed, iterations)}.json"
                if v == "cpu" and rec is not None and rec.is_file():
                    res["psnr"][v][seed] = curve_end(json.loads(rec.read_text()))[1]
                    continue
                run_dir = work / f"{v}_s{seed}"
                if not (run_dir / "train.json").is_file():
                    if v.startswith("clamp999") and tree is None:
                        tree = patched_tree(Path(tmp))
                    # the patched copy must come first on sys.path: it is the working folder too
                    pypath = str(tree if v.startswith("clamp999") else ROOT)
                    env = {**os.environ, "PYTHONPATH": pypath, "BACKEND_SEMANTICS_VARIANT": v}
                    t0 = time.perf_counter()
                    cmd = [sys.executable, str(runner),
                           *train_args(paths, run_dir, recipe, seed, iterations, max(1, iterations // 10),
                                       kernel_threads=1)]
                    with open(work / f"{v}_s{seed}.log", "w") as log:
                        rc = subprocess.run(cmd, cwd=pypath, env=env, stdout=log, stderr=subprocess.STDOUT).returncode
                    if rc != 0:
                        raise RuntimeError(f"{v} seed {seed} failed (exit {rc}); see {work / f'{v}_s{seed}.log'}")
                    print(f"{v} seed {seed}: {_final_psnr(run_dir / 'train.json'):.2f} dB, "
                          f"{time.perf_counter() - t0:.0f} s", flush=True)
                res["psnr"][v][seed] = _final_psnr(run_dir / "train.json")
            res["summary"] = _summary(res["psnr"])
            write_json(out, res)
    return res


def _summary(psnr: dict) -> dict:
    """Per variant: seeds, mean, sd, and the difference to ``cpu`` paired by seed (95 % t)."""
    from evaluation.study.stats import t_interval

    out = {}
    for v, by_seed in psnr.items():
        vals = list(by_seed.values())
        if not vals:
            continue
        row = {"seeds": len(vals), "mean": statistics.mean(vals), "sd": statistics.stdev(vals) if len(vals) > 1 else None}
        base = psnr.get("cpu", {})
        both = sorted(set(by_seed) & set(base))
        if v != "cpu" and both:
            mean, hw, k = t_interval([by_seed[s] - base[s] for s in both])
            row["minus_cpu"] = {"mean": mean, "hw95": None if hw != hw else hw, "seeds": k}
        out[v] = row
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cell", type=Path, required=True, help="a sparse-view grid cell folder (or one packed by "
                                                             "python -m benchmarks.backend_agree pack)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--seeds", nargs="+", type=int, default=list(range(15)), help="seeds (default 0 to 14)")
    p.add_argument("--recipe", default="sparse")
    p.add_argument("--iterations", type=int, default=3000)
    p.add_argument("--work", type=Path, default=None, help="run folders (default: a temporary folder)")
    p.add_argument("--records", type=Path, default=ROOT / "experiments" / "records" / "sparse_views" / "runs",
                   help="the grid's records, whose runs stand for 'cpu' (default %(default)s)")
    p.add_argument("--out", type=Path, required=True, help="summary JSON, rewritten after every run")
    args = p.parse_args(argv)
    import logging

    from runtime.outdir import prepare_out, run_stage
    from runtime.logs import setup_logging
    from splat_train.recipes import RECIPE_NAMES

    setup_logging()
    stage = "backend_semantics"

    def work() -> None:
        if args.recipe not in RECIPE_NAMES:
            raise ValueError(f"--recipe must be one of {list(RECIPE_NAMES)}, got {args.recipe!r}")
        inputs = {"--cell": args.cell, "--records": args.records, "--work": args.work}
        prepare_out(args.out, inputs, stage, folder=False)
        if args.work is not None:  # run folders of this command's own, resumed on a rerun
            prepare_out(args.work, {"--cell": args.cell, "--records": args.records}, stage)
        with tempfile.TemporaryDirectory() as tmp:
            res = run(args.cell, list(args.variants), list(dict.fromkeys(args.seeds)), args.recipe,
                      args.iterations, args.work or Path(tmp), args.out, args.records)
        for v, row in res["summary"].items():
            d = row.get("minus_cpu")
            print(f"{v:12s} {row['seeds']:2d} seeds: {row['mean']:.2f} dB (sd {row['sd'] or 0:.2f})"
                  + (f", minus cpu {d['mean']:+.2f} ± {d['hw95'] or 0:.2f}" if d else ""))

    return run_stage(logging.getLogger("benchmarks.backend_semantics"), work, errors=(ValueError, OSError, RuntimeError))


if __name__ == "__main__":
    raise SystemExit(main())
