"""benchmarks/vggt_frames.py on the CPU with the fixtures' tiny model (the GPU check runs VGGT-1B).

On the CPU the peak is the live tensor bytes seen by ``LiveTensorBytes`` plus weights and input;
the probe must allocate as the real forward does (peaks equal) and give outputs of the same shapes.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import torch

from benchmarks.vggt_frames import LiveTensorBytes, UPSTREAM, WEIGHTS, vggt_frames
from vggt_init.model import VGGTConfig, fastpath

CFG = Path(__file__).parent / "data" / "vggt" / "shared" / "config.json"


def _cfg() -> VGGTConfig:
    return VGGTConfig.from_fixture_config(json.loads(CFG.read_text()))


@pytest.fixture
def aten_attention():
    """The ATen SDPA path (what CUDA takes), whose allocations the probe mirrors."""
    previous = fastpath.set_fast_paths(False)
    yield
    fastpath.set_fast_paths(previous)


def test_vggt_frames_cpu_structure(aten_attention):
    seen = []
    r = vggt_frames("cpu", time.perf_counter() + 600, counts=(3, 2), config=_cfg(), width=56, height=42,
                    search_from=4, search_step=2, search_max=5, bigger=(4, 6),
                    on_result=lambda d: seen.append(json.loads(json.dumps(d))))
    assert r["weights"] == WEIGHTS == "RANDOM (speed and memory only)"
    assert r["upstream"] == UPSTREAM and r["upstream"]["frames"] == 1000
    assert r["size"] == "56x42" and r["heads"] == "camera,point" and not r["stopped_at_deadline"]
    real = [x for x in r["real"] if not x.get("extra")]
    assert [x["frames"] for x in real] == [2, 3] and [x["frames"] for x in r["probe"]] == [2, 3]
    for x in real:
        assert len(x["wall_s_runs"]) == 3 and x["wall_s"] > 0 and x["s_per_frame"] == pytest.approx(x["wall_s"] / x["frames"])
        assert set(x["timings_s"]) == {"aggregator", "camera_head", "point_head"}
        assert x["output_shapes"]["world_points"] == [1, x["frames"], 42, 56, 3]
    for p, x in zip(r["probe"], real):
        assert p["output_shapes_match_real"] and p["output_shapes"] == x["output_shapes"]
        assert p["output_dtypes"] == x["output_dtypes"]
        assert p["peak_ratio_probe_to_real"] == pytest.approx(1.0, abs=0.02)
    assert r["memory_meter"].startswith("live tensor bytes")
    assert real[1]["peak_mb"] > real[0]["peak_mb"] > r["weights_mb"] > 0
    fm = r["fit_memory"]
    assert fm["mb_per_frame"] == pytest.approx(real[1]["peak_mb"] - real[0]["peak_mb"])
    assert r["fit_time"]["degree"] == 1  # two real counts: a line
    # the capped search: 4 fits, 6 beyond the cap is not tried; then one real run at 4 (6 > largest fit)
    assert [t["frames"] for t in r["search"]["tries"]] == [4] and r["search"]["largest_fit_frames"] == 4
    extra = [x for x in r["real"] if x.get("extra")]
    assert [x["frames"] for x in extra] == [4] and extra[0]["predicted_s"] is not None
    assert r["real_frames"] == [2, 3, 4] and r["probe_only_frames"] == []
    assert r["predicted_s_at_largest_fit"] is not None
    assert len(seen) >= 6 and seen[-1]["real_frames"] == [2, 3, 4]


def test_vggt_frames_past_deadline_stops_early():
    r = vggt_frames("cpu", time.perf_counter() - 1.0, counts=(2, 3), config=_cfg(), width=56, height=42)
    assert r["stopped_at_deadline"] and r["real"] == [] and r["probe"] == [] and r["search"]["tries"] == []
    assert r["weights"] == WEIGHTS


def test_live_tensor_bytes_counts_storages_once():
    with torch.inference_mode(), LiveTensorBytes() as t:
        a = torch.empty(1000, dtype=torch.float32)
        view = a[10:20]
        del a  # the view keeps the storage
        assert t.now == 4000
        b = torch.ones(500, dtype=torch.float64)
        assert t.peak == 8000
        del view, b
        assert t.now == 0 and t.peak == 8000


def test_vggt_frames_search_finds_the_largest_count(monkeypatch):
    """Up in doubling steps until out of memory, then bisection; out-of-memory errors are caught
    and the run goes on (the forward is a stand-in above the measured counts: the search's logic)."""
    from benchmarks import vggt_frames as vf

    real_run = vf._Meter.run

    def run(self, n, size, probe):
        if n <= 3:
            return real_run(self, n, size, probe)
        if n > 9:
            raise torch.OutOfMemoryError("stand-in")
        return {"frames": n, "wall_s": 0.01, "peak_mb": float(n), "timings_s": {}, "output_shapes": {},
                "output_dtypes": {}}

    monkeypatch.setattr(vf._Meter, "run", run)
    r = vggt_frames("cpu", time.perf_counter() + 600, counts=(2, 3), config=_cfg(), width=56, height=42,
                    search_from=4, search_step=2, search_resolution=1, search_max=100, bigger=(12, 9))
    tries = [(t["frames"], t["fits"]) for t in r["search"]["tries"]]
    assert tries == [(4, True), (6, True), (10, False), (8, True), (9, True)]
    assert r["search"]["largest_fit_frames"] == 9 and r["search"]["first_oom_frames"] == 10
    assert r["probe_only_frames"] == [4, 6, 8] and 9 in r["real_frames"]  # the larger real run: 9 (12 does not fit)
    assert [x["frames"] for x in r["real"] if x.get("extra")] == [9]


def test_cli_without_cuda_exits_2(capsys):
    from benchmarks.vggt_frames import main

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    assert main(["--minutes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "CUDA" in err


def test_vggt_frames_cuda_branch_with_stand_ins(monkeypatch):
    """Every CUDA line of the benchmark (allocator statistics, the prediction-led search, the
    larger real run) runs here with torch.cuda stood in for: a peak of 100 + 10 n MiB and room
    for 9.5 frames, n > 9 frames out of memory inside the forward."""
    from benchmarks import vggt_frames as vf

    state = {"n": 0}
    build = vf._build

    def build_hooked(device, config):
        model = build("cpu", config)

        def pre(_m, args, kwargs):
            n = args[0].shape[1]
            state["n"] = n
            if n > 9:
                raise torch.OutOfMemoryError("stand-in")

        model.register_forward_pre_hook(pre, with_kwargs=True)
        return model

    calls = []
    mib = 2 ** 20
    fake = {"synchronize": lambda *a: calls.append("sync"), "reset_peak_memory_stats": lambda *a: calls.append("reset"),
            "max_memory_allocated": lambda *a: (100 + 10 * state["n"]) * mib, "empty_cache": lambda: calls.append("empty"),
            "mem_get_info": lambda *a: (int(150 * mib), int(80 * 1024 * mib)), "memory_reserved": lambda *a: int(45 * mib),
            "get_device_name": lambda *a: "stand-in GPU"}
    for name, fn in fake.items():
        monkeypatch.setattr(torch.cuda, name, fn)
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda *a: type("P", (), {"total_memory": 80 * 1024 * mib})())
    monkeypatch.setattr(vf, "_is_cuda", lambda device: True)
    monkeypatch.setattr(vf, "_build", build_hooked)
    r = vggt_frames("cpu", time.perf_counter() + 600, counts=(2, 3), config=_cfg(), width=56, height=42,
                    search_resolution=1, bigger=(12, 9))
    assert r["device_name"] == "stand-in GPU" and r["memory_meter"].startswith("torch.cuda.max_memory_allocated")
    assert r["fit_memory"]["intercept_mb"] == pytest.approx(100) and r["fit_memory"]["mb_per_frame"] == pytest.approx(10)
    assert [p["peak_ratio_probe_to_real"] for p in r["probe"]] == [1.0, 1.0]
    s = r["search"]
    assert s["capacity_mb"] == pytest.approx(195) and s["predicted_fit_frames"] == pytest.approx(9.5)
    assert s["start_frames"] == 9
    assert [(t["frames"], t["fits"]) for t in s["tries"]] == [(9, True), (11, False), (10, False)]
    assert s["largest_fit_frames"] == 9 and s["first_oom_frames"] == 10 and s["largest_fit_peak_mb"] == pytest.approx(190)
    extra = [x for x in r["real"] if x.get("extra")]
    assert [x["frames"] for x in extra] == [9] and not extra[0]["oom"]
    assert r["real_frames"] == [2, 3, 9] and r["probe_only_frames"] == []
    assert "reset" in calls and "empty" in calls and "sync" in calls


def test_vggt_frames_records_failures_and_goes_on(monkeypatch):
    """A library's allocation failure counts as out of memory; any other error is recorded with
    its message, the counts after it are not run for real, and the probe still runs."""
    from benchmarks import vggt_frames as vf

    real_run = vf._Meter.run

    def run(self, n, size, probe):
        if n == 3 and not probe:
            raise RuntimeError("CUDA error: an illegal stand-in")
        if n == 3 and probe:
            raise RuntimeError("CUBLAS_STATUS_ALLOC_FAILED when calling cublasCreate(handle)")
        return real_run(self, n, size, probe)

    monkeypatch.setattr(vf._Meter, "run", run)
    r = vggt_frames("cpu", time.perf_counter() + 600, counts=(2, 3, 4), config=_cfg(), width=56, height=42, bigger=())
    assert [(x["frames"], x["oom"], "error" in x) for x in r["real"]] == [(2, False, False), (3, False, True)]
    assert "illegal stand-in" in r["real"][1]["error"]
    assert [(x["frames"], x["oom"]) for x in r["probe"]] == [(2, False), (3, True), (4, False)]
    assert r["real_frames"] == [2] and r["probe_only_frames"] == [4]
    assert r["fit_memory"] is None and r["fit_memory_probe"]["points"] == 2


def test_vggt_frames_search_bisects_below_a_start_that_does_not_fit(monkeypatch):
    """A start beyond the limit (the linear law overshooting, as on the H100): bisection between
    the largest count known to fit and the start, each failure recorded with its message."""
    from benchmarks import vggt_frames as vf

    real_run = vf._Meter.run

    def run(self, n, size, probe):
        if n <= 3:
            return real_run(self, n, size, probe)
        if n > 9:
            raise torch.OutOfMemoryError(f"stand-in: {n} frames")
        return {"frames": n, "wall_s": 0.01, "peak_mb": float(n), "timings_s": {}, "output_shapes": {},
                "output_dtypes": {}}

    monkeypatch.setattr(vf._Meter, "run", run)
    r = vggt_frames("cpu", time.perf_counter() + 600, counts=(2, 3), config=_cfg(), width=56, height=42,
                    search_from=20, search_step=2, search_resolution=1, search_max=100, bigger=())
    tries = r["search"]["tries"]
    assert [(t["frames"], t["fits"]) for t in tries] == [(20, False), (11, False), (7, True), (9, True), (10, False)]
    assert r["search"]["largest_fit_frames"] == 9 and r["search"]["first_oom_frames"] == 10
    assert tries[0]["message"] == "stand-in: 20 frames" and tries[0]["wall_s"] >= 0
