"""Where one whole training iteration spends its time, phase by phase.

Continues a trainer checkpoint for ``--steps`` iterations by calling the trainer itself: its
:meth:`splat_train.training.trainer.Trainer.step`, then the densification step that ``Trainer.run``
takes after it. The calls the step makes are timed through thin wrappers around them (nothing of
the iteration is copied here, so a change to the step is profiled as it is):

* ``render``: :func:`splat_train.export.render_params` (projection + SH, binning, blending);
* ``loss``: the trainer's :class:`splat_train.losses.TrainingLoss` (L1 + D-SSIM forward);
* ``backward``: ``loss.backward()`` (SSIM, blending and projection backward, autograd glue);
* ``densify_state``: :meth:`DensifyStrategy.update_state` (view-space gradient statistics);
* ``adam``: :func:`splat_train.gaussians.adam_step` and the optimizer's ``zero_grad``;
* ``other``: the rest of ``Trainer.step`` (learning-rate schedule, view choice, the finiteness
  check, the pose step with ``--pose-refine``, any further loss term, the logged scalars);
* ``strategy``: densify / prune / opacity reset (zero unless the steps cross a densify
  iteration: every 100 by default).

Nothing is written: the checkpoint's folder is left as it is. The malloc settings of the
``splat_train`` CLI (:func:`runtime.memory.retain_freed_memory`) are applied, so the times
are those of a CLI run.

    python benchmarks/profile_iteration.py --checkpoint RUN/ckpt/ckpt_0009500.pt \\
        --seed-ply BRIDGE/seed.ply --cameras BRIDGE/sparse/0 --images SCENE/images
    python benchmarks/profile_iteration.py ... --torch-profile   # also torch's operator table
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import sys
import time
from pathlib import Path
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from runtime.cliargs import deprecated_flags  # noqa: E402

PHASES = ("render", "loss", "backward", "densify_state", "adam", "other", "strategy")


def make_trainer(checkpoint: str, seed: str, cameras: str, images: str, kernel_threads: int):
    """A :class:`splat_train.training.trainer.Trainer` restored from ``checkpoint`` (config, views and
    inputs digest taken from the checkpoint; outputs go to a temporary folder never written)."""
    import tempfile

    from splat_train.render.cpu import raster as cpu_raster
    from splat_train.training.checkpoint import load_checkpoint
    from splat_train.config import TrainConfig
    from splat_train.data import load_views
    from splat_train.training.trainer import Trainer

    data = load_checkpoint(Path(checkpoint), "cpu")
    cfg = TrainConfig(**data["config"])
    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    cpu_raster.set_kernel_threads(kernel_threads or cfg.kernel_threads or len(os.sched_getaffinity(0)))
    views = load_views(cameras, images, list(data["train_names"]), cfg.downsample, tuple(cfg.background))
    out = tempfile.mkdtemp(prefix="profile_iteration_")
    tr = Trainer(cfg, seed, views, out, [], ckpt_dir=out, digest=data["inputs_sha256"])
    tr.restore(Path(checkpoint))
    return tr


@contextlib.contextmanager
def timed_calls(tr, ph: dict[str, float]):
    """While inside: the calls that ``tr.step()`` makes add their seconds to ``ph`` (see the
    module doc), by wrappers put where the step looks them up (the trainer module's names, the
    strategy's and the optimizer's methods, ``torch.Tensor.backward``); left as they were after."""

    def timed(key: str, fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                ph[key] += time.perf_counter() - t0
        return wrapper

    with contextlib.ExitStack() as stack:
        for obj, name, key in step_calls(tr):
            stack.enter_context(mock.patch.object(obj, name, timed(key, getattr(obj, name))))
        yield


def step_calls(tr) -> tuple[tuple[object, str, str], ...]:
    """(object, attribute, phase) of each call that ``tr.step()`` makes and a profile times:
    the names where the step looks them up (the trainer module's, the trainer's own loss, the
    strategy's and the optimizer's methods, ``torch.Tensor.backward``)."""
    from splat_train.training import trainer as trainer_mod

    return ((trainer_mod, "render_params", "render"), (tr, "photometric", "loss"),
            (torch.Tensor, "backward", "backward"), (trainer_mod, "adam_step", "adam"),
            (tr.strategy, "update_state", "densify_state"), (tr.optimizer, "zero_grad", "adam"))


def profile_steps(tr, steps: int) -> dict[str, float]:
    """Seconds per phase summed over ``steps`` iterations of ``tr`` (advances its state): each
    iteration is ``tr.step()`` and then the strategy step that ``Trainer.run`` takes after it.
    The wrappers go in once for all the iterations (the strategy step calls none of the wrapped
    names), so that the loop's own time between the phases stays a few microseconds."""
    ph = dict.fromkeys(PHASES, 0.0)
    inside = [k for k in PHASES if k not in ("other", "strategy")]  # the phases within tr.step()
    with timed_calls(tr, ph):
        for _ in range(steps):
            inner = sum(ph[k] for k in inside)
            t0 = time.perf_counter()
            tr.step()
            ph["other"] += time.perf_counter() - t0 - (sum(ph[k] for k in inside) - inner)
            t0 = time.perf_counter()
            tr.strategy.step(tr.params, tr.optimizer, tr.state, tr.iteration, tr.extent, tr.gen)
            ph["strategy"] += time.perf_counter() - t0
    return ph


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", required=True, help="a splat_train checkpoint (RUN/ckpt/ckpt_*.pt)")
    ap.add_argument("--seed-ply", dest="seed_ply", required=True, help="the run's seed point cloud (PLY)")
    ap.add_argument("--cameras", required=True, help="the run's training cameras (COLMAP model folder)")
    ap.add_argument("--images", required=True, help="the run's training images folder")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=2, help="iterations run first and not timed")
    ap.add_argument("--kernel-threads", type=int, default=0, help="0: the checkpoint's setting / all cores")
    ap.add_argument("--torch-profile", action="store_true", help="also print torch.profiler's operator table")
    args = ap.parse_args(deprecated_flags(list(sys.argv[1:] if argv is None else argv),
                                          "benchmarks/profile_iteration.py", {"--seed": ("--seed-ply", None)}))
    from runtime.memory import retain_freed_memory

    retain_freed_memory()
    tr = make_trainer(args.checkpoint, args.seed_ply, args.cameras, args.images, args.kernel_threads)
    profile_steps(tr, args.warmup)
    load0, t0, c0 = os.getloadavg()[0], time.perf_counter(), time.process_time()
    ph = profile_steps(tr, args.steps)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"{tr.num_gaussians} Gaussians, iterations {tr.iteration - args.steps + 1}-{tr.iteration}, "
          f"torch threads {torch.get_num_threads()}, load {load0:.2f} -> {os.getloadavg()[0]:.2f}")
    print(f"{1e3 * wall / args.steps:.1f} ms per iteration ({1e3 * cpu / args.steps:.1f} CPU ms)")
    for k in PHASES:
        print(f"  {k:14s} {1e3 * ph[k] / args.steps:8.1f} ms  {100 * ph[k] / wall:5.1f} %")
    if args.torch_profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            profile_steps(tr, args.steps)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    return 0


if __name__ == "__main__":
    sys.exit(main())
