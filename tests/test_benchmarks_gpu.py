"""``python -m benchmarks --gpu`` without a GPU: --help works, the run exits 2 with a message;
the report plumbing (JSON + Markdown, failed parts recorded) with the CUDA parts stubbed; the
cell passes --device and --rasterizer to training and records them (on CPU, quick sizes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from benchmarks import bench_cell, gpu_check

REPO = Path(__file__).resolve().parents[1]


def test_gpu_help_works_anywhere():
    proc = subprocess.run([sys.executable, "-m", "benchmarks", "--gpu", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "--gpu" in proc.stdout and "gsplat" in proc.stdout


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-GPU message")
def test_gpu_without_cuda_exits_with_message(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "benchmarks", "--gpu", "--out", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "needs a CUDA GPU" in proc.stderr and ".[gpu]" in proc.stderr
    assert not list(tmp_path.iterdir())  # nothing written


def test_gpu_report_json_and_table(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "Fake GPU")
    monkeypatch.setattr(gpu_check, "vggt_fixtures", lambda dev: {
        "tf32_off": {"float64": {"max": 1e-12}, "float32": {"max": 2e-5}},
        "tf32_on": {"float64": {"max": 1e-12}, "float32": {"max": 2e-3}}})
    monkeypatch.setattr(gpu_check, "gsplat_build", lambda dev: {"load_or_build_s": 89.0, "arch_list": "9.0"})
    monkeypatch.setattr(gpu_check, "rasterizer_parity", lambda dev: 1 / 0)
    monkeypatch.setattr(gpu_check, "rasterizer_timing", lambda dev: {
        "torch": {"fwd_bwd_ms": 50.0, "peak_gpu_mb": 900.0}, "gsplat": {"fwd_bwd_ms": 5.0, "peak_gpu_mb": 300.0},
        "speedup_gsplat": 10.0, "case": "c"})
    monkeypatch.setattr(gpu_check, "gpu_cell", lambda iterations, prepared=None, recipe="paper": {
        "scene": "fern", "n": 3, "iterations": iterations, "cell_total_s": 100.0,
        "stages_s": {"train": 60.0, "render": 1.0, "metrics": 2.0}, "metrics": {"psnr": 20.1, "ssim": 0.6},
        "train": {"rasterizer": "gsplat", "device": "cuda", "wall_s": 60.0 if recipe == "paper" else 30.0,
                  "it_per_s": 166.0, "peak_cuda_mb": 1234.0, "final_gaussians": 10, "test_psnr": 20.0,
                  "recipe": recipe}})
    monkeypatch.setattr(gpu_check, "native_cell", lambda iterations, prepared: {
        "iterations": iterations, "wall_s": 50.0, "s_per_1000_it": 5.0, "final_gaussians": 12, "test_psnr": 19.9,
        "peak_cuda_mb": 900.0})
    monkeypatch.setattr(gpu_check, "vggt_frames_part", lambda dev, on_result=None: {"frames": []})
    assert gpu_check.run_cli(tmp_path, 7) == 0
    (js,), (md,) = tmp_path.glob("benchmarks_gpu_*.json"), tmp_path.glob("benchmarks_gpu_*.md")
    rep = json.loads(js.read_text())
    assert rep["cell"]["iterations"] == 7 and "ZeroDivisionError" in rep["rasterizer_parity"]["error"]
    table = md.read_text()
    assert "| cell: peak GPU MB (training) | 1234 |" in table
    assert "rasterizer_parity: FAILED" in table and "gsplat on cuda" in table
    assert "| ours / gsplat-native training time | 1.20 |" in table  # 60 s / 50 s
    assert "| cell, sparse: train s (it/s) | 30.0 (166.0) |" in table
    assert "workflow_cell" not in rep and "vggt_cli" not in rep  # no --stages folder: skipped
    assert table in capsys.readouterr().out


def test_gpu_report_saved_after_each_part(tmp_path, monkeypatch):
    """A run killed in a later part (the device's time limit) leaves the parts done on disk."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "Fake GPU")
    monkeypatch.setattr(gpu_check, "vggt_fixtures", lambda dev: {
        "tf32_off": {"float64": {"max": 1e-12}, "float32": {"max": 2e-5}},
        "tf32_on": {"float64": {"max": 1e-12}, "float32": {"max": 2e-3}}})
    monkeypatch.setattr(gpu_check, "gsplat_build", lambda dev: {"load_or_build_s": 89.0, "arch_list": "9.0"})
    monkeypatch.setattr(gpu_check, "rasterizer_parity", lambda dev: {"rgb_max_abs_diff": 1e-3})

    def killed(dev):
        raise KeyboardInterrupt  # not an Exception: like SIGTERM's kill, the run stops here

    monkeypatch.setattr(gpu_check, "rasterizer_timing", killed)
    with pytest.raises(KeyboardInterrupt):
        gpu_check.run_cli(tmp_path, 7)
    (js,), (md,) = tmp_path.glob("benchmarks_gpu_*.json"), tmp_path.glob("benchmarks_gpu_*.md")
    rep = json.loads(js.read_text())
    assert rep["vggt_fixtures"]["tf32_off"]["float64"]["max"] == 1e-12 and rep["rasterizer_parity"]["rgb_max_abs_diff"] == 1e-3
    assert "rasterizer_timing" not in rep and "VGGT fixtures on CUDA, float32, tf32 on" in md.read_text()


def test_gsplat_parts_wait_for_the_background_build(tmp_path, monkeypatch):
    """With gpu_run.sh's background JIT build (GSPLAT_BUILD_MARKER), a part that imports gsplat
    starts only once the build's marker exists, and a failed build fails those parts with its
    error instead of letting them import a half-built extension; VGGT parts do not wait."""
    import threading

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "Fake GPU")
    marker = tmp_path / "build.json"
    monkeypatch.setenv("GSPLAT_BUILD_MARKER", str(marker))
    seen = {}

    def vggt(dev, on_result=None):
        seen["vggt"] = marker.exists()
        return {}

    def cell(iterations, prepared=None, recipe="paper"):
        seen["cell"] = marker.exists()
        return {"ok": 1}

    monkeypatch.setattr(gpu_check, "vggt_frames_part", vggt)
    monkeypatch.setattr(gpu_check, "gpu_cell", cell)
    timer = threading.Timer(1.5, lambda: marker.write_text(json.dumps({"load_or_build_s": 80.0})))
    timer.start()
    rep = gpu_check.run_gpu(parts=("vggt_frames", "cell_sparse"))
    timer.join()
    assert seen == {"vggt": False, "cell": True}
    assert rep["cell_sparse"]["ok"] == 1 and rep["cell_sparse"]["waited_for_build_s"] > 1.0
    assert rep["gsplat_build_background"] == {"load_or_build_s": 80.0} and "waited_for_build_s" not in rep["vggt_frames"]
    marker.write_text(json.dumps({"error": "nvcc failed"}))
    seen.clear()
    rep = gpu_check.run_gpu(parts=("cell",))
    assert "nvcc failed" in rep["cell"]["error"] and "cell" not in seen


