"""Results tree -> runs.parquet -> Markdown tables, and the plots, on a fake results tree
(tests/eval_fake_results.py; expected cells computed by hand from its values)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from eval_fake_results import build, psnr_of
from evaluation.reports.plots import pareto_front
from evaluation.reports.results import collect_runs, read_run
from evaluation.reports.tables import table_one, to_markdown


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return build(tmp_path_factory.mktemp("fake"))


@pytest.fixture(scope="module")
def runs(tree):
    return collect_runs(tree[0])


def run(runs, scene, n, init, mode=None) -> pd.Series:
    mode = mode or ("uniform" if init == "colmap" else "gated")
    sel = runs[(runs.scene == scene) & (runs.n == n) & (runs.init == init) & (runs.bridge_mode == mode)]
    assert len(sel) == 1
    return sel.iloc[0]


def test_records(runs):
    assert len(runs) == 14  # 12 + VGGT's second bridge mode on room (n = 3, 6)
    assert runs.bridge_mode.notna().all()  # failed COLMAP runs stand for its only mode
    failed = run(runs, "garden", 3, "colmap")
    assert failed.success_paper is False or failed.success_paper == False  # noqa: E712
    assert failed.success_gated == False and failed.has_reference  # noqa: E712
    assert failed.registered == 0 and math.isnan(failed.psnr) and failed.reason == "no initial pair"
    two = run(runs, "nus", 3, "colmap")
    # 2 registered views and points: the paper's criterion holds; no reference: no gate
    assert two.success_paper and two.registered == 2 and two.success_gated is None
    assert two.repeats == 3 and two.repeats_registered_min == 2 and two.repeats_registered_max == 3
    wrong = run(runs, "room", 3, "colmap")
    assert wrong.success_paper and wrong.success_gated == False  # noqa: E712
    v = run(runs, "room", 6, "vggt")
    assert v.success_paper and v.success_gated == True and v.bridge_mode == "gated"  # noqa: E712
    assert v.psnr == psnr_of("room", 6, "vggt") and v.lpips_vgg == 0.4
    u = run(runs, "room", 6, "vggt", "uniform")
    assert u.psnr == psnr_of("room", 6, "vggt", "uniform") and u.ate_rmse == v.ate_rmse  # poses shared
    assert v.init_s == 10.0 and v.bridge_s == 2.0 and v.train_s == 106.0 and v.eval_s == 2.0
    assert v.total_s == 120.0 and v.peak_mem_mb == 3000.0 and v.peak_gpu_mb == 14000.0
    assert v.final_test_psnr == pytest.approx(psnr_of("room", 6, "vggt") - 1)
    assert v.num_gaussians == 6000 and v.iterations == 1000
    c = run(runs, "room", 6, "colmap")
    assert c.init_s == 36.0 and c.peak_mem_mb == 1200.5  # the metrics benchmark TSV's max_rss
    assert run(runs, "nus", 6, "vggt").success_gated is None  # no reference cameras


def test_both_protocols_side_by_side(runs, tmp_path):
    """The test-pose metrics fill their own columns; the strict ones never come from them."""
    from evaluation.reports.tables import table_one, table_two

    r = run(runs, "room", 6, "vggt", "gated")
    assert r["testpose_psnr"] == pytest.approx(r["psnr"] + 1.0) and r["testpose_rot_deg_mean"] == 0.5
    assert math.isnan(run(runs, "room", 6, "colmap", "uniform")["testpose_psnr"])
    r3 = table_one(runs).set_index("n").loc[3]
    assert r3["PSNR [test-pose] vggt (all)"] == pytest.approx(r3["PSNR [strict] vggt (all)"] + 1.0)
    assert math.isnan(r3["PSNR [test-pose] colmap (matched)"])
    t2 = table_two(runs)
    assert {"PSNR [strict]", "PSNR [test-pose]", "LPIPS-vgg [test-pose]"} <= set(t2.columns)
    # the test-pose settings every run recorded are stated once, with the runs they cover
    from evaluation.reports.tables import protocol_note

    n_tp = int(runs["testpose_steps"].notna().sum())
    assert n_tp == int((runs["init"] == "vggt").sum()) > 0
    note = protocol_note(runs)
    assert ("at most 500 Adam steps per held-out view, a view ending after 100 steps without a lower loss, "
            f"in {n_tp} runs (docs") in note
    assert protocol_note(runs[runs["init"] == "colmap"]) is None
    # a mode folder with only the test-pose metrics has no strict PSNR
    from evaluation.reports.results import read_run

    d = tmp_path / "mip360" / "s" / "n3" / "vggt"
    (d / "testpose").mkdir(parents=True)
    (d / "testpose" / "metrics.json").write_text('{"psnr": 30.0}')
    rec = read_run(d)
    assert math.isnan(rec["psnr"]) and rec["testpose_psnr"] == 30.0


def test_eval_time_falls_back_to_benchmark(tmp_path):
    from eval_fake_results import build as b

    results, _ = b(tmp_path)
    r = results / "mip360" / "garden" / "n6" / "vggt"
    (r / "gated" / "metrics.json").unlink()
    (r / "pose.json").unlink()
    (r / "timing.json").unlink()
    rec = read_run(r, mode="gated")
    assert rec["eval_s"] == 4.0 and rec["init_s"] == 12.0  # from metrics.tsv and vggt_init.tsv


def test_table_one_by_hand(runs):
    t = table_one(runs).set_index("n")
    r3 = t.loc[3]
    assert r3["scenes"] == 3 and r3["colmap success (paper)"] == "2/3"
    assert r3["colmap success (accurate)"] == "0/2" and r3["colmap registered"] == "5/9"
    assert r3["vggt success (paper)"] == "3/3" and r3["vggt success (accurate)"] == "2/2"
    assert r3["matched"] == 1
    assert r3["PSNR [strict] colmap (matched)"] == pytest.approx(25.5)
    assert r3["PSNR [strict] vggt (matched)"] == pytest.approx(26.5) and r3["PSNR [strict] delta"] == pytest.approx(1.0)
    assert r3["PSNR [strict] vggt (all)"] == pytest.approx(np.mean([22.5, 26.5, 18.5]))
    r6 = t.loc[6]
    assert r6["colmap success (paper)"] == "3/3" and r6["colmap success (accurate)"] == "2/2"
    assert r6["PSNR [strict] colmap (matched)"] == pytest.approx(np.mean([23.0, 27.0, 19.0]))
    assert r6["LPIPS-vgg [strict] delta"] == pytest.approx(0.0)


def test_tables_cli(tree, tmp_path):
    from evaluation.__main__ import main

    assert main(["tables", "--results", str(tree[0]), "--out", str(tmp_path / "t")]) == 0
    df = pd.read_parquet(tmp_path / "t" / "runs.parquet")
    assert len(df) == 14 and {"success_paper", "success_gated", "ate_rel_radius", "peak_mem_mb"} <= set(df.columns)
    md = (tmp_path / "t" / "tables.md").read_text()
    for title in ("## Table I", "## Table II", "## Pose accuracy", "## Run time", "## COLMAP repeats"):
        assert title in md
    row3 = next(ln for ln in md.splitlines() if ln.startswith("| mip360 | 3 | 3 |"))
    assert "| 2/3 | 0/2 | 5/9 | 3/3 | 2/2 | 1 | 25.50 | 26.50 | 1.00 |" in row3
    # a stricter gate (option) fails the VGGT runs too
    main(["tables", "--results", str(tree[0]), "--out", str(tmp_path / "s"), "--max-rel-rot-deg", "0.5"])
    assert "| 3/3 | 0/2 |" in (tmp_path / "s" / "tables.md").read_text()


def test_markdown_formatting():
    df = pd.DataFrame({"a": ["x|y", None], "b": [1.23456, float("nan")], "c": [True, False]})
    md = to_markdown(df, {"b": 3}).splitlines()
    assert md[0] == "| a | b | c |" and md[2] == "| x\\|y | 1.235 | yes |" and md[3] == "| - | - | no |"


def test_missing_tree_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        collect_runs(tmp_path / "nope")


def test_pareto_front():
    t = np.array([10.0, 5.0, 20.0, 7.0, np.nan])
    e = np.array([1.0, 3.0, 0.5, 3.5, 0.1])
    assert pareto_front(t, e).tolist() == [1, 0, 2]


def test_plots_cli(tree, tmp_path):
    from evaluation.__main__ import main

    assert main(["plots", "--results", str(tree[0]), "--out", str(tmp_path / "p")]) == 0
    pngs = sorted((tmp_path / "p").rglob("*.png"))
    names = {p.name for p in pngs}
    assert "pareto__mip360__garden__n3.png" in names and "mip360__garden__n3.png" in names
    assert len(pngs) == 12  # 6 training-curve plots + one Pareto plot per scene and view count
    for p in pngs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000


def test_run_that_never_produced_results_is_left_out(tmp_path):
    """A run folder holding only logs (e.g. VGGT offline without its checkpoint) did not
    happen: it is not counted as a failure of the method."""
    results, _ = build(tmp_path / "fake")
    before = collect_runs(results)
    ghost = results / "mip360" / "garden" / "n9" / "vggt" / "logs"
    ghost.mkdir(parents=True)
    (ghost / "vggt_init.log").write_text("CheckpointNotFoundError: no VGGT checkpoint found\n")
    after = collect_runs(results)
    assert len(after) == len(before) and not (after.n == 9).any()


def test_held_out_psnr_at_final_and_best_iteration(tmp_path):
    """A run whose held-out PSNR peaks before the end: both numbers are recorded and shown."""
    import pandas as pd

    from eval_fake_results import build
    from evaluation.reports.results import collect_runs
    from evaluation.reports.tables import run_tables

    results, _ = build(tmp_path / "fake")
    log_path = sorted(results.rglob("log.parquet"))[0]
    lg = pd.read_parquet(log_path)
    ev = lg.index[lg["test_psnr"].notna()]
    assert len(ev) >= 3
    lg.loc[ev, "test_psnr"] = [20.0 + (5.0 if i == 1 else 0.5 * i) for i in range(len(ev))]
    lg.to_parquet(log_path)
    runs = collect_runs(results)
    row = runs[runs["run_dir"].map(lambda d: log_path.is_relative_to(d))].iloc[0]
    assert row["best_test_psnr"] == 25.0 and row["best_test_iter"] == float(lg.loc[ev[1], "iteration"])
    assert row["final_test_psnr"] == 20.0 + 0.5 * (len(ev) - 1)
    run_tables(results, tmp_path / "t")
    md = (tmp_path / "t" / "tables.md").read_text()
    assert "log PSNR final" in md and "log PSNR best" in md
