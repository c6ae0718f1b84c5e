"""The GPU check (CUDA): VGGT fixtures on the GPU, our torch rasterizer against gsplat, the cell.

    python -m benchmarks --gpu [--out DIR] [--gpu-iterations 10000]     # the entry point
    python benchmarks/gpu_check.py [--out DIR]                            # parts 1-3 only

What it does, each part independent (a failing part is recorded, the others still run):
1. VGGT: the official reference fixtures (tests/data/vggt/shared) run on CUDA in float64 and
   float32; max |ours - expected| per output against the float64 / float32 expectations.
2. Rasterizer: one random scene (N Gaussians, SH degree 3) rendered on CUDA by our vectorised
   torch backend and by gsplat (through splat_train's adapter): image difference, relative
   difference of the gradients of every input, and the means2d gradient's shape.
3. Timing of forward+backward for both, with peak GPU memory.
4. (``run_gpu`` only) the pipeline cell of benchmarks/bench_cell.py (fern n = 3 when
   ../shared has it, else the synthetic scene) trained for 10,000 iterations on CUDA with the
   rasterizer forced to gsplat: stage times, PSNR, and the training process's peak GPU memory
   (``torch.cuda.max_memory_allocated``, from its train.json).
Not part of the test suite (CI has no GPU); tests/test_benchmarks_gpu.py checks the CLI only.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Callable

import torch

log = logging.getLogger("benchmarks")
ROOT = Path(__file__).resolve().parents[1]
FIX = ROOT / "tests" / "data" / "vggt" / "shared"
CELL_ITERATIONS = 10_000  # the paper's training length


def vggt_fixtures(device: str) -> dict:
    """VGGT on the reference fixtures at float64 and float32, max |ours - expected| per output.
    TF32 is switched off for the check (cuDNN convolutions use it by default on CUDA, which
    puts the float32 DPT heads ~1e-3 off: the first H100 run) and restored after."""
    flags = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        return {**_vggt_fixtures(device), "tf32": False}
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags


def _vggt_fixtures(device: str) -> dict:
    from safetensors.torch import load_file

    from vggt_init.model import VGGT, VGGTConfig

    cfg = VGGTConfig.from_fixture_config(json.loads((FIX / "config.json").read_text()))
    sd = load_file(str(FIX / "weights.safetensors"))
    inputs = load_file(str(FIX / "inputs.safetensors"))
    out = {}
    for dtype, name in ((torch.float64, "expected.safetensors"), (torch.float32, "expected_fp32.safetensors")):
        model = VGGT(cfg, heads=("camera", "depth", "point"))
        model.load_state_dict({k: v for k, v in sd.items() if k.split(".")[0] in
                               {"aggregator", "camera_head", "depth_head", "point_head"}}, strict=True)
        model = model.to(device=device, dtype=dtype).eval()
        exp = load_file(str(FIX / name))
        with torch.inference_mode():
            res = model(inputs["images"].to(device=device, dtype=dtype)[None])
        errs = {k: float((res[k].double().cpu() - exp[k].double()).abs().max())
                for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf") if k in exp}
        out[str(dtype).replace("torch.", "")] = {"max_abs_err": errs, "max": max(errs.values())}
    return out


def _scene(n: int, device: str, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.0, 1.0, 0.5]) + torch.tensor([0.0, 0.0, 4.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.05 + 0.005
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    ts = [t.to(device).requires_grad_(True) for t in (means, quats, scales, opac, sh)]
    return ts


def _render(backend: str, ts, W: int, H: int):
    from splat_train.rasterize import rasterize

    dev = ts[0].device
    view = torch.eye(4, device=dev)
    K = torch.tensor([[0.9 * W, 0, W / 2], [0, 0.9 * W, H / 2], [0, 0, 1.0]], device=dev)
    return rasterize(*ts, view, K, W, H, background=torch.zeros(3, device=dev), sh_degree=3, backend=backend)


def rasterizer_parity(device: str, n: int = 20000, size: int = 256) -> dict:
    res = {}
    cot = None
    grads = {}
    for backend in ("torch", "gsplat"):
        ts = _scene(n, device)
        out = _render(backend, ts, size, size)
        if cot is None:
            cot = torch.randn(out["rgb"].shape, generator=torch.Generator().manual_seed(1)).to(device)
        (out["rgb"] * cot).sum().backward()
        m2g = out["means2d"].grad
        grads[backend] = {"rgb": out["rgb"].detach(), "radii": out["radii"].detach(),
                          **{k: t.grad.detach() for k, t in zip(("means", "quats", "scales", "opacities", "sh"), ts)},
                          "means2d_grad": None if m2g is None else m2g.detach().reshape(-1, 2)}
        res[f"{backend}_means2d_grad_shape"] = None if m2g is None else list(m2g.shape)
    a, b = grads["torch"], grads["gsplat"]
    res["rgb_max_abs_diff"] = float((a["rgb"] - b["rgb"]).abs().max())
    res["rgb_mean_abs_diff"] = float((a["rgb"] - b["rgb"]).abs().mean())
    vis = (a["radii"] > 0) & (b["radii"] > 0)
    res["visible_torch_gsplat_both"] = [int((a["radii"] > 0).sum()), int((b["radii"] > 0).sum()), int(vis.sum())]
    for k in ("means", "quats", "scales", "opacities", "sh", "means2d_grad"):
        if a[k] is None or b[k] is None:
            res[f"grad_rel_l2_{k}"] = None
            continue
        x, y = a[k][vis].double(), b[k][vis].double()
        res[f"grad_rel_l2_{k}"] = float((x - y).norm() / x.norm().clamp_min(1e-30))
    return res


def rasterizer_timing(device: str, n: int = 100000, size: int = 512, reps: int = 10) -> dict:
    out = {}
    for backend in ("torch", "gsplat"):
        ts = _scene(n, device)
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        for i in range(reps + 2):
            if i == 2:
                torch.cuda.synchronize()
                t0 = time.perf_counter()
            o = _render(backend, ts, size, size)
            o["rgb"].sum().backward()
        torch.cuda.synchronize()
        out[backend] = {"fwd_bwd_ms": 1e3 * (time.perf_counter() - t0) / reps,
                        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20}
    out["speedup_gsplat"] = out["torch"]["fwd_bwd_ms"] / out["gsplat"]["fwd_bwd_ms"]
    out["case"] = f"{n} Gaussians, {size}x{size}, SH 3"
    return out


def gpu_cell(iterations: int = CELL_ITERATIONS, scene: str = "auto", prepared: Path | None = None) -> dict:
    """The pipeline cell on CUDA with the gsplat rasterizer (benchmarks/bench_cell.py, no VGGT
    forward: the fixtures part checks VGGT on the GPU). ``prepared``: a folder of
    ``bench_cell.py --prepare-only`` (its CPU stages made elsewhere; train, render, metrics here)."""
    sys.path.insert(0, str(ROOT))
    from benchmarks import bench_cell

    with tempfile.TemporaryDirectory(prefix="gpu_cell_") as tmp:
        return bench_cell.run_cell(Path(tmp), scene, 3, iterations, vggt=False, device="cuda", rasterizer="gsplat",
                                   prepared=prepared)


def run_gpu(cell_iterations: int = CELL_ITERATIONS, parts: tuple[str, ...] = ("vggt_fixtures", "rasterizer_parity",
            "rasterizer_timing", "cell"), on_part: Callable[[dict], None] | None = None,
            cell_prepared: Path | None = None) -> dict:
    """Run the parts on CUDA (each independent: a failure is recorded as ``{"error": ...}``);
    ``on_part(report)`` after each one (the caller saves it: a run cut off by a time limit
    keeps the parts done)."""
    import torch

    if not torch.cuda.is_available():
        raise RuntimeError("no CUDA device")
    from splat_train._gsplat_backend import installed_version

    report = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__, "cuda": torch.version.cuda,
              "gsplat": installed_version(), "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S")}
    fns = {"vggt_fixtures": vggt_fixtures, "rasterizer_parity": rasterizer_parity,
           "rasterizer_timing": rasterizer_timing, "cell": lambda _dev: gpu_cell(cell_iterations, prepared=cell_prepared)}
    for name in parts:
        t0 = time.perf_counter()
        try:
            report[name] = fns[name]("cuda")
        except Exception:  # noqa: BLE001  (record and go on: each part is independent)
            report[name] = {"error": traceback.format_exc()[-3000:]}
        report[name]["wall_s"] = time.perf_counter() - t0
        print(name, json.dumps(report[name], indent=1, default=str), flush=True)
        if on_part is not None:
            on_part(report)
    return report


def _f(x, spec: str = ".3g") -> str:
    return "n/a" if x is None else format(x, spec)


def format_gpu_table(r: dict) -> str:
    """The report as a Markdown table (one row per measured number)."""
    rows = [("device", r.get("device")), ("torch / CUDA / gsplat", f"{r.get('torch')} / {r.get('cuda')} / {r.get('gsplat')}")]
    v = r.get("vggt_fixtures", {})
    for dt in ("float64", "float32"):
        if dt in v:
            rows.append((f"VGGT fixtures on CUDA, {dt}: max abs err vs {dt} expectation", _f(v[dt]["max"])))
    p = r.get("rasterizer_parity", {})
    if "rgb_max_abs_diff" in p:
        rows.append(("torch vs gsplat: rgb max / mean abs diff",
                     f"{_f(p.get('rgb_max_abs_diff'))} / {_f(p.get('rgb_mean_abs_diff'))}"))
        for k in ("means", "quats", "scales", "opacities", "sh", "means2d_grad"):
            rows.append((f"torch vs gsplat: grad rel L2, {k}", _f(p.get(f"grad_rel_l2_{k}"))))
        rows.append(("means2d grad shape (torch, gsplat)",
                     f"{p.get('torch_means2d_grad_shape')}, {p.get('gsplat_means2d_grad_shape')}"))
    t = r.get("rasterizer_timing", {})
    if "torch" in t:
        rows.append((f"fwd+bwd ms torch / gsplat ({t.get('case')})",
                     f"{_f(t['torch']['fwd_bwd_ms'])} / {_f(t['gsplat']['fwd_bwd_ms'])} "
                     f"(x{_f(t.get('speedup_gsplat'))})"))
        rows.append(("peak GPU MB torch / gsplat", f"{_f(t['torch']['peak_gpu_mb'], '.0f')} / "
                                                   f"{_f(t['gsplat']['peak_gpu_mb'], '.0f')}"))
    c = r.get("cell", {})
    if "train" in c:
        tr = c["train"]
        rows.append((f"cell {c.get('scene')} n={c.get('n')}, {c.get('iterations')} it, rasterizer",
                     f"{tr.get('rasterizer')} on {tr.get('device')}"))
        rows.append(("cell: train s (it/s)", f"{_f(tr.get('wall_s'), '.1f')} ({_f(tr.get('it_per_s'), '.1f')})"))
        rows.append(("cell: peak GPU MB (training)", _f(tr.get("peak_cuda_mb"), ".0f")))
        rows.append(("cell: Gaussians, test PSNR dB", f"{tr.get('final_gaussians')}, {_f(tr.get('test_psnr'), '.2f')}"))
        rows.append(("cell: total s", _f(c.get("cell_total_s"), ".1f")))
    for name in ("vggt_fixtures", "rasterizer_parity", "rasterizer_timing", "cell"):
        if "error" in r.get(name, {}):
            rows.append((f"{name}: FAILED", r[name]["error"].strip().splitlines()[-1][:120]))
    lines = ["| check | result |", "|---|---|"] + [f"| {a} | {b} |" for a, b in rows]
    return "\n".join(lines)


def run_cli(out: Path, iterations: int | None = None, machine_info=None, cell_prepared: Path | None = None) -> int:
    """``python -m benchmarks --gpu``: every part, JSON + Markdown into ``out``, the table printed.
    Exits 2 with a message when torch sees no CUDA device."""
    if not torch.cuda.is_available():
        log.error("python -m benchmarks --gpu needs a CUDA GPU, and torch %s sees none here "
                  "(torch.cuda.is_available() is False). On a GPU machine: install a CUDA build of torch, "
                  "then pip install -e '.[gpu]' (README, 'GPU install').", torch.__version__)
        return 2
    from camio.atomic import write_json

    stem = out / f"benchmarks_gpu_{time.strftime('%Y%m%d_%H%M%S')}"
    machine = machine_info() if machine_info is not None else None

    def save(report: dict) -> str:  # after every part, so a run cut short keeps what it measured
        if machine is not None:
            report["machine"] = machine
        write_json(stem.with_suffix(".json"), report)
        table = format_gpu_table(report)
        stem.with_suffix(".md").write_text(table + "\n")
        return table

    report = run_gpu(iterations or CELL_ITERATIONS, on_part=save, cell_prepared=cell_prepared)
    table = save(report)
    print(table)
    log.info("saved %s.json and %s.md", stem, stem)
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out")
    args = p.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("no CUDA device: this check needs a GPU")
    report = run_gpu(parts=("vggt_fixtures", "rasterizer_parity", "rasterizer_timing"))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gpu_check.json").write_text(json.dumps(report, indent=2))
    print(format_gpu_table(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
