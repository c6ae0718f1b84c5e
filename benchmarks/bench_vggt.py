"""Speed / memory benchmark of our VGGT-1B implementation on this machine.

RANDOM WEIGHTS: the full-size architecture is filled with random numbers. The outputs are
meaningless; only wall time and peak memory are measured. Never report these as results.

Each (frames, dtype) configuration runs in its own subprocess so that its peak RSS
(ru_maxrss) is its own. Prints a table and saves JSON to benchmarks/out/ (git-ignored).

    python benchmarks/bench_vggt.py --frames 3 6 12 --dtypes fp32 bf16 --threads 2

Reference (fixtures README, official implementation, random init, idle 2-core machine):
3 frames at 518x518, fp32, camera + depth + point heads: 78.1 s forward, 6.91 GB peak RSS.
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

log = logging.getLogger("bench_vggt")
OUT = Path(__file__).parent / "out"
REFERENCE = {"frames": 3, "size": 518, "dtype": "fp32", "forward_s": 78.1, "aggregator_s": 64.8,
             "peak_rss_gb": 6.91, "heads": "camera,depth,point", "note": "official code, idle 2-core machine"}


OUTPUT_KEYS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")


def _child(frames: int, dtype: str, size: int, threads: int, heads: list[str], seed: int,
           save: Path | None = None, trim: bool = True) -> dict:
    """Build the random-weight model, run one forward, return timings (runs in a subprocess).

    Memory settings as in the vggt_init CLI: freed memory kept in the process
    (``runtime.memory``, off with RETAIN_FREED_MEMORY=0), free pages returned after the
    weights are built and cast (``trim``).
    """
    import vggt_init  # noqa: F401  (sets THP_MEM_ALLOC_ENABLE before torch's first allocation)
    from runtime.memory import release_free_memory, retain_freed_memory

    retained = retain_freed_memory()
    import torch
    from vggt_init.model.fastpath import fast_paths_enabled

    from vggt_init.model import VGGT, VGGTConfig

    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    with torch.device("meta"):
        model = VGGT(VGGTConfig(), heads=heads)
    model = model.to_empty(device="cpu")
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("gamma"):
                p.fill_(0.05)  # LayerScale
            elif p.dim() == 1 and ("norm" in name):
                p.fill_(1.0 if name.endswith("weight") else 0.0)
            elif p.dim() == 1:
                p.zero_()  # biases
            else:
                fan_in = max(1, p[0].numel()) if p.dim() > 1 else 1
                p.normal_(0.0, min(0.02, fan_in ** -0.5))
    model.eval().requires_grad_(False)
    if dtype == "bf16":
        model.cast_trunk_weights(torch.bfloat16)  # as vggt_init.run does
    if trim:
        release_free_memory()
    build_s = time.perf_counter() - t0
    rss_built = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    x = torch.rand(frames, 3, size, size, generator=torch.Generator().manual_seed(seed))
    comp: dict[str, float] = {}
    t0 = time.perf_counter()
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    with torch.inference_mode():
        out = model(x, trunk_dtype=torch.bfloat16 if dtype == "bf16" else None, frames_chunk_size=4, timings=comp)
    forward_s = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    sys_s = cpu1.ru_stime - cpu0.ru_stime  # kernel time: mostly zeroing freshly faulted pages
    minflt = cpu1.ru_minflt - cpu0.ru_minflt
    nonfinite = {k: int((~torch.isfinite(v)).sum()) for k, v in out.items() if isinstance(v, torch.Tensor)}
    if save is not None:  # same seed -> same random weights and input in every child
        import numpy as np

        np.savez(save, **{k: out[k].float().numpy() for k in OUTPUT_KEYS if k in out})
    return {"frames": frames, "dtype": dtype, "size": size, "threads": threads, "heads": ",".join(heads),
            "build_s": build_s, "forward_s": forward_s, "forward_cpu_s": cpu_s, "forward_sys_s": sys_s,
            "forward_minor_faults": minflt, **{f"{k}_s": v for k, v in comp.items()},
            "rss_after_build_gb": rss_built, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
            "nonfinite_outputs": nonfinite, "onednn_fast_paths": fast_paths_enabled(),
            "thp_alloc": os.environ.get("THP_MEM_ALLOC_ENABLE", ""), "retain_freed_memory": retained,
            "trim_after_build": trim}


def _compare_outputs(saved: dict[tuple[int, str], Path], frames: list[int]) -> dict:
    """{frames: {output: {rel_l2, max_abs, max_abs_fp32, nonfinite}}} for each n run in both dtypes.

    rel_l2 = ||bf16 - fp32||_2 / ||fp32||_2 over the entries finite in both runs (float64).
    """
    import numpy as np

    result: dict = {}
    for n in frames:
        a, b = saved.get((n, "fp32")), saved.get((n, "bf16"))
        if a is None or b is None or not a.is_file() or not b.is_file():
            continue
        fa, fb = np.load(a), np.load(b)
        per_key = {}
        for k in OUTPUT_KEYS:
            if k not in fa.files or k not in fb.files:
                continue
            x, y = fa[k].astype(np.float64), fb[k].astype(np.float64)
            ok = np.isfinite(x) & np.isfinite(y)
            d = y[ok] - x[ok]
            per_key[k] = {"rel_l2": float(np.linalg.norm(d) / max(np.linalg.norm(x[ok]), 1e-300)),
                          "max_abs": float(np.abs(d).max()) if d.size else 0.0,
                          "max_abs_fp32": float(np.abs(x[ok]).max()) if d.size else 0.0,
                          "nonfinite": int((~ok).sum())}
        result[n] = per_key
    return result


_REUSE_PROBE = """
import json, resource, sys
from runtime.memory import heap_stats, retain_freed_memory
applied = retain_freed_memory() if sys.argv[1] == "retain" else False
import torch
faults, arena = [], []
for _ in range(5):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.empty(16 * 2**20, dtype=torch.float32)  # 64 MB
    x.fill_(1.0)
    del x
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
    arena.append((heap_stats() or {}).get("arena"))