def test_cell_passes_device_and_rasterizer_to_training(tmp_path):
    res = bench_cell.run_cell(tmp_path, "synthetic", 3, bench_cell.QUICK_ITERATIONS, quick=True, vggt=False,
                              inprocess=True, device="cpu", rasterizer="torch")
    assert res["train"]["rasterizer"] == "torch" and res["train"]["device"] == "cpu"
    assert res["train"]["peak_cuda_mb"] is None


def test_cell_from_prepared_bundle(tmp_path):
    """--prepare-only keeps what training, render and metrics read (images copied, no links);
    --prepared runs those three from it and reports the prepared stages' times and origin."""
    bundle = tmp_path / "bundle"
    assert bench_cell.main(["--prepare-only", str(bundle), "--scene", "synthetic", "--quick", "--inprocess"]) == 0
    state = json.loads((bundle / bench_cell.PREPARED_FILE).read_text())
    assert state["used"] == "oracle" and {"prep", "bridge", "align"} <= set(state["stages_s"])
    files = [p for p in bundle.rglob("*") if not p.is_dir()]
    assert not any(p.is_symlink() for p in files)
    assert len(list((bundle / "scene" / "images").iterdir())) == 3  # the n = 3 training images only
    with pytest.raises(FileExistsError):
        bench_cell.prepare_bundle(bundle, "synthetic", 3, quick=True, inprocess=True)
    res = bench_cell.run_cell(tmp_path / "work", "synthetic", 3, bench_cell.QUICK_ITERATIONS, quick=True, vggt=False,
                              inprocess=True, device="cpu", rasterizer="torch", prepared=bundle)
    assert res["prepared"]["stages"] == sorted(state["stages_s"]) and res["train"]["device"] == "cpu"
    assert set(res["stages_s"]) >= {"prep", "align", "train", "render", "metrics"}
    assert res["metrics"]["n_images"] == len(list((bundle / "test_images").iterdir())) > 0
    assert res["image_size"] == state["image_size"]


