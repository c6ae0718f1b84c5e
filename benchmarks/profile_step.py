"""One training step on a GPU, part by part: where the time of a ``splat_train`` iteration goes.

On a prepared cell (``bench_cell.py --prepare-only``: the Bridge's seed and cameras, the
training images), for one recipe: a trainer (:class:`splat_train.training.trainer.Trainer`, the run's
config at the cell's 10,000 iterations, no held-out views) is run ``warm`` iterations, then

* ``ms_per_step``: the plain loop (``Trainer.step`` and the strategy step, as ``Trainer.run``
  takes them), ``steps`` iterations between two device synchronisations, with the loss as a
  CUDA graph and op by op (``graphs_on`` / ``graphs_off``);
* ``phases``: the same iterations with every call of the step timed on the host
  (``perf_counter``) and on the device (CUDA events recorded around it: the span the device's
  queue takes from the call's first to its last work, idle gaps included), per iteration, for
  the phases of :data:`benchmarks.profile_iteration.PHASES`;
* ``rasterizer_only_ms``: the gsplat forward and backward alone on the same model and views
  (a loss of ``rgb.sum()``): the floor that no change of the loop around it moves;
* ``torch_profiler``: ``torch.profiler`` over ``profile_steps`` iterations: kernel launches,
  device synchronisations and host-device copies per iteration, the device's busy time per
  iteration (the sum of the kernels' times), and the 15 operators with the most host and
  device time.

A host time per iteration above the device's busy time means the step is bound by the host
(Python and launch overhead), which is what this profile was made to show.

``--late`` profiles the state late in the run instead (:func:`late_profile`): each recipe after
``warm`` (:data:`WARM_LATE`) of the 10,000 iterations, past the ``sparse`` recipe's growth, timed
with the densification statistics skipped (what the trainer does once nothing reads them) and
computed, in turns; then the phases, gsplat alone, gsplat's tile intersections in one view and
the ``torch.profiler`` summary.

    python benchmarks/profile_step.py --cell .gpu_cell --recipe sparse [--warm 1000 --steps 200]
    python benchmarks/profile_step.py --cell .gpu_cell --late

CUDA only (the CPU profile is ``benchmarks/profile_iteration.py``).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.profile_iteration import PHASES, step_calls  # noqa: E402

CELL_ITERATIONS = 10_000  # the paper's training length, which sets the recipes' schedules
WARM = 1000  # iterations before the step is timed (the growing model)
WARM_LATE = 6000  # the same for the late-run profile: past sparse's growth (to 5,000 of 10,000)


def cell_trainer(cell: Path, recipe: str, device: str = "cuda", graphs: bool | None = None, **overrides):
    """A :class:`splat_train.training.trainer.Trainer` on the prepared ``cell`` (training views only),
    ``recipe`` at :data:`CELL_ITERATIONS` (``overrides``: other config values), writing nowhere
    it keeps (a temporary folder)."""
    from benchmarks.gsplat_native import load_cell
    from splat_train.config import TrainConfig
    from splat_train.losses import TrainingLoss
    from splat_train.training.trainer import Trainer, seed_depth_prior

    train, _test, _cloud = load_cell(cell)
    cfg = TrainConfig(recipe=recipe, iterations=CELL_ITERATIONS, device=device, **overrides)
    out = tempfile.mkdtemp(prefix="profile_step_")
    seed = cell / "bridge" / "seed.ply"
    # the depth prior beside the seed, as the training command finds it (sparse's depth term)
    tr = Trainer(cfg, seed, train, out, [], ckpt_dir=out, depth_prior=seed_depth_prior(seed, cfg))
    tr.photometric = TrainingLoss(cfg.lambda_dssim, tr.dev, graphs=graphs)
    return tr


def iterate(tr, n: int) -> None:
    """``n`` iterations as :meth:`Trainer.run` takes them (step, strategy), without logging."""
    for _ in range(n):
        tr.step()
        tr.strategy.step(tr.params, tr.optimizer, tr.state, tr.iteration, tr.extent, tr.gen)


def ms_per_step(tr, n: int) -> float:
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    iterate(tr, n)
    torch.cuda.synchronize()
    return 1e3 * (time.perf_counter() - t0) / n


@contextlib.contextmanager
def _timed_calls(tr, spans: list, host: dict[str, float]):
    """While inside, each timed call appends (phase, start event, end event) to ``spans`` and
    adds its host seconds to ``host``."""

    def timed(key: str, fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            e0 = torch.cuda.Event(enable_timing=True)
            e0.record()
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                host[key] += time.perf_counter() - t0
                e1 = torch.cuda.Event(enable_timing=True)
                e1.record()
                spans.append((key, e0, e1))
        return wrapper

    with contextlib.ExitStack() as stack:
        for obj, name, key in step_calls(tr):
            stack.enter_context(mock.patch.object(obj, name, timed(key, getattr(obj, name))))
        yield


def phase_times(tr, n: int) -> dict:
    """Host and device milliseconds per iteration of each phase over ``n`` iterations."""
    spans, host = [], dict.fromkeys(PHASES, 0.0)
    steps = []
    for _ in range(n):
        e0 = torch.cuda.Event(enable_timing=True)
        e0.record()
        t0 = time.perf_counter()
        with _timed_calls(tr, spans, host):
            tr.step()
        t1 = time.perf_counter()
        tr.strategy.step(tr.params, tr.optimizer, tr.state, tr.iteration, tr.extent, tr.gen)
        host["strategy"] += time.perf_counter() - t1
        e1 = torch.cuda.Event(enable_timing=True)
        e1.record()
        steps.append((e0, e1, t1 - t0))
    torch.cuda.synchronize()
    device = dict.fromkeys(PHASES, 0.0)
    for key, a, b in spans:
        device[key] += a.elapsed_time(b) / 1e3
    step_device = sum(a.elapsed_time(b) for a, b, _ in steps) / 1e3
    step_host = sum(h for _, _, h in steps)
    inner = [k for k in PHASES if k not in ("other", "strategy")]
    host["other"] = step_host - sum(host[k] for k in inner)
    device["other"] = step_device - sum(device[k] for k in inner)
    return {"host_ms": {k: 1e3 * v / n for k, v in host.items()},
            "device_span_ms": {k: 1e3 * v / n for k, v in device.items()},
            "iteration_device_span_ms": 1e3 * step_device / n, "note": (
                "device spans include the device's idle time waiting for the host inside the call; "
                "'strategy' device time is inside the iteration span")}


def rasterizer_only_ms(tr, n: int = 100) -> float:
    """Milliseconds per gsplat forward + backward of the current model (loss ``rgb.sum()``),
    cycling over the training views."""
    from splat_train.export import render_params

    def once(i: int) -> None:
        cam = tr.train_views[i % len(tr.train_views)].camera
        cw, K = tr.cams[i % len(tr.cams)]
        deg = tr.sched.sh_degree_at(max(tr.iteration, 1), tr.cfg.sh_degree)
        out = render_params(tr.params, deg, cw, K, cam.width, cam.height, tr.bg, tr.backend, depth=False)
        out["rgb"].sum().backward()

    for i in range(5):
        once(i)
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for i in range(n):
        once(i)
    torch.cuda.synchronize()
    tr.optimizer.zero_grad(set_to_none=True)
    return 1e3 * (time.perf_counter() - t0) / n


def torch_profile(tr, n: int) -> dict:
    """Launches, synchronisations and copies per iteration, device busy ms per iteration, and
    the top operators, from ``torch.profiler`` over ``n`` iterations."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        iterate(tr, n)
        torch.cuda.synchronize()
    events = prof.key_averages()
    dev_attr = "self_device_time_total" if hasattr(events[0], "self_device_time_total") else "self_cuda_time_total"
    count = lambda *names: sum(e.count for e in events if e.key in names) / n  # noqa: E731
    device_us = sum(getattr(e, dev_attr) for e in events if e.device_type == torch.autograd.DeviceType.CUDA)

    def top(attr: str) -> list[dict]:
        rows = sorted(events, key=lambda e: getattr(e, attr), reverse=True)[:15]
        return [{"op": e.key, "count_per_it": e.count / n, "self_host_ms_per_it": e.self_cpu_time_total / 1e3 / n,
                 "self_device_ms_per_it": getattr(e, dev_attr) / 1e3 / n} for e in rows]

    return {"iterations": n,
            "kernel_launches_per_it": count("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC",
                                            "cuLaunchKernelEx"),
            "graph_launches_per_it": count("cudaGraphLaunch"),
            "syncs_per_it": count("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize"),
            "memcpy_per_it": count("cudaMemcpyAsync", "cudaMemcpy"),
            "device_busy_ms_per_it": device_us / 1e3 / n,
            "top_host": top("self_cpu_time_total"), "top_device": top(dev_attr)}