print(json.dumps({"retained": applied, "minor_faults": faults, "heap_arena_bytes": arena}))
"""


def reuse_probe() -> list[dict]:
    """Page faults of a 64 MB tensor allocated, filled and freed 5 times, with glibc's defaults and
    with freed memory kept (``runtime.memory``); huge-page allocation on, as in vggt_init.

    Fault counts are kernel counters: they also depend on reclaim, huge-page splits and other
    jobs, which is why they are measured here and not asserted in tests (tests/test_runtime_memory.py
    checks glibc's bookkeeping instead).
    """
    rows = []
    for mode in ("default", "retain"):
        env = {k: v for k, v in os.environ.items() if k not in ("RETAIN_FREED_MEMORY", "VGGT_INIT_RETAIN_MEMORY")}
        env["THP_MEM_ALLOC_ENABLE"] = "1"
        res = subprocess.run([sys.executable, "-c", _REUSE_PROBE, mode], capture_output=True, text=True, env=env)
        if res.returncode != 0:
            raise RuntimeError(res.stderr[-2000:])
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return rows


def _machine() -> dict:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        commit = None
    import torch

    return {"python": platform.python_version(), "torch": torch.__version__, "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(), "loadavg_at_start": os.getloadavg(),
            "git_commit": commit}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, nargs="+", default=[3, 6, 12])
    p.add_argument("--dtypes", nargs="+", choices=("fp32", "bf16"), default=["fp32", "bf16"])
    p.add_argument("--image-size", dest="size", type=int, default=518, help="network input width (as vggt_init's --image-size)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--heads", default="camera,depth,point", help="comma list; the reference ran all three")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-fast-paths", action="store_true",
                   help="ATen's addmm/SDPA instead of the oneDNN paths (VGGT_INIT_ONEDNN=0)")
    p.add_argument("--no-thp", action="store_true",
                   help="4 kB pages for torch's large allocations (THP_MEM_ALLOC_ENABLE=0)")
    p.add_argument("--no-retain", action="store_true",
                   help="let glibc return freed memory to the system (RETAIN_FREED_MEMORY=0)")
    p.add_argument("--no-trim", action="store_true", help="no malloc_trim after building the weights")
    p.add_argument("--no-compare", action="store_true",
                   help="skip the bf16-vs-fp32 output comparison (outputs are kept in a temp dir otherwise)")
    p.add_argument("--reuse-probe", action="store_true",
                   help="only the page-fault probe: a 64 MB buffer re-allocated with and without freed memory kept")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--save", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    heads = [h for h in args.heads.split(",") if h]
    if args.child:
        print(json.dumps(_child(args.frames[0], args.dtypes[0], args.size, args.threads, heads, args.seed, args.save,
                                trim=not args.no_trim)))
        return 0
    if args.reuse_probe:
        for r in reuse_probe():
            print(f"freed memory {'kept    ' if r['retained'] else 'returned'}: minor faults per round "
                  f"{r['minor_faults']}, heap arena MB {[a // 2**20 if a else a for a in r['heap_arena_bytes']]}")
        print(f"load average: {os.getloadavg()} on {os.cpu_count()} CPUs")
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    log.info("RANDOM-WEIGHT speed/memory benchmark (outputs are meaningless, not results)")
    rows = []
    tmp = tempfile.TemporaryDirectory(prefix="bench_vggt_")
    saved: dict[tuple[int, str], Path] = {}
    for n in args.frames:
        for dt in args.dtypes:
            log.info("running %d frames, %s, %dx%d, %d threads ...", n, dt, args.size, args.size, args.threads)
            cmd = [sys.executable, __file__, "--child", "--frames", str(n), "--dtypes", dt, "--image-size", str(args.size),
                   "--threads", str(args.threads), "--heads", args.heads, "--seed", str(args.seed)]
            if args.no_trim:
                cmd.append("--no-trim")
            if not args.no_compare:
                saved[n, dt] = Path(tmp.name) / f"out_{n}_{dt}.npz"
                cmd += ["--save", str(saved[n, dt])]
            env = dict(os.environ)
            if args.no_fast_paths:
                env["VGGT_INIT_ONEDNN"] = "0"
            if args.no_thp:
                env["THP_MEM_ALLOC_ENABLE"] = "0"
            if args.no_retain:
                env["RETAIN_FREED_MEMORY"] = "0"
            res = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if res.returncode != 0:
                log.error("configuration %d/%s failed:\n%s", n, dt, res.stderr[-2000:])
                rows.append({"frames": n, "dtype": dt, "error": res.stderr[-500:]})
                continue
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
    print("\nVGGT-1B architecture, RANDOM WEIGHTS (speed/memory only)")
    print(f"{'frames':>6} {'dtype':>5} {'forward s':>10} {'CPU s':>8} {'aggregator s':>12} {'heads s':>8} "
          f"{'peak RSS GB':>11}")
    for r in rows:
        if "error" in r:
            print(f"{r['frames']:>6} {r['dtype']:>5} {'failed':>10}")
            continue
        heads_s = sum(v for k, v in r.items() if k.endswith("_head_s"))
        print(f"{r['frames']:>6} {r['dtype']:>5} {r['forward_s']:>10.1f} {r['forward_cpu_s']:>8.1f} {r['aggregator_s']:>12.1f} "
              f"{heads_s:>8.1f} {r['peak_rss_gb']:>11.2f}")
    print(f"reference (official, fp32, 3 frames, idle machine): forward {REFERENCE['forward_s']} s "
          f"(about {2 * REFERENCE['forward_s']:.0f} CPU s on 2 threads), peak RSS {REFERENCE['peak_rss_gb']} GB")
    print(f"load average at the end: {os.getloadavg()} on {os.cpu_count()} CPUs (wall times grow with contention)")
    comparison = _compare_outputs(saved, args.frames)
    tmp.cleanup()
    if comparison:
        print("\nbf16 vs fp32 outputs (same random weights and input): relative L2 ||bf16 - fp32|| / ||fp32||; "
              "target < 1e-2")
        for n, per_key in comparison.items():
            print(f"  {n:>2} frames: " + ", ".join(f"{k} {v['rel_l2']:.2e}" for k, v in per_key.items()))
    for r in rows:
        if r.get("dtype") == "bf16" and "forward_s" in r:
            fp32 = next((x for x in rows if x.get("frames") == r["frames"] and x.get("dtype") == "fp32"
                         and "forward_s" in x), None)
            if fp32:
                print(f"  {r['frames']:>2} frames: bf16 / fp32 wall = {r['forward_s'] / fp32['forward_s']:.2f} "
                      f"(aggregator {r['aggregator_s'] / fp32['aggregator_s']:.2f})")
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"bench_vggt_{time.strftime('%Y%m%d_%H%M%S')}.json"
    path.write_text(json.dumps({"benchmark": "vggt_init random-weight speed/memory", "weights": "RANDOM",
                                "machine": _machine(), "reference": REFERENCE, "runs": rows,
                                "bf16_vs_fp32": comparison}, indent=2))
    log.info("saved %s", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