@pytest.fixture(scope="module")
def quick_bundle(tmp_path_factory):
    bundle = tmp_path_factory.mktemp("native") / "bundle"
    assert bench_cell.main(["--prepare-only", str(bundle), "--scene", "synthetic", "--quick", "--inprocess"]) == 0
    return bundle


def test_gsplat_native_loop_runs_gsplats_strategy(quick_bundle, monkeypatch):
    """benchmarks/gsplat_native.py on the CPU stand-in of gsplat.rasterization (tests/_fake_gsplat.py):
    gsplat's DefaultStrategy grows and prunes through it with the paper recipe's schedule,
    and the held-out PSNR is scored."""
    pytest.importorskip("gsplat")
    import _fake_gsplat
    from benchmarks import gsplat_native
    from camio.ply import read_gaussian_ply
    from splat_train.config import TrainConfig

    monkeypatch.setattr(gsplat_native, "_rasterization", lambda: _fake_gsplat.rasterization)
    res = gsplat_native.train_native(quick_bundle, 40, device="cpu", densify_every=10)
    seed = len(read_gaussian_ply(quick_bundle / "bridge" / "seed.ply"))
    assert res["iterations"] == 40 and res["final_gaussians"] > seed  # the strategy grew the model
    assert res["schedule"] == TrainConfig(recipe="paper", iterations=40, densify_every=10).schedule().to_dict()
    assert 5.0 < res["test_psnr"] < 60.0 and res["peak_cuda_mb"] is None


@pytest.mark.slow
def test_gpu_stages_reproduce_the_workflow_cell_on_cpu(tmp_path):
    """gpu_stages.prepare runs the cell with snakemake; its stage commands, run again on the
    CPU, give the workflow's held-out numbers exactly (the same commands the GPU runs with
    --device cuda), and vggt_init on the fixture model matches itself."""
    from benchmarks import gpu_stages

    folder = gpu_stages.prepare(tmp_path / "wf", tmp_path / "results")
    cpu = json.loads((folder / gpu_stages.CPU_FILE).read_text())
    assert cpu["train"]["config"]["iterations"] == 300 and cpu["metrics"]["n_images"] > 0
    res = gpu_stages.workflow_cell(folder, "cpu")
    assert res["psnr_device_minus_cpu"] == 0.0 and res["ssim_device_minus_cpu"] == 0.0
    assert res["device_run"]["train"]["num_gaussians"] == cpu["train"]["num_gaussians"]
    v = gpu_stages.vggt_cli(folder, "cpu")
    assert v["names_equal"] and max(v["max_abs_diff_vs_cpu"].values()) == 0.0


def _cpu_stand_ins(monkeypatch):
    """CUDA events and synchronisation stood in for on the CPU, and the profile's trainers made
    on the CPU (the step's own code runs unchanged; the loss is never a CUDA graph there)."""
    from benchmarks import profile_step

    class Event:
        def __init__(self, enable_timing: bool = False) -> None:
            self.t = None

        def record(self) -> None:
            import time

            self.t = time.perf_counter()

        def elapsed_time(self, end: "Event") -> float:
            return 1e3 * (end.t - self.t)

    monkeypatch.setattr(torch.cuda, "Event", Event)
    monkeypatch.setattr(torch.cuda, "synchronize", lambda *a, **k: None)
    real = profile_step.cell_trainer
    monkeypatch.setattr(profile_step, "cell_trainer",
                        lambda cell, recipe, device="cuda", graphs=None, **o: real(cell, recipe, "cpu", graphs, **o))
    return profile_step


