"""Where one rasterizer forward+backward spends its time, stage by stage.

Stages of :func:`splat_train.rasterize` on the CPU backend, each timed alone (best of
``--reps``) on the synthetic scene of ``bench_rasterizer.py`` (SH degree 3):

* ``project``: the fused C++ projection + SH (``cpu_project``), forward only;
* ``sh``: 0 (SH colour is fused into ``project``; the column stays for the tables recorded with
  the scalar kernel "cpu_v1", since deleted, whose torch SH it timed);
* ``bin``: depth sort + tile lists (``bin_cpu`` with the footprints, i.e. the tight lists and
  the footprint pass that the blend then reuses);
* ``blend_fwd`` / ``blend_bwd``: the C++ blending kernel forward / backward (raw entries,
  including the per-pair gradient reduction);
* ``total_fwd`` / ``total_fwd_bwd``: the whole ``rasterize`` call and its backward
  (``loss = sum(rgb) + sum(alpha)``); ``autograd_rest`` = total minus the stages above, i.e.
  the backward of projection and SH plus glue.

    python benchmarks/profile_rasterizer.py --sizes 100000x256 100000x512 --backend cpu
    python benchmarks/profile_rasterizer.py --cpu-time   # CPU ms on one thread (loaded box, A/B of builds)
    python benchmarks/profile_rasterizer.py --checkpoint RUN/ckpt/ckpt_0009500.pt --cameras RUN_CAMERAS

``--checkpoint`` profiles a trained model instead of the synthetic scene: the Gaussians of a
trainer checkpoint (``splat_train`` ckpt/ folder) seen from one camera of a COLMAP model
(``--cameras``, ``--view`` index), e.g. the 200k small Gaussians of the 10,000-iteration fern
cell, whose cost profile differs from the synthetic scene's (more, smaller footprints).

Memory: this script runs with glibc's default malloc settings, so a fresh buffer above the mmap
threshold (sh_rest's 37 MB gradient at 206k Gaussians) is faulted in on every call; the
``splat_train`` CLI keeps freed memory (``runtime.memory.retain_freed_memory``), and
``profile_iteration.py`` does the same, so use that one for what a training run pays.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_rasterizer import make_scene  # noqa: E402


_CLOCK = time.perf_counter


def _best(fn, reps: int) -> float:
    best = float("inf")
    for _ in range(reps):
        t0 = _CLOCK()
        fn()
        best = min(best, _CLOCK() - t0)
    return best


def checkpoint_scene(ckpt: str, cameras: str, view: int) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, int, int]:
    """The Gaussians of a trainer checkpoint and one camera of a COLMAP model.

    Returns:
        ([means [N, 3], quats [N, 4], scales [N, 3] linear, opacities [N], sh [N, 16, 3]]
        leaf tensors (requires_grad), cam_from_world [4, 4], K [3, 3], width, height).
    """
    from camio.colmap import read_model
    from splat_train.training.checkpoint import load_checkpoint
    from splat_train.export import camera_tensors
    from splat_train.gaussians import activated, sh_coeffs

    p = {k: v.detach() for k, v in load_checkpoint(Path(ckpt), "cpu")["params"].items()}
    scales, opac, quats = activated(p)
    cams = read_model(cameras).cameras
    cam = cams[view]
    cw, K = camera_tensors(cam)
    leaves = [t.detach().clone().requires_grad_(True) for t in (p["means"], quats, scales, opac, sh_coeffs(p, 3))]
    return leaves, cw, K, cam.width, cam.height


def profile(n: int, size: int, backend: str, reps: int, scene=None) -> dict[str, float]:
    """Seconds per stage (best of ``reps``) for N Gaussians at size x size, or for ``scene``
    (:func:`checkpoint_scene`'s tuple; n and size are then ignored)."""
    from splat_train import rasterize
    from splat_train.render.cpu import raster as cpu_raster
    from splat_train.render.projection import project_gaussians
    from splat_train.render.sh import sh_to_color

    if scene is None:
        params, K = make_scene(n, size, size)
        eye, width, height = torch.eye(4), size, size
    else:
        params, eye, K, width, height = scene
    means, quats, scales, opac, sh = params
    centre = -eye[:3, :3].T @ eye[:3, 3]  # camera centre in the world
    res: dict[str, float] = {}
    from splat_train.render.cpu.project import project_sh_cpu

    res["project"] = _best(lambda: project_sh_cpu(means, quats, scales, sh, 3, eye, K, width, height, 0.01, 0.3), reps)
    res["sh"] = 0.0
    with torch.no_grad():
        proj = project_gaussians(means, quats, scales, eye, K, width, height)
        feats = torch.cat([sh_to_color(3, sh, means, centre), proj.depths[:, None]], 1).contiguous()
    fns = cpu_raster.backend_functions(backend)
    # "cpu" bins with the footprints (tight tile lists, as rasterize does)
    kw = {"means2d": proj.means2d, "conics": proj.conics, "opacities": opac.detach()}
    res["bin"] = _best(lambda: fns.tile_pairs(proj.depths, proj.rect, proj.visible, width, height, **kw), reps)
    bins = fns.tile_pairs(proj.depths, proj.rect, proj.visible, width, height, **kw)
    fwd = lambda: fns.forward_raw(proj.means2d, proj.conics, feats, opac.detach(), bins, width, height)  # noqa: E731
    res["blend_fwd"] = _best(fwd, reps)
    accum, t_final, last, _ = fwd()
    v_acc, v_t = torch.ones_like(accum), -torch.ones_like(t_final)
    res["blend_bwd"] = _best(lambda: fns.backward_raw(proj.means2d, proj.conics, feats, opac.detach(), bins,
                                                       width, height, t_final, last, v_acc, v_t), reps)

    def whole(do_bwd: bool) -> None:
        for p in params:
            p.grad = None
        out = rasterize(*params, eye, K, width, height, torch.zeros(3), sh_degree=3, backend=backend)
        if do_bwd:
            (out["rgb"].sum() + out["alpha"].sum()).backward()

    res["total_fwd"] = _best(lambda: whole(False), reps)
    res["total_fwd_bwd"] = _best(lambda: whole(True), reps)
    res["autograd_rest"] = res["total_fwd_bwd"] - sum(res[k] for k in ("project", "sh", "bin", "blend_fwd", "blend_bwd"))
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["100000x256", "100000x512"], help="NxSIZE")
    ap.add_argument("--backend", nargs="+", default=["cpu"], choices=["cpu"])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the kernel uses --kernel-threads)")
    ap.add_argument("--kernel-threads", type=int, default=2)
    ap.add_argument("--checkpoint", help="profile the Gaussians of this trainer checkpoint (instead of --sizes)")
    ap.add_argument("--cameras", help="with --checkpoint: COLMAP model folder of the camera to render from")
    ap.add_argument("--view", type=int, default=0, help="with --checkpoint: index of the camera in --cameras")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time by the calling thread's CPU time (sets torch and kernel threads to 1): robust to "
                         "waiting for a core on a loaded box, for comparing builds")
    args = ap.parse_args(argv)
    if (args.checkpoint is None) != (args.cameras is None):
        ap.error("--checkpoint and --cameras go together")
    if args.cpu_time:
        global _CLOCK
        _CLOCK = time.thread_time
        args.threads = args.kernel_threads = 1
    torch.set_num_threads(args.threads)
    from splat_train.render.cpu import raster as cpu_raster

    cpu_raster.set_kernel_threads(args.kernel_threads)
    print(f"load average {os.getloadavg()}, torch threads {args.threads}, kernel threads {args.kernel_threads}"
          + (", CPU time of the calling thread" if args.cpu_time else ", wall clock"))
    keys = ["project", "sh", "bin", "blend_fwd", "blend_bwd", "autograd_rest", "total_fwd", "total_fwd_bwd"]
    print(f"{'backend':>8} {'case':>12} " + " ".join(f"{k:>13}" for k in keys) + "  (ms)")
    if args.checkpoint is not None:
        scene = checkpoint_scene(args.checkpoint, args.cameras, args.view)
        n, (w, h) = scene[0][0].shape[0], scene[3:]
        print(f"checkpoint {args.checkpoint}: {n} Gaussians, view {args.view} ({w}x{h})")
        cases = [(f"{n}@{w}x{h}", n, 0, scene)]
    else:
        cases = [(s, *(int(x) for x in s.split("x")), None) for s in args.sizes]
    for name, n, size, scene in cases:
        for b in args.backend:
            r = profile(n, size, b, args.reps, scene)
            print(f"{b:>8} {name:>12} " + " ".join(f"{1e3 * r[k]:>13.1f}" for k in keys))
    print(f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