def profile_recipe(cell: Path, recipe: str, warm: int = WARM, steps: int = 200, profile_steps: int = 30) -> dict:
    """The profile of ``recipe`` on ``cell`` (module docstring)."""
    return profile(cell, (recipe,), warm=warm, steps=steps, profile_steps=profile_steps)[recipe]


def _time_recipe(cell: Path, recipe: str, warm: int, steps: int):
    """The timed part of a recipe's profile (a fresh trainer per variant, so both variants time
    the same iterations ``warm + 1 .. warm + steps``) and the last trainer."""
    out: dict = {"recipe": recipe, "warm_iterations": warm, "steps": steps}
    for graphs in (False, True):
        tr = cell_trainer(cell, recipe, graphs=graphs)
        iterate(tr, warm)
        ms = ms_per_step(tr, steps)
        key = "graphs_on" if graphs else "graphs_off"
        out[key] = {"ms_per_step": ms, "loss_graphed": tr.photometric.use_graphs,
                    "gaussians": tr.num_gaussians}
        print(f"profile {recipe} {key}: {ms:.2f} ms per iteration at {tr.num_gaussians} Gaussians", flush=True)
    out["parts"] = [p.name for p in tr.parts]
    out["phases"] = phase_times(tr, steps)
    out["rasterizer_only_ms"] = rasterizer_only_ms(tr)
    out["ms_per_step"] = out["graphs_on"]["ms_per_step"]
    return out, tr


