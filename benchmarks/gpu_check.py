"""The GPU check (CUDA): VGGT, our rasterizer against gsplat, the workflow's stage commands,
the paper's cell with both recipes and gsplat's own training loop.

    python -m benchmarks --gpu [--out DIR] [--gpu-iterations 10000] [--gpu-parts a,b]
        [--cell-prepared DIR] [--stages DIR]                            # the entry point
    bash scripts/gpu_run.sh OUT                                         # on a machine without network
    python benchmarks/gpu_check.py [--out DIR]                          # VGGT fixtures and rasterizer only

The parts (:data:`PARTS`, in this order; each independent: a failing part is recorded as
``{"error": ...}`` and the others still run; benchmarks/README.md, "GPU", lists what each
measures): ``vggt_fixtures`` (the official fixtures, float64 / float32, TF32 off and on),
``vggt_cli`` and ``workflow_cell`` (stage commands on CUDA against a CPU run, from a
``benchmarks/gpu_stages.py prepare`` folder; skipped without ``--stages``), ``vggt_speed``
(VGGT-1B, random weights), ``gsplat_build``, ``rasterizer_parity`` and ``rasterizer_timing``,
``cell`` and ``cell_sparse`` (benchmarks/bench_cell.py's fern n = 3 cell, 10,000 iterations on
gsplat, ``paper`` and ``sparse`` recipes), ``native`` (the same cell, benchmarks/gsplat_native.py),
``loop_gap`` (``paper`` and gsplat's own loop on the same cell over many seeds, several runs at a
time: benchmarks/loop_gap.py),
``profile`` and ``step_ab`` (benchmarks/profile_step.py), ``vggt_frames``, ``vggt_many`` and
``vggt_search`` (benchmarks/vggt_frames.py: 12-200 frames, 1,000 frames, the largest count),
``backend_agree`` (benchmarks/backend_agree.py, on a packed grid cell: ``--gpu-agree-cell``).
Not part of the test suite (CI has no GPU); tests/test_benchmarks_gpu.py checks the CLI, the
report and, on CPU stand-ins, the native loop and the stage commands.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Callable

import torch

from experiments.results_doc.gpu_table import PARTS, format_gpu_table  # noqa: E402  (the report's table)

log = logging.getLogger("benchmarks")
ROOT = Path(__file__).resolve().parents[1]
FIX = ROOT / "tests" / "data" / "vggt" / "shared"
CELL_ITERATIONS = 10_000  # the paper's training length


def vggt_fixtures(device: str) -> dict:
    """VGGT on the reference fixtures at float64 and float32, max |ours - expected| per output,
    with TF32 off (the check: cuDNN convolutions use TF32 by default on CUDA, which put the
    float32 DPT heads ~2e-3 off on the first H100 run) and with TF32 on (what a user gets with
    ``torch.backends.cuda.matmul.allow_tf32``); the flags are restored after."""
    flags = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    out = {}
    try:
        for tf32 in (False, True):
            torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = tf32
            out[f"tf32_{'on' if tf32 else 'off'}"] = _vggt_fixtures(device)
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags
    return out


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


def vggt_chunked(device: str) -> dict:
    """The official fixtures on ``device`` with every chunked path of the many-frame forward
    forced on (token chunks of 16 tokens, attention in query chunks of 16 rows from the first
    row; TF32 off): the max abs error per output against the float64 and float32 expectations,
    as :func:`vggt_fixtures` measures the one-pass forward."""
    from vggt_init.model import fastpath, layers

    saved = (layers.TOKEN_CHUNK, fastpath.QUERY_CHUNK_MIN_ROWS, fastpath.QUERY_CHUNK_ROWS,
             torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    try:
        layers.TOKEN_CHUNK, fastpath.QUERY_CHUNK_MIN_ROWS, fastpath.QUERY_CHUNK_ROWS = 16, 0, 16
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
        out = _vggt_fixtures(device)
    finally:
        (layers.TOKEN_CHUNK, fastpath.QUERY_CHUNK_MIN_ROWS, fastpath.QUERY_CHUNK_ROWS,
         torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32) = saved
    return {"token_chunk": 16, "query_chunk_rows": 16, **out}


def vggt_speed(device: str, frames: int = 12, width: int = 518, height: int = 392, reps: int = 5) -> dict:
    """VGGT-1B forward on ``frames`` images of ``width`` x ``height`` with RANDOM weights (speed
    and memory only), camera and point heads (what vggt_init runs), fp32 and bf16 (the trunk
    cast to bf16, as vggt_init's ``--dtype bf16``); median of ``reps`` after two warm-ups,
    the model already on the GPU (the time after loading)."""
    from vggt_init.model import VGGT

    out = {"frames": frames, "size": f"{width}x{height}", "weights": "RANDOM (speed only)"}
    for dtype in ("fp32", "bf16"):
        torch.manual_seed(0)
        with torch.device(device):
            model = VGGT(heads=("camera", "point")).eval().requires_grad_(False)
        trunk = torch.bfloat16 if dtype == "bf16" else None
        if trunk is not None:
            model.cast_trunk_weights(trunk)
        x = torch.rand(1, frames, 3, height, width, device=device)
        torch.cuda.reset_peak_memory_stats()
        times = []
        with torch.inference_mode():
            for i in range(reps + 2):
                torch.cuda.synchronize()
                t0 = time.perf_counter()
                model(x, trunk_dtype=trunk)
                torch.cuda.synchronize()
                if i >= 2:
                    times.append(time.perf_counter() - t0)
        out[dtype] = {"forward_s_median": sorted(times)[len(times) // 2], "forward_s_min": min(times),
                      "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20}
        del model, x
        torch.cuda.empty_cache()
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
    from splat_train.render.rasterize import rasterize

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


def gpu_cell(iterations: int = CELL_ITERATIONS, scene: str = "auto", prepared: Path | None = None,
             recipe: str = "paper") -> dict:
    """The pipeline cell on CUDA with the gsplat rasterizer (benchmarks/bench_cell.py, no VGGT
    forward: the fixtures part checks VGGT on the GPU). ``prepared``: a folder of
    ``bench_cell.py --prepare-only`` (its CPU stages made elsewhere; train, render, metrics here).
    ``recipe``: the training recipe (``paper``: the paper's cell; ``cell_sparse`` runs ``sparse``)."""
    sys.path.insert(0, str(ROOT))
    from benchmarks import bench_cell

    with tempfile.TemporaryDirectory(prefix="gpu_cell_") as tmp:
        return bench_cell.run_cell(Path(tmp), scene, 3, iterations, vggt=False, device="cuda", rasterizer="gsplat",
                                   prepared=prepared, recipe=recipe)


def native_cell(iterations: int, prepared: Path | None) -> dict:
    """The same prepared cell trained by gsplat's own loop (benchmarks/gsplat_native.py)."""
    if prepared is None:
        raise ValueError("the gsplat-native loop needs a prepared cell (--cell-prepared)")
    from benchmarks.gsplat_native import train_native

    return train_native(prepared, iterations)


def gsplat_build(device: str) -> dict:
    """Load gsplat's CUDA extension, JIT-building it on a fresh machine (its time is the
    first-use cost a user pays once per machine); gsplat removes a build folder that another
    process is still building, so nothing else may import it meanwhile."""
    t0 = time.perf_counter()
    from gsplat.cuda._backend import _C

    if _C is None:
        raise RuntimeError("gsplat's CUDA extension did not load (no CUDA toolkit found?)")
    return {"load_or_build_s": time.perf_counter() - t0, "arch_list": os.environ.get("TORCH_CUDA_ARCH_LIST"),
            "max_jobs": os.environ.get("MAX_JOBS")}


def gsplat_build_marker(marker: str) -> int:
    """:func:`gsplat_build` in a process of its own (scripts/gpu_run.sh's background build),
    its result or its error written to ``marker`` when it ends, failed or not (atomically: the
    part that waits for the file reads it whole); exit status 0 or 1."""
    from runtime.atomic import write_json

    try:
        res = gsplat_build("cuda")
    except Exception:  # noqa: BLE001  (the waiting part reports it)
        res = {"error": traceback.format_exc()[-3000:]}
    write_json(marker, res)
    print(json.dumps(res), flush=True)
    return 1 if "error" in res else 0


# the parts that import gsplat (they wait for a background build: scripts/gpu_run.sh)
GSPLAT_PARTS = ("rasterizer_parity", "rasterizer_timing", "workflow_cell", "profile", "profile_late", "step_ab", "cell", "native",
                "cell_sparse", "loop_gap", "backend_agree")
# seconds the vggt_frames part may take (it stops starting new forwards past its deadline)
VGGT_FRAMES_BUDGET_S = 240.0
# vggt_many: the upstream model's frame count on 80 GB, run for real after a 12-frame warm-up
VGGT_MANY_FRAMES = 1000
# vggt_search: the probe search from here up (doubling steps), bisected to the resolution. The
# start is just under what the H100's 1,000-frame run predicts for 80 GB (20.9 MiB per frame
# from 200 to 1,000 frames: ~3,670; docs/results.md); a start that does not fit is bisected
# down from. Each probe near 3,500 frames takes ~1 min.
VGGT_SEARCH_FROM, VGGT_SEARCH_STEP, VGGT_SEARCH_RESOLUTION = 3500, 250, 50


def _run_deadline(budget_s: float, reserve_s: float) -> float:
    """A ``time.time()`` deadline: ``budget_s`` from now, and no later than ``GPU_RUN_DEADLINE``
    (a Unix time, when set: the end of a lent machine's time) less ``reserve_s``."""
    end = time.time() + budget_s
    if os.environ.get("GPU_RUN_DEADLINE"):
        end = min(end, float(os.environ["GPU_RUN_DEADLINE"]) - reserve_s)
    return end


def step_profile(prepared: Path | None) -> dict:
    """benchmarks/profile_step.py on the prepared cell, both recipes."""
    if prepared is None:
        raise ValueError("the step profile needs a prepared cell (--cell-prepared)")
    from benchmarks.profile_step import profile

    return profile(prepared)


def late_step_profile(prepared: Path | None) -> dict:
    """benchmarks/profile_step.py's late-run profile on the prepared cell: both recipes after
    :data:`benchmarks.profile_step.WARM_LATE` of the 10,000 iterations (past ``sparse``'s
    growth), the densification statistics skipped and computed in turns."""
    if prepared is None:
        raise ValueError("the late step profile needs a prepared cell (--cell-prepared)")
    from benchmarks.profile_step import late_profile

    return late_profile(prepared)


def step_ab(prepared: Path | None) -> dict:
    """benchmarks/profile_step.py's in-process comparison of the recipes and the sparse recipe's
    parts on the prepared cell."""
    if prepared is None:
        raise ValueError("the step comparison needs a prepared cell (--cell-prepared)")
    from benchmarks.profile_step import recipe_ab

    return recipe_ab(prepared)


def vggt_frames_part(device: str, on_result: Callable[[dict], None] | None = None) -> dict:
    """benchmarks/vggt_frames.py within :data:`VGGT_FRAMES_BUDGET_S` (environment
    ``VGGT_FRAMES_BUDGET_S`` overrides it), and no later than ``GPU_RUN_DEADLINE`` (a Unix time,
    when set: the end of a lent machine's time) less a minute for a forward already started."""
    from benchmarks.vggt_frames import vggt_frames

    end = _run_deadline(float(os.environ.get("VGGT_FRAMES_BUDGET_S", VGGT_FRAMES_BUDGET_S)), 60.0)
    return vggt_frames(device, deadline_s=time.perf_counter() + (end - time.time()), on_result=on_result,
                       search_resolution=50)


def vggt_many_part(device: str, on_result: Callable[[dict], None] | None = None) -> dict:
    """benchmarks/vggt_frames.py at 12 and :data:`VGGT_MANY_FRAMES` frames, real and probed, no
    search (``vggt_search`` does that): the upstream figure's frame count, timed."""
    from benchmarks.vggt_frames import vggt_frames

    end = _run_deadline(float("inf"), 60.0)
    return vggt_frames(device, deadline_s=time.perf_counter() + (end - time.time()), counts=(12, VGGT_MANY_FRAMES),
                       on_result=on_result, search_max=0, bigger=())


def vggt_search_part(device: str, on_result: Callable[[dict], None] | None = None) -> dict:
    """The probe search for the largest frame count that fits, from :data:`VGGT_SEARCH_FROM` up,
    with the caching allocator's expandable segments on (the search's tensors are GB each: a
    fragmented pool must not be what stops it); deadline as ``vggt_frames`` (no budget of its
    own unless ``VGGT_SEARCH_BUDGET_S`` sets one, so that later parts keep their time)."""
    from benchmarks.vggt_frames import vggt_frames

    # torch 2.11 names it torch._C._accelerator_setAllocatorSettings; older ones only the other
    set_alloc = getattr(torch._C, "_accelerator_setAllocatorSettings", None) or torch.cuda.memory._set_allocator_settings
    setting = "expandable_segments:True"
    try:
        set_alloc(setting)
    except (AttributeError, RuntimeError) as exc:
        setting = f"default (setting expandable segments failed: {exc})"
    end = _run_deadline(float(os.environ.get("VGGT_SEARCH_BUDGET_S", "inf")), 90.0)
    try:
        res = vggt_frames(device, deadline_s=time.perf_counter() + (end - time.time()), counts=(12,),
                          on_result=on_result, search_from=VGGT_SEARCH_FROM, search_step=VGGT_SEARCH_STEP,
                          search_resolution=VGGT_SEARCH_RESOLUTION, search_from_prediction=False, bigger=())
    finally:
        if setting.startswith("expandable"):
            set_alloc("expandable_segments:False")
    res["allocator"] = setting
    return res


def wait_for_gsplat_build(end: float) -> tuple[float, dict | None]:
    """Wait (until ``end``, a ``time.time()``) for ``GSPLAT_BUILD_MARKER``, the file
    scripts/gpu_run.sh's background JIT build of gsplat writes when it ends: importing gsplat
    while it builds would remove the build folder. Returns (seconds waited, the build's record;
    None when no background build runs); RuntimeError when it failed or wrote nothing in time."""
    marker = os.environ.get("GSPLAT_BUILD_MARKER")
    if not marker:
        return 0.0, None
    waited = time.perf_counter()
    while not Path(marker).exists() and time.time() < end:
        time.sleep(1.0)
    waited = time.perf_counter() - waited
    if not Path(marker).exists():
        raise RuntimeError(f"gsplat's background build wrote no {marker} before the deadline")
    build = json.loads(Path(marker).read_text())
    if "error" in build:
        raise RuntimeError(f"gsplat's background build failed:\n{build['error']}")
    return waited, build


def loop_gap_part(prepared: Path | None, iterations: int, on_result: Callable[[dict], None] | None = None) -> dict:
    """benchmarks/loop_gap.py on the prepared cell: ``paper`` and gsplat's own loop over the seeds
    of ``LOOP_GAP_SEEDS`` (default :data:`benchmarks.loop_gap.SEEDS`), ``LOOP_GAP_JOBS`` runs at a
    time; no run starts that would end past ``GPU_RUN_DEADLINE`` (less 30 s)."""
    from benchmarks.backend_agree import parse_seeds
    from benchmarks.loop_gap import JOBS, SEEDS, loop_gap

    if prepared is None:
        raise ValueError("the loop comparison needs a prepared cell (--cell-prepared)")
    seeds = parse_seeds(os.environ["LOOP_GAP_SEEDS"]) if os.environ.get("LOOP_GAP_SEEDS") else list(SEEDS)
    jobs = int(os.environ.get("LOOP_GAP_JOBS", JOBS))
    return loop_gap(prepared, seeds, iterations, jobs, deadline=_run_deadline(float("inf"), 30.0), on_result=on_result)


def backend_agree_part(cell: Path | None, on_result: Callable[[dict], None] | None = None) -> dict:
    """benchmarks/backend_agree.py on the carried grid cell (``--gpu-agree-cell``): gsplat on
    CUDA against the grid's CPU records, the runs of :data:`benchmarks.backend_agree.RUNS` or of
    ``AGREE_SEEDS`` ("0-14") and ``AGREE_RECIPES`` ("sparse,paper")."""
    from benchmarks.backend_agree import RUNS, backend_agree, cell_name, parse_runs
    from experiments.sparse_views.__main__ import RECORDS

    if cell is None:
        raise ValueError("the backend comparison needs a grid cell (--gpu-agree-cell)")
    runs = RUNS
    if os.environ.get("AGREE_SEEDS") or os.environ.get("AGREE_RECIPES"):
        runs = parse_runs(os.environ.get("AGREE_SEEDS", "0-2"), os.environ.get("AGREE_RECIPES", "sparse,paper"))
    end = _run_deadline(float("inf"), 30.0)
    return backend_agree(Path(cell), cell_name(cell), runs=runs, records=RECORDS / "runs", deadline=end,
                         on_result=on_result)


def run_gpu(cell_iterations: int = CELL_ITERATIONS, parts: tuple[str, ...] = PARTS,
            on_part: Callable[[dict], None] | None = None, cell_prepared: Path | None = None,
            stages: Path | None = None, agree_cell: Path | None = None) -> dict:
    """Run the parts on CUDA in the order given (each independent: a failure is recorded as
    ``{"error": ...}``); ``on_part(report)`` after each one (the caller saves it: a run cut off
    by a time limit keeps the parts done). ``workflow_cell`` and ``vggt_cli`` need ``stages``
    (a folder of ``benchmarks/gpu_stages.py prepare``) and are skipped without it."""
    import torch

    if not torch.cuda.is_available():
        raise RuntimeError("no CUDA device")
    from splat_train.render._gsplat_backend import installed_version

    report = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__, "cuda": torch.version.cuda,
              "gsplat": installed_version(), "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S")}
    from benchmarks import gpu_stages

    fns = {"vggt_fixtures": vggt_fixtures, "vggt_chunked": vggt_chunked, "vggt_speed": vggt_speed, "gsplat_build": gsplat_build, "rasterizer_parity": rasterizer_parity,
           "rasterizer_timing": rasterizer_timing,
           "workflow_cell": lambda dev: gpu_stages.workflow_cell(stages, dev),
           "vggt_cli": lambda dev: gpu_stages.vggt_cli(stages, dev),
           "cell": lambda _dev: gpu_cell(cell_iterations, prepared=cell_prepared),
           "native": lambda _dev: native_cell(cell_iterations, cell_prepared),
           "cell_sparse": lambda _dev: gpu_cell(cell_iterations, prepared=cell_prepared, recipe="sparse"),
           "loop_gap": lambda _dev: loop_gap_part(cell_prepared, cell_iterations, on_result=_partial("loop_gap")),
           "profile": lambda _dev: step_profile(cell_prepared),
           "profile_late": lambda _dev: late_step_profile(cell_prepared),
           "step_ab": lambda _dev: step_ab(cell_prepared),
           "vggt_frames": lambda dev: vggt_frames_part(dev, on_result=_partial("vggt_frames")),
           "vggt_many": lambda dev: vggt_many_part(dev, on_result=_partial("vggt_many")),
           "vggt_search": lambda dev: vggt_search_part(dev, on_result=_partial("vggt_search")),
           "backend_agree": lambda _dev: backend_agree_part(agree_cell, on_result=_partial("backend_agree"))}
    unknown = set(parts) - set(fns)
    if unknown:
        raise ValueError(f"unknown parts {sorted(unknown)}; choose from {', '.join(PARTS)}")
    if stages is None:
        parts = tuple(p for p in parts if p not in ("workflow_cell", "vggt_cli"))

    def _partial(name: str) -> Callable[[dict], None]:
        def save(partial: dict) -> None:  # a part that measures in steps keeps each step
            report[name] = dict(partial, partial=True)
            if on_part is not None:
                on_part(report)
        return save
    for name in parts:
        t0 = time.perf_counter()
        try:
            build = None
            if name in GSPLAT_PARTS:
                waited, build = wait_for_gsplat_build(_run_deadline(float("inf"), 30.0))
                if build is not None:
                    report["gsplat_build_background"] = build
            report[name] = fns[name]("cuda")
            if build is not None:
                report[name]["waited_for_build_s"] = waited
        except Exception:  # noqa: BLE001  (record and go on: each part is independent)
            report[name] = {"error": traceback.format_exc()[-3000:]}
        report[name]["part_s"] = time.perf_counter() - t0  # the whole part, setup and scoring included
        print(name, json.dumps(report[name], indent=1, default=str), flush=True)
        if on_part is not None:
            on_part(report)
    return report