def test_step_profile_parts_and_report(quick_bundle, monkeypatch):
    """The GPU step profile's plumbing on the CPU (benchmarks/profile_step.py): per recipe the
    plain loop with the loss graphed and not, every phase timed, the rasterizer alone and the
    torch.profiler counts; the recipes in turns in one process; the table rows of both."""
    profile_step = _cpu_stand_ins(monkeypatch)
    from benchmarks.profile_iteration import PHASES

    prof = profile_step.profile(quick_bundle, ("paper", "sparse"), warm=3, steps=2, profile_steps=1)
    for recipe in ("paper", "sparse"):
        p = prof[recipe]
        assert p["graphs_on"]["loss_graphed"] is False  # never a CUDA graph off CUDA
        assert p["ms_per_step"] == p["graphs_on"]["ms_per_step"] > 0
        assert set(p["phases"]["host_ms"]) == set(PHASES) and p["phases"]["host_ms"]["render"] > 0
        assert p["rasterizer_only_ms"] > 0 and p["torch_profiler"]["iterations"] == 1
        assert p["torch_profiler"]["top_host"] and isinstance(p["host_bound"], bool)
    ab = profile_step.recipe_ab(quick_bundle, rounds=2, warm=2, steps=2)
    assert set(ab) == set(profile_step.AB_VARIANTS) | {"setup"}
    assert all(len(ab[k]["ms_per_step"]) == 2 and ab[k]["median_ms"] > 0 for k in profile_step.AB_VARIANTS)
    assert ab["sparse_no_dropout"]["config"] == {"recipe": "sparse", "dropout_rate": 0.0}
    table = gpu_check.format_gpu_table({"profile": prof, "step_ab": ab})
    assert "step profile, sparse: host ms per phase | render" in table
    assert "| step A/B in one process (paper, sparse, sparse_no_dropout, sparse_no_opacity_reg, sparse_no_depth)" in table


def test_late_step_profile_times_statistics_off_and_on(quick_bundle, monkeypatch):
    """The late-run profile's plumbing on the CPU, through gsplat's CPU stand-in: past the
    sparse recipe's growth the trainer reads no statistics; both variants are timed in turns,
    the tile footprint comes from gsplat's own intersections, and the table shows them."""
    pytest.importorskip("gsplat")
    import _fake_gsplat
    from splat_train.render import _gsplat_backend

    profile_step = _cpu_stand_ins(monkeypatch)
    monkeypatch.setattr(_gsplat_backend, "_rasterization", lambda: _fake_gsplat.rasterization)
    real = profile_step.cell_trainer
    monkeypatch.setattr(profile_step, "cell_trainer",
                        lambda cell, recipe, **o: real(cell, recipe, densify_until=3, rasterizer="gsplat", **o))
    prof = profile_step.late_profile(quick_bundle, ("sparse",), warm=4, steps=2, rounds=2, profile_steps=1)
    p = prof["sparse"]
    assert p["stats_read_after_warm"] is False
    # the Bridge's depth prior beside the seed is used, as the training command uses it
    assert (quick_bundle / "bridge" / "depth_prior.npz").is_file() and "depth_prior" in p["parts"]
    assert len(p["ms_per_step"]["stats_skipped"]) == len(p["ms_per_step"]["stats_computed"]) == 2
    fp = p["footprint"]
    assert 0 < fp["visible"] <= fp["gaussians"] and fp["tile_intersections"] >= fp["visible"]
    table = gpu_check.format_gpu_table({"profile_late": prof})
    assert "late step, sparse, after 4 it" in table and "statistics skipped / computed" in table


def test_gpu_scripts_refuse_a_folder_that_is_not_a_prepared_cell(tmp_path, monkeypatch, quick_bundle):
    """gsplat_native.py and profile_step.py say in one line what is missing (CUDA, or a cell
    made by bench_cell.py --prepare-only) and write their JSON only where --out says."""
    from benchmarks.gsplat_native import emit, preflight

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert preflight(quick_bundle, "x") == "x: needs a CUDA GPU"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    msg = preflight(tmp_path, "profile_step")
    assert msg.startswith(f"profile_step: {tmp_path} is not a prepared cell") and "\n" not in msg
    assert preflight(quick_bundle, "x") is None
    emit({"a": 1.5}, tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": 1.5}
