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
    r = vggt_frames("cpu", time.perf_counter() + 120, counts=(3, 2), config=_cfg(), width=56, height=42,
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
    r = vggt_frames("cpu", time.perf_counter() + 60, counts=(2, 3), config=_cfg(), width=56, height=42,
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