#: the recipes and the sparse recipe without each of its per-iteration parts
AB_VARIANTS = {"paper": {"recipe": "paper"}, "sparse": {"recipe": "sparse"},
               "sparse_no_dropout": {"recipe": "sparse", "dropout_rate": 0.0},
               "sparse_no_opacity_reg": {"recipe": "sparse", "opacity_reg": 0.0},
               "sparse_no_depth": {"recipe": "sparse", "depth_weight": 0.0}}


def recipe_ab(cell: Path, variants: dict[str, dict] | None = None, rounds: int = 3, warm: int = 300,
              steps: int = 200) -> dict:
    """Milliseconds per iteration of each variant (config overrides, :data:`AB_VARIANTS`),
    measured in turns in one process (``rounds`` blocks of ``steps`` iterations each, after
    ``warm``), so that a difference between recipes is not one between processes or moments.
    Run it before any ``torch.profiler`` session in the process: the profiler's hooks stay
    and slow every later launch."""
    import os

    variants = variants or AB_VARIANTS
    trainers = {}
    for name, v in variants.items():
        v = dict(v)
        trainers[name] = cell_trainer(cell, v.pop("recipe"), **v)
        iterate(trainers[name], warm)
    ms = {name: [] for name in variants}
    for _ in range(rounds):
        for name, tr in trainers.items():
            ms[name].append(ms_per_step(tr, steps))
    out = {name: {"ms_per_step": vals, "median_ms": sorted(vals)[len(vals) // 2],
                  "gaussians": trainers[name].num_gaussians, "config": variants[name]}
           for name, vals in ms.items()}
    out["setup"] = {"warm": warm, "steps": steps, "rounds": rounds, "cpus": len(os.sched_getaffinity(0)),
                    "loadavg": os.getloadavg()}
    for name in variants:
        print(f"step A/B {name}: {out[name]['median_ms']:.2f} ms per iteration ({ms[name]})", flush=True)
    return out


def _tile_footprint(tr) -> dict:
    """The current model's tile intersections in the first training view (gsplat's own
    opacity-aware radii): the rasterizer's work grows with them, not with the Gaussian count."""
    from splat_train.render import _gsplat_backend
    from splat_train.export import render_params

    real, seen = _gsplat_backend._rasterization(), {}

    def spy(*args, **kwargs):
        rc, ra, meta = real(*args, **kwargs)
        seen.update(meta)
        return rc, ra, meta

    cam = tr.train_views[0].camera
    cw, K = tr.cams[0]
    deg = tr.sched.sh_degree_at(max(tr.iteration, 1), tr.cfg.sh_degree)
    with torch.no_grad(), mock.patch.object(_gsplat_backend, "_rasterization", lambda: spy):
        render_params(tr.params, deg, cw, K, cam.width, cam.height, tr.bg, tr.backend, depth=False, stats=False)
    visible = int((seen["radii"] > 0).all(-1).sum())
    isects = int(seen["isect_ids"].numel())
    return {"tile_intersections": isects, "gaussians": tr.num_gaussians, "visible": visible,
            "tiles_per_visible": isects / max(visible, 1)}


def late_profile(cell: Path, recipes: tuple[str, ...] = ("sparse", "paper"), warm: int = WARM_LATE, steps: int = 200,
                 rounds: int = 3, profile_steps: int = 30) -> dict:
    """Each recipe's step after ``warm`` iterations of the cell's 10,000 (past the sparse
    recipe's growth, which stops at 5,000): ms per iteration with the densification statistics
    skipped (what the trainer does once nothing reads them) and computed (as before), in turns
    (``rounds`` blocks of ``steps``); then the phases, the rasterizer alone, the tile footprint
    and the ``torch.profiler`` summary of that state."""
    out = {}
    trainers = {}
    for recipe in recipes:
        tr = cell_trainer(cell, recipe)
        t0 = time.perf_counter()
        iterate(tr, warm)
        torch.cuda.synchronize()
        warm_s = time.perf_counter() - t0
        strategy = type(tr.strategy)
        ab = {"stats_skipped": [], "stats_computed": []}
        for _ in range(rounds):
            ab["stats_skipped"].append(ms_per_step(tr, steps))
            with mock.patch.object(strategy, "wants_stats", lambda self, it: True):
                ab["stats_computed"].append(ms_per_step(tr, steps))
        res = {"warm_iterations": warm, "warm_s": warm_s, "gaussians": tr.num_gaussians, "steps": steps,
               "parts": [p.name for p in tr.parts],
               "ms_per_step": ab, "median_ms": {k: sorted(v)[len(v) // 2] for k, v in ab.items()},
               "stats_read_after_warm": bool(tr.strategy.wants_stats(tr.iteration + 1))}
        res["phases"] = phase_times(tr, steps)
        res["rasterizer_only_ms"] = rasterizer_only_ms(tr)
        res["footprint"] = _tile_footprint(tr)
        print(f"late profile {recipe}: {res['median_ms']} ms per iteration at {tr.num_gaussians} Gaussians; "
              f"rasterizer alone {res['rasterizer_only_ms']:.2f} ms; {res['footprint']}", flush=True)
        out[recipe], trainers[recipe] = res, tr
    for recipe, tr in trainers.items():  # the profiler's hooks slow every later launch: last
        out[recipe]["torch_profiler"] = torch_profile(tr, profile_steps)
        out[recipe]["host_bound"] = (out[recipe]["median_ms"]["stats_skipped"]
                                     > 1.2 * out[recipe]["torch_profiler"]["device_busy_ms_per_it"])
    return out


def profile(cell: Path, recipes: tuple[str, ...] = ("paper", "sparse"), warm: int = WARM, steps: int = 200,
            profile_steps: int = 30) -> dict:
    """The profile of each recipe (module docstring): every recipe's timings first, then the
    ``torch.profiler`` runs (its hooks stay in the process and slow every later launch)."""
    timed = {r: _time_recipe(cell, r, warm, steps) for r in recipes}
    for r, (out, tr) in timed.items():
        out["torch_profiler"] = torch_profile(tr, profile_steps)
        out["host_bound"] = out["ms_per_step"] > 1.2 * out["torch_profiler"]["device_busy_ms_per_it"]
    return {r: out for r, (out, _tr) in timed.items()}


def main() -> int:
    from benchmarks.gsplat_native import emit, preflight
    from runtime.cliargs import plain
    from splat_train.recipes import RECIPE_NAMES

    p = argparse.ArgumentParser(description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cell", type=Path, required=True, help="folder of bench_cell.py --prepare-only")
    p.add_argument("--recipe", action="append", choices=RECIPE_NAMES,
                   help="recipe(s) to profile (default: paper and sparse)")
    p.add_argument("--late", action="store_true",
                   help=f"profile late in the run: statistics skipped and computed, in turns (default --warm {WARM_LATE})")
    p.add_argument("--warm", type=int, default=None, help=f"iterations run before timing (default {WARM}; {WARM_LATE} with --late)")
    p.add_argument("--steps", type=int, default=200, help="iterations timed")
    p.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = p.parse_args()
    problem = preflight(args.cell, "profile_step")
    if problem:
        print(problem, file=sys.stderr)
        return 2
    recipes = tuple(args.recipe or ("paper", "sparse"))
    if args.late:
        res = late_profile(args.cell, recipes, warm=WARM_LATE if args.warm is None else args.warm, steps=args.steps)
    else:
        res = profile(args.cell, recipes, warm=WARM if args.warm is None else args.warm, steps=args.steps)
    emit(res, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
