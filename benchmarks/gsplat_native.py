"""gsplat's own training loop on a prepared cell: the yardstick for ``splat_train`` on a GPU.

Trains the cell of ``bench_cell.py --prepare-only`` (the Bridge's seed and cameras, the
training images, the aligned held-out cameras) with ``gsplat.rasterization`` and gsplat's own
``DefaultStrategy``, with what ``splat_train``'s ``paper`` recipe uses: the same iterations,
view order (a reshuffled stack from a seeded generator), loss (L1 + 0.2 D-SSIM,
:func:`splat_train.losses.photometric_loss`), learning rates (position rate decayed from
1.6e-4 to 1.6e-6 x extent), fused Adam with eps 1e-15, SH degree schedule, densification
window, period, gradient threshold and opacity-reset period, and the same scene extent. What
differs is the engine: gsplat's strategy instead of :mod:`splat_train.strategy.densify`, and no
per-iteration logging, held-out evaluation or checkpoints (held-out PSNR once, at the end).

    python benchmarks/gsplat_native.py --cell .gpu_cell --iterations 10000 --out OUT.json

Prints and writes: wall seconds of the loop, seconds per 1,000 iterations, final Gaussian
count, peak GPU memory, held-out PSNR. CUDA and gsplat only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def load_cell(cell: Path):
    """(train views, test views, seed cloud) of a prepared cell folder."""
    from splat_train.data import load_views, read_name_list
    from camio.ply import read_gaussian_ply

    state = json.loads((cell / "prepared.json").read_text())
    names = read_name_list(cell / state["train_txt"])
    train = load_views(cell / "bridge" / "sparse" / "0", cell / state["scene"] / "images", names)
    test = load_views(cell / "align" / "sparse" / "0", cell / state["test_dir"])
    return train, test, read_gaussian_ply(cell / "bridge" / "seed.ply")


def preflight(cell: Path, prog: str) -> str | None:
    """The one-line reason a GPU script of this folder cannot run on ``cell`` here (no CUDA
    device, or not a folder of ``bench_cell.py --prepare-only``), or None."""
    if not torch.cuda.is_available():
        return f"{prog}: needs a CUDA GPU"
    if not (cell / "prepared.json").is_file():
        return f"{prog}: {cell} is not a prepared cell (make one with: python benchmarks/bench_cell.py --prepare-only DIR)"
    return None


def emit(result: dict, out: Path | None) -> None:
    """Print ``result`` as JSON and, with ``out``, write it there (atomically)."""
    from runtime.atomic import write_json

    print(json.dumps(result, indent=1))
    if out is not None:
        write_json(out, result)


def _rasterization():
    """``gsplat.rasterization`` (a function so that a CPU test can substitute a stand-in)."""
    from gsplat import rasterization

    return rasterization


def train_native(cell: Path, iterations: int, seed: int = 0, device: str = "cuda", **overrides) -> dict:
    """Train the prepared ``cell`` with gsplat's loop on ``device`` (CUDA; a CPU run needs a
    stand-in for :func:`_rasterization`) and score the held-out views once at the end.
    ``overrides``: TrainConfig keys on top of the ``paper`` recipe (the schedule ones too)."""
    from gsplat import DefaultStrategy

    from splat_train.config import TrainConfig
    from splat_train.data import scene_extent
    from splat_train.export import camera_tensors
    from splat_train.gaussians import params_from_cloud, position_lr
    from splat_train.losses import photometric_loss, psnr

    dev = torch.device(device)
    cuda = dev.type == "cuda"
    rasterization = _rasterization()
    cfg = TrainConfig(recipe="paper", iterations=iterations, device=device, seed=seed, **overrides)
    sched = cfg.schedule()
    train, test, cloud = load_cell(cell)
    extent = scene_extent([v.camera for v in train], cloud.means if cfg.extent_from_points else None)
    p = params_from_cloud(cloud, cfg.sh_degree, dev)
    params = torch.nn.ParameterDict({
        "means": p["means"], "scales": p["scales"], "quats": p["quats"], "opacities": p["opacity"],
        "sh0": torch.nn.Parameter(p["sh_dc"].reshape(len(cloud), 1, 3)), "shN": p["sh_rest"]})
    lrs = {"means": cfg.lr_position_init * extent, "scales": cfg.lr_scaling, "quats": cfg.lr_rotation,
           "opacities": cfg.lr_opacity, "sh0": cfg.lr_sh_dc, "shN": cfg.lr_sh_rest}
    optimizers = {k: torch.optim.Adam([{"params": [params[k]], "lr": lrs[k], "name": k}], eps=cfg.adam_eps,
                                      fused=True) for k in params}
    strategy = DefaultStrategy(
        prune_opa=0.005, grow_grad2d=cfg.densify_grad_threshold, grow_scale3d=cfg.percent_dense,
        refine_start_iter=sched.densify_from, refine_stop_iter=sched.densify_until,
        reset_every=sched.opacity_reset_every or 10**9, refine_every=sched.densify_every, absgrad=False)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=extent)
    cams = [camera_tensors(v.camera, dev) for v in train]
    targets = [torch.as_tensor(v.image, device=dev) for v in train]
    bg = torch.tensor(cfg.background, dtype=torch.float32, device=dev)
    gen = torch.Generator().manual_seed(seed)
    stack: list[int] = []

    def render(view, K, w, h, deg):
        colors = torch.cat([params["sh0"], params["shN"]], 1)
        img, _, info = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                     torch.sigmoid(params["opacities"]), colors, view[None], K[None], w, h,
                                     sh_degree=deg, packed=False, backgrounds=bg[None])
        return img[0], info

    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    marks = {}
    for it in range(1, iterations + 1):
        if not stack:
            stack = torch.randperm(len(train), generator=gen).tolist()
        i = stack.pop()
        for g in optimizers["means"].param_groups:
            g["lr"] = position_lr(cfg, it, extent)
        cam = train[i].camera
        img, info = render(*cams[i], cam.width, cam.height, sched.sh_degree_at(it, cfg.sh_degree))
        strategy.step_pre_backward(params, optimizers, state, it - 1, info)
        loss, _, _ = photometric_loss(img, targets[i], cfg.lambda_dssim)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        # gsplat counts steps from 0; ours from 1: step it-1 here is our iteration it
        strategy.step_post_backward(params, optimizers, state, it - 1, info, packed=False)
        if it % 1000 == 0:
            if cuda:
                torch.cuda.synchronize()
            marks[it] = time.perf_counter() - t0
            print(f"gsplat-native it {it}: {marks[it]:.1f} s, {len(params['means'])} Gaussians", flush=True)
    if cuda:
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else None
    with torch.no_grad():
        scores = []
        for v in test:
            view, K = camera_tensors(v.camera, dev)
            img, _ = render(view, K, v.camera.width, v.camera.height, cfg.sh_degree)
            scores.append(psnr(img.clamp(0, 1), torch.as_tensor(v.image, device=dev)))
    return {"engine": "gsplat.rasterization + gsplat.DefaultStrategy", "iterations": iterations, "wall_s": wall,
            "s_per_1000_it": 1000 * wall / iterations, "final_gaussians": len(params["means"]),
            "peak_cuda_mb": peak, "test_psnr": sum(scores) / len(scores), "scene_extent": extent,
            "schedule": sched.to_dict(), "marks_s": marks}


def main() -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cell", type=Path, required=True, help="folder of bench_cell.py --prepare-only")
    p.add_argument("--iterations", type=int, default=10000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = p.parse_args()
    problem = preflight(args.cell, "gsplat_native")
    if problem:
        print(problem, file=sys.stderr)
        return 2
    emit(train_native(args.cell, args.iterations, args.seed), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