def run_cli(out: Path, iterations: int | None = None, machine_info=None, cell_prepared: Path | None = None,
            stages: Path | None = None, parts: tuple[str, ...] = PARTS, agree_cell: Path | None = None) -> int:
    """``python -m benchmarks --gpu``: every part, JSON + Markdown into ``out``, the table printed.
    Exits 2 with a message when torch sees no CUDA device."""
    if not torch.cuda.is_available():
        log.error("python -m benchmarks --gpu needs a CUDA GPU, and torch %s sees none here "
                  "(torch.cuda.is_available() is False). On a GPU machine: install a CUDA build of torch, "
                  "then pip install -e '.[gpu]' (README, 'GPU install').", torch.__version__)
        return 2
    from runtime.atomic import write_json

    stem = out / f"benchmarks_gpu_{time.strftime('%Y%m%d_%H%M%S')}"
    machine = machine_info() if machine_info is not None else None

    def save(report: dict) -> str:  # after every part, so a run cut short keeps what it measured
        if machine is not None:
            report["machine"] = machine
        write_json(stem.with_suffix(".json"), report)
        table = format_gpu_table(report)
        stem.with_suffix(".md").write_text(table + "\n")
        return table

    report = run_gpu(iterations or CELL_ITERATIONS, parts, on_part=save, cell_prepared=cell_prepared, stages=stages,
                     agree_cell=agree_cell)
    table = save(report)
    print(table)
    log.info("saved %s.json and %s.md", stem, stem)
    return 0


def main() -> int:
    from runtime.cliargs import plain

    p = argparse.ArgumentParser(description=plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
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
