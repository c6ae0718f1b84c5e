"""``python -m benchmarks``: quick smoke run of all sections, the JSON record, --compare, and
sections that are missing are reported as missing (never filled with numbers).

The quick run uses tiny sizes (a few seconds of CPU on an idle 2-core machine; the wall time
grows with the machine's load). It needs no real scene: the cell uses the synthetic scene.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import benchmarks.__main__ as agg
from benchmarks import bench_cell


def _fake(raster_s: float, vggt_s: float, train_ips: float, commit: str) -> dict:
    return {
        "timestamp": "t", "machine": {"git_commit": commit, "loadavg_start": [1.0, 1.0, 1.0]},
        "sections": {
            "raster": {"runs": [{"backend": "cpu", "threads": 2, "n": 10, "width": 8, "height": 8,
                                 "fwd_bwd_s": raster_s, "blended_pairs_per_s": 100.0 / raster_s}]},
            "vggt": {"runs": [{"frames": 3, "dtype": "bf16", "forward_s": vggt_s}]},
            "cell": {"stages_s": {"train": 1000 / train_ips}, "train": {"it_per_s": train_ips}, "cell_total_s": 50.0},
        },
    }


def test_quick_run_writes_json_and_table(tmp_path, capsys):
    rc = agg.main(["--quick", "--only", "raster,vggt,cell", "--vggt-frames", "2", "--out", str(tmp_path)])
    assert rc == 0
    files = list(tmp_path.glob("benchmarks_*_quick.json"))
    assert len(files) == 1
    res = json.loads(files[0].read_text())
    m = res["machine"]
    assert m["cpu_count"] >= 1 and m["torch"] and m["torch_threads"] >= 1 and len(m["loadavg_start"]) == 3
    assert "git_commit" in m and len(res["loadavg_end"]) == 3 and res["quick"] is True
    sec = res["sections"]
    for name in ("raster", "vggt", "cell"):
        assert "error" not in sec[name], (name, sec[name].get("error"))
    # rasterizer: the fast path and the dense reference on the same case, and a speed-up
    backends = {r["backend"] for r in sec["raster"]["runs"]}
    assert "reference" in backends and len(backends) >= 2
    assert all(r["fwd_bwd_s"] > 0 for r in sec["raster"]["runs"])
    speed = next(iter(sec["raster"]["speedup_vs_reference"].values()))
    assert all(v > 0 for k, v in speed.items() if k != "case")
    # VGGT: fp32 and bf16 rows for the requested frame count, labelled random weights
    rows = {(r["frames"], r["dtype"]) for r in sec["vggt"]["runs"]}
    assert rows == {(2, "fp32"), (2, "bf16")}
    assert "RANDOM" in sec["vggt"]["weights"]
    # cell: every stage timed, training rate and final Gaussian count from train.json
    cell = sec["cell"]
    for stage in ("prep", "init_oracle", "bridge", "align", "train", "render", "metrics"):
        assert cell["stages_s"][stage] > 0, stage
    assert cell["init_used"] == "oracle" and cell["iterations"] == bench_cell.QUICK_ITERATIONS
    assert cell["train"]["it_per_s"] > 0 and cell["train"]["final_gaussians"] > 0
    assert math.isfinite(cell["metrics"]["psnr"])
    assert cell["cell_total_s"] <= sum(cell["stages_s"].values()) + 1e-9
    assert cell["loadavg_during"]["samples"] >= 2 and len(cell["loadavg_start"]) == 3
    table = capsys.readouterr().out
    for heading in ("## Rasterizer", "## VGGT forward, RANDOM weights", "## Pipeline cell", "cell total"):
        assert heading in table
    # comparing a run with itself gives ratio 1 for every quantity
    text = agg.compare(res, res)
    ratios = [float(line.rsplit("|", 2)[-2]) for line in text.splitlines()[3:] if line.startswith("| ")]
    assert ratios and all(r == pytest.approx(1.0) for r in ratios)


def test_compare_ratios_and_cli(tmp_path, capsys):
    old, new = _fake(2.0, 10.0, 4.0, "aaa"), _fake(1.0, 6.0, 8.0, "bbb")
    a, b = tmp_path / "old.json", tmp_path / "new.json"
    a.write_text(json.dumps(old))
    b.write_text(json.dumps(new))
    assert agg.main(["--compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    rows = {line.split("|")[1].strip(): float(line.split("|")[4]) for line in out.splitlines()
            if line.startswith("| ") and not line.startswith("| quantity")}
    assert rows["raster cpu t2 N=10 8x8 fwd_bwd_s"] == pytest.approx(0.5)
    assert rows["raster cpu t2 N=10 8x8 pairs_per_s"] == pytest.approx(2.0)
    assert rows["vggt n=3 bf16 forward_s"] == pytest.approx(0.6)
    assert rows["cell train it_per_s"] == pytest.approx(2.0)
    assert rows["cell train s"] == pytest.approx(0.5)
    assert "aaa" in out and "bbb" in out
    # a bench_cell JSON (no "sections") is read as the cell section
    text = agg.compare(old["sections"]["cell"], new["sections"]["cell"])
    assert "| cell train it_per_s | 4 | 8 | 2.000 |" in text
    with pytest.raises(ValueError, match="not a benchmark result"):
        agg.flatten({"foo": 1})


def test_missing_vggt_benchmark_is_reported_not_invented(tmp_path, monkeypatch):
    monkeypatch.setattr(agg, "HERE", tmp_path)  # a benchmarks folder without bench_vggt.py
    sec = agg.vggt_section(quick=False, threads=1, frames=[3])
    assert "error" in sec and "bench_vggt.py" in sec["error"] and "runs" not in sec
    monkeypatch.setattr(bench_cell, "HERE", tmp_path)
    row = bench_cell.vggt_random_forward(3)
    assert "error" in row and "forward_s" not in row
    res = {"timestamp": "t", "quick": False, "machine": agg.machine_info(), "sections": {"vggt": sec},
           "loadavg_end": [0.0, 0.0, 0.0], "wall_s": 0.0}
    table = agg.format_table(res)
    assert "missing" in table and "bf16/fp32" not in table
    assert not any(k.startswith("vggt") for k in agg.flatten(res))


def test_bad_section_name_is_an_error(capsys):
    with pytest.raises(SystemExit):
        agg.main(["--only", "raster,gpu"])
    assert "unknown sections ['gpu']" in capsys.readouterr().err
