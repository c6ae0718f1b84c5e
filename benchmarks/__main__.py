"""``python -m benchmarks``: rasterizer, VGGT and pipeline-cell benchmarks in one table and one JSON.

    python -m benchmarks                         # full (long: the VGGT part alone takes hours on 2 loaded cores)
    python -m benchmarks --quick                 # tiny sizes, a smoke run (about a minute)
    python -m benchmarks --only raster,cell      # a subset
    python -m benchmarks --compare benchmarks/out/benchmarks_OLD.json          # run, then ratios vs OLD
    python -m benchmarks --compare OLD.json NEW.json                          # ratios only, no run
    python -m benchmarks --gpu                   # the GPU check (CUDA only; see benchmarks/gpu_check.py)

Sections: ``raster`` runs benchmarks/bench_rasterizer.py (full mode, as a subprocess writing
JSON; quick mode calls its functions in-process at tiny sizes); ``vggt`` runs
benchmarks/bench_vggt.py at n = 3, 6, 12, fp32 and bf16 with the full-size RANDOM-weight model
(speed/memory only; quick mode: the tiny fixture architecture of tests/data/vggt/shared);
``cell`` runs benchmarks/bench_cell.py. A section that is missing or fails is reported as
such, never filled in. Results go to OUT/benchmarks_<time>.json with the timestamp, the git
commit, the machine (CPU count, torch version and threads, load average) and each section.

``--gpu`` runs the GPU check instead (benchmarks/gpu_check.py: VGGT fixtures on CUDA against the
float64 expectation, our torch rasterizer against gsplat on one scene, forward and gradients and
time, and the cell trained 10,000 iterations with gsplat with its peak GPU memory), writing
OUT/benchmarks_gpu_<time>.json and a Markdown table beside it (.md). Without CUDA it exits 2
with a message.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

log = logging.getLogger("benchmarks")
HERE = Path(__file__).resolve().parent
SECTIONS = ("raster", "vggt", "cell")
VGGT_FIXTURE_CONFIG = HERE.parent / "tests" / "data" / "vggt" / "shared" / "config.json"


def _git(*args: str) -> str | None:
    try:
        res = subprocess.run(["git", *args], capture_output=True, text=True, cwd=HERE, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout.strip() if res.returncode == 0 else None


def machine_info() -> dict:
    """Commit, CPU, torch version and threads, load average: what a comparison needs."""
    import torch

    status = _git("status", "--porcelain", "--untracked-files=no")
    return {"git_commit": _git("rev-parse", "HEAD"), "git_dirty": bool(status) if status is not None else None,
            "cpu_count": os.cpu_count(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "python": platform.python_version(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(), "loadavg_start": list(os.getloadavg())}


def _new_json(pattern: str, before: set[Path]) -> Path | None:
    out = HERE / "out"
    new = sorted(set(out.glob(pattern)) - before, key=lambda p: p.stat().st_mtime) if out.is_dir() else []
    return new[-1] if new else None


# ----------------------------------------------------------------------------- sections


def raster_section(quick: bool, threads: int) -> dict:
    """Fast CPU rasterizer vs the dense reference (see benchmarks/bench_rasterizer.py)."""
    if not quick:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "raster.json"
            res = subprocess.run([sys.executable, str(HERE / "bench_rasterizer.py"), "--threads", str(threads),
                                  "--out", str(path)], cwd=HERE.parent, capture_output=True, text=True)
            if res.returncode != 0 or not path.is_file():
                return {"error": f"bench_rasterizer.py exit {res.returncode}: {res.stderr[-800:]}"}
            return json.loads(path.read_text())
    import torch

    from benchmarks import bench_rasterizer as br
    from splat_train.render.cpu import raster as cpu_raster

    torch.set_num_threads(threads)
    ref_case, fast_case = (300, 32, 32), (2000, 64, 64)
    backends = ["cpu", "reference"] if cpu_raster.available() else ["torch", "reference"]
    gflops = br.matmul_gflops(threads, size=256, min_seconds=0.0, min_reps=3)  # smoke: a quick probe
    runs = []
    for backend, (n, w, h) in [(b, ref_case) for b in backends] + [("cpu", fast_case)] * ("cpu" in backends):
        br.use_threads(backend, threads)  # the trainer's layout, as bench_rasterizer.py times it
        t = br.time_iteration(backend, n, w, h, reps=1 if backend == "reference" else 2)
        pc = br.count_pairs(n, w, h) if "cpu" in backends else {"blended_pairs": None}
        rate = pc["blended_pairs"] / t["fwd_bwd_s"] if pc["blended_pairs"] is not None else None
        bound = gflops * 1e9 / br.FLOPS_PER_PAIR
        runs.append({"threads": threads, "backend": backend, "n": n, "width": w, "height": h, **t, **pc,
                     "it_per_s": 1 / t["fwd_bwd_s"], "blended_pairs_per_s": rate, "matmul_gflops": gflops,
                     "bound_pairs_per_s": bound, "fraction_of_bound": rate / bound if rate else None})
    by = {r["backend"]: r["fwd_bwd_s"] for r in runs if (r["n"], r["width"], r["height"]) == ref_case}
    out = {"quick": True, "flops_per_pair": br.FLOPS_PER_PAIR, "runs": runs, "speedup_vs_reference": {
        str(threads): {"case": list(ref_case), **{b: by["reference"] / by[b] for b in by if b != "reference"}}}}
    if not cpu_raster.available():
        out["note"] = f"CPU kernel unavailable: {cpu_raster.build_error()}"
    return out


def _vggt_small(frames: list[int], threads: int) -> dict:
    """Quick mode: the tiny fixture architecture, random weights, fp32 vs bf16 (speed only)."""
    import torch

    from vggt_init.model import VGGT, VGGTConfig

    torch.set_num_threads(threads)
    cfg = json.loads(VGGT_FIXTURE_CONFIG.read_text())
    h, w = cfg["input"]["height"], cfg["input"]["width"]
    rows = []
    for dtype in ("fp32", "bf16"):
        torch.manual_seed(0)
        model = VGGT(VGGTConfig.from_json(VGGT_FIXTURE_CONFIG)).eval().requires_grad_(False)
        if dtype == "bf16":
            model.cast_trunk_weights(torch.bfloat16)
        for n in frames:
            x = torch.rand(n, 3, h, w, generator=torch.Generator().manual_seed(n))
            best, comp = float("inf"), {}
            for _ in range(2):
                t = {}
                t0 = time.perf_counter()
                with torch.inference_mode():
                    model(x, timings=t)
                if time.perf_counter() - t0 < best:
                    best, comp = time.perf_counter() - t0, t
            rows.append({"frames": n, "dtype": dtype, "size": f"{w}x{h}", "threads": threads, "forward_s": best,
                         **{f"{k}_s": v for k, v in comp.items()}})
    return {"model": f"tiny fixture architecture ({VGGT_FIXTURE_CONFIG.relative_to(HERE.parent)})",
            "weights": "RANDOM (speed only)", "runs": rows}


def vggt_section(quick: bool, threads: int, frames: list[int]) -> dict:
    """VGGT fp32 vs bf16 at n in ``frames``: bench_vggt.py (full size) or the tiny fixture (quick)."""
    try:
        if quick:
            return _vggt_small(frames, threads)
        script = HERE / "bench_vggt.py"
        if not script.is_file():
            return {"error": f"{script} is missing"}
        before = set((HERE / "out").glob("bench_vggt_*.json"))
        res = subprocess.run([sys.executable, str(script), "--frames", *map(str, frames), "--dtypes", "fp32", "bf16",
                              "--threads", str(threads)], cwd=HERE.parent, capture_output=True, text=True)
        path = _new_json("bench_vggt_*.json", before)
        if res.returncode != 0 or path is None:
            return {"error": f"bench_vggt.py exit {res.returncode}, JSON {path}: {res.stderr[-800:]}"}
        return {"model": "VGGT-1B full size", **json.loads(path.read_text()), "json": str(path)}
    except Exception as exc:  # reported in the table, never replaced by numbers
        log.exception("vggt section failed")
        return {"error": f"{type(exc).__name__}: {exc}"}


def cell_section(quick: bool, threads: int | None, vggt: dict | None) -> dict:
    """One pipeline cell (benchmarks/bench_cell.py); reuses the n = 3 fp32 VGGT row when the
    vggt section ran at full size, else times that forward itself (full mode only)."""
    from benchmarks import bench_cell

    reuse = None
    if vggt and not quick and "runs" in vggt:
        reuse = next((r for r in vggt["runs"] if r.get("frames") == 3 and r.get("dtype") == "fp32"
                      and "forward_s" in r), None)
    with tempfile.TemporaryDirectory(prefix="bench_cell_") as tmp:
        if quick:
            result = bench_cell.run_cell(Path(tmp), "synthetic", 3, bench_cell.QUICK_ITERATIONS, quick=True,
                                         threads=threads, vggt=False, inprocess=True)
        else:
            result = bench_cell.run_cell(Path(tmp), "auto", 3, 2000, threads=threads, vggt=reuse is None)
    if reuse is not None:
        result["vggt_forward_random"] = {**reuse, "weights": "RANDOM (speed/memory only)", "from": "vggt section"}
        result["cell_total_vggt_estimate_s"] = (result["cell_total_s"] - result["stages_s"][f"init_{result['init_used']}"]
                                                + reuse["forward_s"])
    return result


# ----------------------------------------------------------------------------- table


def _fmt(x, spec: str = ".3g") -> str:
    return "n/a" if x is None else format(x, spec)


def format_table(res: dict) -> str:
    """All sections as Markdown-style text."""
    from benchmarks.bench_cell import format_cell

    m = res["machine"]
    lines = [f"# Benchmarks {res['timestamp']}  commit {(m['git_commit'] or '?')[:10]}{' (dirty)' if m['git_dirty'] else ''}"
             f"  {m['cpu_count']} CPUs, torch {m['torch']}, load {m['loadavg_start'][0]:.1f}"
             f"{'  QUICK (tiny sizes)' if res['quick'] else ''}", ""]
    sec = res["sections"]
    if "raster" in sec:
        r = sec["raster"]
        lines.append("## Rasterizer (forward + backward, SH degree 3)")
        if "error" in r:
            lines.append(f"missing: {r['error'][:300]}")
        else:
            lines += ["| threads | backend | N | size | fwd+bwd s | it/s | blended pairs/s | of bound |",
                      "|---:|---|---:|---|---:|---:|---:|---:|"]
            for x in r["runs"]:
                lines.append(f"| {x['threads']} | {x['backend']} | {x['n']} | {x['width']}x{x['height']} | "
                             f"{x['fwd_bwd_s']:.3f} | {x['it_per_s']:.2f} | {_fmt(x.get('blended_pairs_per_s'))} | "
                             f"{_fmt(x.get('fraction_of_bound'), '.1%')} |")
            for nt, s in r.get("speedup_vs_reference", {}).items():
                sp = ", ".join(f"{k} {v:.1f}x" for k, v in s.items() if k != "case")
                lines.append(f"speed-up vs dense reference (threads {nt}, N={s['case'][0]} "
                             f"{s['case'][1]}x{s['case'][2]}): {sp}")
        lines.append("")
    if "vggt" in sec:
        v = sec["vggt"]
        lines.append(f"## VGGT forward, RANDOM weights (speed/memory only): {v.get('model', '')}")
        if "error" in v:
            lines.append(f"missing: {v['error'][:300]}")
        else:
            lines += ["| frames | dtype | forward s | aggregator s | peak RSS GB | bf16/fp32 |", "|---:|---|---:|---:|---:|---:|"]
            fp32 = {r["frames"]: r.get("forward_s") for r in v["runs"] if r.get("dtype") == "fp32"}
            for r in v["runs"]:
                if "forward_s" not in r:
                    lines.append(f"| {r['frames']} | {r['dtype']} | failed | | | |")
                    continue
                ratio = r["forward_s"] / fp32[r["frames"]] if r["dtype"] == "bf16" and fp32.get(r["frames"]) else None
                lines.append(f"| {r['frames']} | {r['dtype']} | {r['forward_s']:.2f} | {_fmt(r.get('aggregator_s'), '.2f')} | "
                             f"{_fmt(r.get('peak_rss_gb'), '.2f')} | {_fmt(ratio, '.2f')} |")
            for n, per_key in (v.get("bf16_vs_fp32") or {}).items():
                worst = max(per_key.items(), key=lambda kv: kv[1]["rel_l2"], default=None)
                if worst:
                    lines.append(f"bf16 vs fp32 outputs, {n} frames: largest relative L2 {worst[1]['rel_l2']:.2e} "
                                 f"({worst[0]}; target < 1e-2)")
        lines.append("")
    if "cell" in sec:
        c = sec["cell"]
        lines.append("## Pipeline cell")
        lines.append(f"missing: {c['error'][:500]}" if "error" in c else format_cell(c))
        lines.append("")
    per = ", ".join(f"{k} {w:.0f} s wall / {res['section_cpu_s'][k]:.0f} s CPU"
                    for k, w in res.get("section_wall_s", {}).items())
    lines.append(f"load average at the end: {res['loadavg_end'][0]:.1f} (1 min); total {res['wall_s']:.0f} s ({per})")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- compare


def as_aggregate(res: dict) -> dict:
    """A result of this command as is; a JSON of bench_cell, bench_rasterizer or bench_vggt
    wrapped as a one-section result (so --compare also reads the single benchmarks' files)."""
    if "sections" in res:
        return res
    if "stages_s" in res:
        return {"timestamp": None, "machine": {"loadavg_start": res.get("loadavg_start")}, "sections": {"cell": res}}
    if "runs" in res and "flops_per_pair" in res:
        return {"timestamp": None, "machine": res.get("machine", {}), "sections": {"raster": res}}
    if "runs" in res and "vggt" in str(res.get("benchmark", "")):
        return {"timestamp": None, "machine": res.get("machine", {}), "sections": {"vggt": res}}
    raise ValueError("not a benchmark result: expected the JSON of python -m benchmarks, bench_cell, "
                     "bench_rasterizer or bench_vggt")


def flatten(res: dict) -> dict[str, float]:
    """Comparable numbers of a result JSON, keyed by a readable name (lower is better for
    seconds; it/s and pairs/s are higher-is-better)."""
    out: dict[str, float] = {}
    sec = as_aggregate(res).get("sections", {})
    for r in sec.get("raster", {}).get("runs", []):
        key = f"raster {r['backend']} t{r['threads']} N={r['n']} {r['width']}x{r['height']}"
        out[f"{key} fwd_bwd_s"] = r["fwd_bwd_s"]
        if r.get("blended_pairs_per_s"):
            out[f"{key} pairs_per_s"] = r["blended_pairs_per_s"]
    for r in sec.get("vggt", {}).get("runs", []):
        for k in ("forward_s", "peak_rss_gb"):
            if r.get(k) is not None:
                out[f"vggt n={r['frames']} {r['dtype']} {k}"] = r[k]
    c = sec.get("cell", {})
    for k, v in c.get("stages_s", {}).items():
        out[f"cell {k} s"] = v
    for k in ("it_per_s", "final_gaussians"):
        if k in c.get("train", {}):
            out[f"cell train {k}"] = c["train"][k]
    for k in ("cell_total_s", "cell_total_cpu_s", "cell_total_vggt_estimate_s"):
        if k in c:
            out[f"cell {k}"] = c[k]
    return {k: float(v) for k, v in out.items() if isinstance(v, (int, float))}


def _load(res: dict) -> str:
    load = (res.get("machine") or {}).get("loadavg_start") or (res.get("machine") or {}).get("loadavg_at_start")
    return f"{load[0]:.1f}" if load else "?"


def compare(old: dict, new: dict) -> str:
    """Table of new/old ratios for every number both results have."""
    a, b = flatten(old), flatten(new)
    old, new = as_aggregate(old), as_aggregate(new)
    lines = [f"Compare: old {old.get('timestamp')} {(old.get('machine', {}).get('git_commit') or '?')[:10]} "
             f"(load {_load(old)}) -> new {new.get('timestamp')} "
             f"{(new.get('machine', {}).get('git_commit') or '?')[:10]} "
             f"(load {_load(new)})",
             "| quantity | old | new | new/old |", "|---|---:|---:|---:|"]
    common = [k for k in b if k in a]
    for k in common:
        lines.append(f"| {k} | {a[k]:.4g} | {b[k]:.4g} | {b[k] / a[k] if a[k] else float('nan'):.3f} |")
    only = sorted(set(a) ^ set(b))
    if only:
        lines.append(f"({len(only)} quantities in only one of the two runs: {', '.join(only[:8])}{' ...' if len(only) > 8 else ''})")
    if not common:
        lines.append("(no quantity in common)")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main


def run(only: list[str], quick: bool, threads: int, cell_threads: int | None, frames: list[int]) -> dict:
    """Run the chosen sections; returns the JSON-ready result."""
    t0 = time.perf_counter()
    res = {"timestamp": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "quick": quick, "machine": machine_info(),
           "threads": threads, "sections": {}, "section_wall_s": {}, "section_cpu_s": {}}
    clock: dict[str, tuple[float, float]] = {}

    def tick(name: str) -> None:  # wall and CPU (this process and finished children) per section
        ru = [resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
        now = (time.perf_counter(), sum(r.ru_utime + r.ru_stime for r in ru))
        if name in clock:
            res["section_wall_s"][name] = now[0] - clock[name][0]
            res["section_cpu_s"][name] = now[1] - clock[name][1]
        else:
            clock[name] = now

    if "raster" in only:
        log.info("section raster ...")
        tick("raster")
        try:
            res["sections"]["raster"] = raster_section(quick, threads)
        except Exception as exc:
            log.exception("raster section failed")
            res["sections"]["raster"] = {"error": f"{type(exc).__name__}: {exc}"}
        tick("raster")
    if "vggt" in only:
        log.info("section vggt (frames %s) ...", frames)
        tick("vggt")
        res["sections"]["vggt"] = vggt_section(quick, threads, frames)
        tick("vggt")
    if "cell" in only:
        log.info("section cell ...")
        tick("cell")
        try:
            res["sections"]["cell"] = cell_section(quick, cell_threads, res["sections"].get("vggt"))
        except Exception as exc:
            log.exception("cell section failed")
            res["sections"]["cell"] = {"error": f"{type(exc).__name__}: {exc}"}
        tick("cell")
    res["loadavg_end"] = list(os.getloadavg())
    res["wall_s"] = time.perf_counter() - t0
    return res


def main(argv: list[str] | None = None) -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(prog="python -m benchmarks", description=plain(__doc__).split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny sizes (smoke run)")
    p.add_argument("--only", default=",".join(SECTIONS), help=f"comma list of {', '.join(SECTIONS)}")
    p.add_argument("--out", type=Path, default=HERE / "out", help="folder for the JSON (default benchmarks/out)")
    p.add_argument("--threads", type=int, default=2, help="torch threads of the raster and VGGT sections")
    p.add_argument("--cell-threads", type=int, default=None, help="training threads of the cell (default: trainer's)")
    p.add_argument("--vggt-frames", type=int, nargs="+", default=[3, 6, 12])
    p.add_argument("--compare", type=Path, nargs="+", metavar="JSON",
                   help="OLD.json: ratios of this run vs OLD; OLD.json NEW.json: ratios only, nothing is run")
    p.add_argument("--gpu", action="store_true",
                   help="the GPU check instead of the CPU sections (needs CUDA): VGGT fixtures on CUDA vs the "
                        "float64 expectation, our torch rasterizer vs gsplat (forward, gradients, time), the "
                        "cell trained with gsplat with its peak GPU memory; writes JSON and a Markdown table")
    p.add_argument("--gpu-iterations", type=int, default=None,
                   help="training iterations of the --gpu cell (default 10000, gpu_check.CELL_ITERATIONS)")
    p.add_argument("--cell-prepared", type=Path, metavar="DIR", default=None,
                   help="the --gpu cell from a folder of `python benchmarks/bench_cell.py --prepare-only DIR` "
                        "(made on another machine: the GPU runs training, render and metrics only)")
    p.add_argument("--stages", type=Path, metavar="DIR", default=None,
                   help="the --gpu parts workflow_cell and vggt_cli from a folder of "
                        "`python benchmarks/gpu_stages.py prepare DIR` (skipped without it)")
    p.add_argument("--gpu-agree-cell", type=Path, metavar="DIR", default=None,
                   help="the --gpu part backend_agree from a copy of a sparse-view grid cell "
                        "(scripts/gpu_bundle.sh makes .gpu_agree; benchmarks/backend_agree.py)")
    p.add_argument("--gpu-parts", default=None,
                   help="comma list of --gpu parts, run in this order (default: all, see benchmarks/gpu_check.py)")
    args = p.parse_args(argv)
    from runtime.atomic import write_json
    from runtime.logs import setup_logging

    setup_logging()
    if args.gpu:
        from benchmarks import gpu_check

        parts = tuple(x.strip() for x in args.gpu_parts.split(",") if x.strip()) if args.gpu_parts else gpu_check.PARTS
        unknown = set(parts) - set(gpu_check.PARTS)
        if unknown:
            p.error(f"--gpu-parts: unknown {sorted(unknown)}; choose from {', '.join(gpu_check.PARTS)}")
        return gpu_check.run_cli(args.out, args.gpu_iterations, machine_info, cell_prepared=args.cell_prepared,
                                 stages=args.stages, parts=parts, agree_cell=args.gpu_agree_cell)
    if args.compare and len(args.compare) > 2:
        p.error("--compare takes OLD.json or OLD.json NEW.json")
    if args.compare and len(args.compare) == 2:
        old, new = (json.loads(Path(f).read_text()) for f in args.compare)
        print(compare(old, new))
        return 0
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = set(only) - set(SECTIONS)
    if unknown:
        p.error(f"--only: unknown sections {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    res = run(only, args.quick, args.threads, args.cell_threads, args.vggt_frames)
    path = args.out / f"benchmarks_{time.strftime('%Y%m%d_%H%M%S')}{'_quick' if args.quick else ''}.json"
    write_json(path, res)
    print(format_table(res))
    if args.compare:
        print()
        print(compare(json.loads(args.compare[0].read_text()), res))
    log.info("saved %s", path)
    return 0


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    sys.exit(run_command(main))
