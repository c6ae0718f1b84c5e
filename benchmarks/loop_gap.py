"""Does ``paper`` train as gsplat's own loop does? Both loops on one prepared cell over many
seeds, several runs at a time on one GPU.

    python -m benchmarks.loop_gap --cell .gpu_cell [--seeds 0 1 ...] [--jobs 8] [--iterations 10000] [--out X.json]

Per seed, one run of each loop, each in a process of its own (:func:`commands`):

* ``ours``: ``python -m splat_train`` with the ``paper`` recipe on the gsplat backend, the
  training command of ``bench_cell.py``'s cell; its held-out PSNR is the trainer's final
  evaluation (:mod:`splat_train.training.heldout`);
* ``native``: ``benchmarks/gsplat_native.py``, gsplat's ``DefaultStrategy`` loop with the same
  schedule, rates and loss; its held-out PSNR is scored once at the end, the same way.

At the paper's cell size (497x372) a training step is fixed cost (Python, kernel launches),
so ``jobs`` runs share one GPU with little loss each. The runs are started seed by seed, the
two loops of a seed together, so a comparison cut short by its deadline stays balanced. The
loops draw their random numbers differently: a seed pairs nothing across them, and the result
is each loop's mean and standard deviation over its seeds and the difference of the means with
Welch's 95 % interval (:func:`evaluation.study.stats.welch_interval`). The GPU check runs this
as its part ``loop_gap`` (``LOOP_GAP_SEEDS``, ``LOOP_GAP_JOBS``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
LOOPS = ("ours", "native")
ITERATIONS = 10_000  # the cell where the two loops differed: the paper's length
SEEDS, JOBS = tuple(range(8)), 8
RUN_S_GUESS = 300.0  # a run's seconds before one has finished (then: the longest seen)


def commands(cell: Path, seed: int, iterations: int, out: Path, device: str = "cuda",
             rasterizer: str = "gsplat") -> dict[str, tuple[list[str], Path]]:
    """Per loop, the command line of one run on the prepared ``cell`` and the JSON it leaves
    in ``out`` (``train.json`` of the trainer; the native loop's result)."""
    from benchmarks.bench_cell import PREPARED_FILE, cell_train_args

    cell = Path(cell)
    state = json.loads((cell / PREPARED_FILE).read_text())
    ours_out = out / f"ours_s{seed}"
    ours = [sys.executable, "-m", "splat_train",
            *cell_train_args(cell, state, ours_out, iterations, seed, threads=1, device=device, rasterizer=rasterizer,
                             recipe="paper"), "--eval-every", str(iterations)]
    native_json = out / f"native_s{seed}.json"
    native = [sys.executable, str(ROOT / "benchmarks" / "gsplat_native.py"), "--cell", str(cell),
              "--iterations", str(iterations), "--seed", str(seed), "--out", str(native_json)]
    return {"ours": (ours, ours_out / "train.json"), "native": (native, native_json)}


def read_result(loop: str, path: Path) -> dict:
    """``psnr`` (held-out, final), ``gaussians`` and ``train_s`` of a finished run's JSON."""
    d = json.loads(Path(path).read_text())
    if loop == "ours":
        return {"psnr": d.get("test_psnr"), "gaussians": d.get("num_gaussians"), "train_s": d.get("wall_time_s")}
    return {"psnr": d.get("test_psnr"), "gaussians": d.get("final_gaussians"), "train_s": d.get("wall_s")}


def summarise(runs: list[dict]) -> dict:
    """Per loop: seeds, mean and sd of the final held-out PSNR, mean Gaussians and training
    seconds; ``ours_minus_native``: the difference of the mean PSNRs with Welch's 95 %
    half-width (None below two seeds a side)."""
    from evaluation.study.stats import welch_interval

    out: dict = {}
    vals: dict[str, list[float]] = {}
    for loop in LOOPS:
        rs = [r for r in runs if r["loop"] == loop and r.get("psnr") is not None]
        vals[loop] = [r["psnr"] for r in rs]
        if rs:
            out[loop] = {"seeds": sorted(r["seed"] for r in rs), "psnr": statistics.mean(vals[loop]),
                         "psnr_sd": statistics.stdev(vals[loop]) if len(rs) > 1 else None,
                         "gaussians": statistics.mean(r["gaussians"] for r in rs),
                         "train_s": statistics.mean(r["train_s"] for r in rs)}
    if all(len(vals[lp]) >= 2 for lp in LOOPS):
        diff, hw, df = welch_interval(vals["ours"], vals["native"])
        out["ours_minus_native"] = {"psnr": diff, "hw95": None if hw != hw else hw,
                                    "df": df if math.isfinite(df) else None}
    return out


def check_cell(cell: Path) -> None:
    """ValueError naming the problem when ``cell`` is not a folder of ``bench_cell.py --prepare-only``."""
    from benchmarks.bench_cell import PREPARED_FILE

    if not (Path(cell) / PREPARED_FILE).is_file():
        raise ValueError(f"{cell} is not a prepared cell (make one with: "
                         "python benchmarks/bench_cell.py --prepare-only DIR)")


def loop_gap(cell: Path, seeds: list[int], iterations: int = ITERATIONS, jobs: int = JOBS, device: str = "cuda",
             rasterizer: str = "gsplat", deadline: float | None = None, loops: tuple[str, ...] = LOOPS,
             on_result: Callable[[dict], None] | None = None) -> dict:
    """Run ``loops`` x ``seeds`` on ``cell``, ``jobs`` processes at a time, and summarise.

    Args:
        cell: a folder of ``bench_cell.py --prepare-only``.
        deadline: a ``time.time()`` value; no run starts when the longest run seen so far
            (:data:`RUN_S_GUESS` before the first ends) would end past it.
        on_result: called with the live result after each finished run (write it out at once).

    Returns:
        dict: ``cell``, ``iterations``, ``jobs``, ``device``; ``runs`` (``loop``, ``seed``,
        ``start_s`` after the first start, ``wall_s`` of the process, and ``psnr``,
        ``gaussians``, ``train_s``, or ``error``: the exit status and the end of its log);
        ``summary`` (:func:`summarise`); ``stopped_at_deadline``; ``wall_s``.
    """
    cell = Path(cell)
    check_cell(cell)
    res = {"cell": str(cell), "iterations": iterations, "jobs": jobs, "device": device, "rasterizer": rasterizer,
           "runs": [], "summary": {}, "stopped_at_deadline": False}
    queue = [(loop, seed) for seed in seeds for loop in loops]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    t_start, longest = time.perf_counter(), RUN_S_GUESS
    running: dict = {}
    with tempfile.TemporaryDirectory(prefix="loop_gap_") as tmp:
        out = Path(tmp)
        plans = {seed: commands(cell, seed, iterations, out, device, rasterizer) for seed in seeds}
        while queue or running:
            while queue and len(running) < jobs:
                if deadline is not None and time.time() + longest > deadline:
                    res["stopped_at_deadline"], queue = True, []
                    break
                loop, seed = queue.pop(0)
                argv, result = plans[seed][loop]
                log = out / f"{loop}_s{seed}.log"
                with open(log, "w") as fh:
                    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
                running[proc] = (loop, seed, time.perf_counter(), result, log)
            time.sleep(0.2)
            for proc in [p for p in running if p.poll() is not None]:
                loop, seed, t0, result, log = running.pop(proc)
                entry = {"loop": loop, "seed": seed, "start_s": t0 - t_start, "wall_s": time.perf_counter() - t0}
                longest = max(longest if res["runs"] else 0.0, entry["wall_s"])
                if proc.returncode == 0 and result.is_file():
                    entry.update(read_result(loop, result))
                else:
                    entry["error"] = f"exit {proc.returncode}: " + log.read_text(errors="replace")[-1500:]
                res["runs"].append(entry)
                res["summary"] = summarise(res["runs"])
                res["wall_s"] = time.perf_counter() - t_start
                print(f"loop_gap: {loop} seed {seed}: " + (f"{entry['psnr']:.2f} dB, {entry['gaussians']} Gaussians, "
                      f"{entry['wall_s']:.0f} s" if "psnr" in entry else "FAILED"), flush=True)
                if on_result is not None:
                    on_result(res)
    res["wall_s"] = time.perf_counter() - t_start
    return res


def main(argv: list[str] | None = None) -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(prog="python -m benchmarks.loop_gap", description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--cell", type=Path, required=True, help="folder of bench_cell.py --prepare-only")
    p.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS), help="seeds, each run by both loops (default: 0 to 7)")
    p.add_argument("--jobs", type=int, default=JOBS, help="runs at a time (default %(default)s)")
    p.add_argument("--iterations", type=int, default=ITERATIONS)
    p.add_argument("--device", default="cuda", help="the trainer's device (default %(default)s)")
    p.add_argument("--rasterizer", default="gsplat", help="the trainer's backend (default %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = p.parse_args(argv)
    try:
        seeds = list(dict.fromkeys(args.seeds))
        if args.jobs < 1 or args.iterations < 1 or min(seeds) < 0:
            raise ValueError("--jobs and --iterations must be positive and --seeds at least 0")
        check_cell(args.cell)
        if args.out is not None:  # a file of its own: never an input, never a file another command wrote
            from runtime.outdir import prepare_out

            prepare_out(args.out, {"--cell": args.cell}, "benchmarks.loop_gap", folder=False)
    except ValueError as exc:
        print(f"loop_gap: {exc}", file=sys.stderr)
        return 2
    from runtime.atomic import write_json

    save = (lambda r: write_json(args.out, r)) if args.out else None
    res = loop_gap(args.cell, seeds, args.iterations, args.jobs, args.device, args.rasterizer, on_result=save)
    if save:
        save(res)
    print(json.dumps(res["summary"], indent=1))
    return 0


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    raise SystemExit(run_command(main))
