"""benchmarks/loop_gap.py: the comparison of `paper` and gsplat's own loop over many seeds.

gsplat's loop needs CUDA, so the runs here are the trainer's (``ours``) on the CPU kernel, a
few iterations on the quick synthetic cell: what is checked is what a GPU run relies on
(processes side by side, every run recorded or its failure named, the deadline, the summary,
the GPU table's rows); the native loop itself is tested on gsplat's CPU stand-in in
tests/test_benchmarks_gpu.py.
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
import pytest

from benchmarks import bench_cell, gpu_check, loop_gap


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    bundle = tmp_path_factory.mktemp("loop_gap") / "bundle"
    assert bench_cell.main(["--prepare-only", str(bundle), "--scene", "synthetic", "--quick", "--inprocess"]) == 0
    return bundle


def test_runs_side_by_side_and_summarises(cell):
    seen = []
    res = loop_gap.loop_gap(cell, [0, 1], iterations=20, jobs=2, device="cpu", rasterizer="cpu", loops=("ours",),
                            on_result=lambda r: seen.append(len(r["runs"])))
    runs = sorted(res["runs"], key=lambda r: r["seed"])
    assert [r["seed"] for r in runs] == [0, 1] and seen == [1, 2] and not res["stopped_at_deadline"]
    assert all("error" not in r and math.isfinite(r["psnr"]) and r["gaussians"] > 0 for r in runs), runs
    first, second = sorted(runs, key=lambda r: r["start_s"])
    assert second["start_s"] < first["start_s"] + first["wall_s"]  # two at a time: the second began before the first ended
    s = res["summary"]["ours"]
    assert s["seeds"] == [0, 1] and s["psnr"] == pytest.approx(statistics.mean(r["psnr"] for r in runs), abs=1e-12)
    assert "ours_minus_native" not in res["summary"]  # one loop ran: no difference to state


def test_a_failed_run_is_recorded_with_its_log(cell):
    res = loop_gap.loop_gap(cell, [3], iterations=5, jobs=1, device="cpu", rasterizer="no-such-backend", loops=("ours",))
    (run,) = res["runs"]
    assert run["seed"] == 3 and run["error"].startswith("exit ") and "no-such-backend" in run["error"]
    assert res["summary"] == {}


def test_no_run_starts_past_the_deadline(cell):
    res = loop_gap.loop_gap(cell, [0, 1], iterations=5, device="cpu", rasterizer="cpu", deadline=time.time() + 1.0)
    assert res["runs"] == [] and res["stopped_at_deadline"]


def test_summary_of_two_loops_is_welchs_difference_of_means():
    ours, native = [10.1, 10.9, 10.4, 10.6], [11.2, 11.0, 11.9]
    runs = ([{"loop": "ours", "seed": i, "psnr": v, "gaussians": 100 + i, "train_s": 60.0} for i, v in enumerate(ours)]
            + [{"loop": "native", "seed": i, "psnr": v, "gaussians": 200, "train_s": 70.0} for i, v in enumerate(native)]
            + [{"loop": "native", "seed": 9, "error": "exit 1: out of memory"}])
    s = loop_gap.summarise(runs)
    a, b = np.asarray(ours, np.float64), np.asarray(native, np.float64)
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    df = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    from scipy.stats import t

    d = s["ours_minus_native"]
    assert d["psnr"] == pytest.approx(a.mean() - b.mean(), abs=1e-12) and d["df"] == pytest.approx(df, rel=1e-12)
    assert d["hw95"] == pytest.approx(t.ppf(0.975, df) * math.sqrt(va + vb), rel=1e-12)
    assert s["native"]["seeds"] == [0, 1, 2] and s["ours"]["psnr_sd"] == pytest.approx(a.std(ddof=1), rel=1e-12)
    table = gpu_check.format_gpu_table({"loop_gap": {"iterations": 10000, "jobs": 8, "summary": s}})
    assert "ours 10.50" in table and "native 11.37" in table and f"{d['psnr']:+.2f} ± {d['hw95']:.2f} dB" in table


def test_commands_name_the_seed_cell_and_length(cell, tmp_path):
    cmds = loop_gap.commands(cell, 5, 1234, tmp_path)
    native, native_json = cmds["native"]
    ours, train_json = cmds["ours"]
    assert native[1].endswith("gsplat_native.py") and native[native.index("--seed") + 1] == "5"
    assert native[native.index("--cell") + 1] == str(cell) and native[native.index("--iterations") + 1] == "1234"
    assert ours[1:3] == ["-m", "splat_train"] and ours[ours.index("--recipe") + 1] == "paper"
    assert ours[ours.index("--rasterizer") + 1] == "gsplat" and ours[ours.index("--seed") + 1] == "5"
    assert train_json.name == "train.json" and native_json.parent == tmp_path


def test_cli_refuses_a_folder_that_is_not_a_prepared_cell(tmp_path, capsys):
    assert loop_gap.main(["--cell", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not a prepared cell" in err[0]
    assert loop_gap.main(["--cell", str(tmp_path), "--jobs", "0"]) == 2
    assert "--jobs and --iterations must be positive" in capsys.readouterr().err


def test_cli_never_writes_over_an_input_or_a_file_it_did_not_write(cell, tmp_path, capsys):
    prepared = cell / "prepared.json"
    before = prepared.read_bytes()
    for out in (prepared, cell / "bridge" / "result.json"):
        assert loop_gap.main(["--cell", str(cell), "--out", str(out), "--seeds", "0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--out" in err[0], err
    foreign = tmp_path / "notes.json"
    foreign.write_text("{}")
    assert loop_gap.main(["--cell", str(cell), "--out", str(foreign), "--seeds", "0"]) == 2
    assert "never replaces a file it did not write" in capsys.readouterr().err
    assert prepared.read_bytes() == before and foreign.read_text() == "{}"


def test_gpu_check_lists_the_part():
    assert "loop_gap" in gpu_check.PARTS and "loop_gap" in gpu_check.GSPLAT_PARTS  # it waits for gsplat's build
