"""Where one whole training iteration spends its time, phase by phase (issue 15, part 2).

Continues a trainer checkpoint for ``--steps`` iterations, exactly as ``Trainer.step`` and the
densification bookkeeping of ``Trainer.run`` do, and times each phase:

* ``render``: :func:`splat_train.export.render_params` (projection + SH, binning, blending);
* ``loss``: L1 + D-SSIM forward;
* ``backward``: ``loss.backward()`` (SSIM, blending and projection backward, autograd glue);
* ``densify_state``: :meth:`DensifyStrategy.update_state` (view-space gradient statistics);
* ``adam``: optimizer step and ``zero_grad``;
* ``strategy``: densify / prune / opacity reset (zero unless the steps cross a densify
  iteration: every 100 by default).

Nothing is written: the checkpoint's folder is left as it is. The malloc settings of the
``splat_train`` CLI (:func:`vggt_init.memory.retain_freed_memory`) are applied, so the times
are those of a CLI run.

    python benchmarks/profile_iteration.py --checkpoint RUN/ckpt/ckpt_0009500.pt \\
        --seed BRIDGE/seed.ply --cameras BRIDGE/sparse/0 --images SCENE/images
    python benchmarks/profile_iteration.py ... --torch-profile   # also torch's operator table
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PHASES = ("render", "loss", "backward", "densify_state", "adam", "strategy")


def make_trainer(checkpoint: str, seed: str, cameras: str, images: str, kernel_threads: int):
    """A :class:`splat_train.trainer.Trainer` restored from ``checkpoint`` (config, views and
    inputs digest taken from the checkpoint; outputs go to a temporary folder never written)."""
    import tempfile

    from splat_train.cpu import raster as cpu_raster
    from splat_train.checkpoint import load_checkpoint
    from splat_train.config import TrainConfig
    from splat_train.data import load_views
    from splat_train.trainer import Trainer

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


def profile_steps(tr, steps: int) -> dict[str, float]:
    """Seconds per phase summed over ``steps`` iterations of ``tr`` (advances its state)."""
    from splat_train.cpu.optim import adam_step
    from splat_train.export import render_params
    from splat_train.losses import photometric_loss

    cfg, ph = tr.cfg, dict.fromkeys(PHASES, 0.0)

    def tick(key: str, t0: float) -> float:
        t = time.perf_counter()
        ph[key] += t - t0
        return t

    for _ in range(steps):
        tr.iteration += 1
        it = tr.iteration
        deg = tr.sched.sh_degree_at(it, cfg.sh_degree)
        idx = tr.next_view()
        cam = tr.train_views[idx].camera
        t0 = time.perf_counter()
        out = render_params(tr.params, deg, tr.camera(idx), tr.intrinsics(idx), cam.width, cam.height, tr.bg,
                            tr.backend)
        t0 = tick("render", t0)
        loss, _, _ = photometric_loss(out["rgb"], tr.targets[idx], cfg.lambda_dssim)
        t0 = tick("loss", t0)
        loss.backward()
        t0 = tick("backward", t0)
        if out["means2d"].grad is not None:
            tr.strategy.update_state(tr.state, out["means2d"].grad, out["radii"], out["visible"],
                                     cam.width, cam.height, it)
        t0 = tick("densify_state", t0)
        adam_step(tr.optimizer)
        tr.optimizer.zero_grad(set_to_none=True)
        t0 = tick("adam", t0)
        tr.strategy.step(tr.params, tr.optimizer, tr.state, it, tr.extent, tr.gen)
        tick("strategy", t0)
    return ph


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", required=True, help="a splat_train checkpoint (RUN/ckpt/ckpt_*.pt)")
    ap.add_argument("--seed", required=True, help="the run's seed PLY")
    ap.add_argument("--cameras", required=True, help="the run's training cameras (COLMAP model folder)")
    ap.add_argument("--images", required=True, help="the run's training images folder")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=2, help="iterations run first and not timed")
    ap.add_argument("--kernel-threads", type=int, default=0, help="0: the checkpoint's setting / all cores")
    ap.add_argument("--torch-profile", action="store_true", help="also print torch.profiler's operator table")
    args = ap.parse_args(argv)
    from vggt_init.memory import retain_freed_memory

    retain_freed_memory()
    tr = make_trainer(args.checkpoint, args.seed, args.cameras, args.images, args.kernel_threads)
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
