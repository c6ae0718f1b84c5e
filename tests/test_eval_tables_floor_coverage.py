"""The floor (floor.json) and the coverage (metrics.json's coverage / covered) in every quality
table: the run records, Table I, Table II, their legends, the Markdown of ``python -m
evaluation tables`` and the HTML of ``python -m evaluation report``, on the fake results tree
(tests/eval_fake_results.py) with those files written by hand; a tree without them still builds
its tables with "-"."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from _cli import run as run_cli
from eval_fake_results import build
from evaluation.reports.results import collect_runs
from evaluation.reports.tables import FLOOR, TABLE_ONE, TABLE_TWO, table_legends, table_one, table_two

# floor.json per (scene, n): room and garden at n = 3 only (nus and every n = 6 have none)
FLOORS = {("garden", 3): (11.0, 0.21, 0.61, 0.71), ("room", 3): (13.0, 0.23, 0.63, 0.73)}
ALPHA = 0.5  # the covered-alpha threshold the fake metrics.json record
# metrics.json coverage of the VGGT gated runs at n = 3: scene -> (coverage, covered psnr, ssim, alex, vgg)
COVERED = {"garden": (0.6, 25.0, 0.7, 0.2, 0.3), "room": (0.8, 29.0, 0.8, 0.1, 0.2), "nus": (0.7, 21.0, 0.6, 0.3, 0.4)}
TESTPOSE_COVERED = {"room": (0.9, 31.0, 0.85, 0.05, 0.15)}


def _floor(path: Path, psnr, ssim, alex, vgg) -> None:
    path.write_text(json.dumps({
        "colour": [120, 110, 100], "psnr": psnr, "ssim": ssim, "lpips_alex": alex, "lpips_vgg": vgg,
        "n_images": 2, "per_image": [], "train_names": ["a.JPG", "b.JPG", "c.JPG"], "psnr_cap_db": 100.0,
        "lpips_weights": {}, "wall_time_s": 0.1}))


def _cover(path: Path, values) -> None:
    m = json.loads(path.read_text())
    cov, *measures = values
    m.update({"covered_alpha": ALPHA, "coverage": cov,
              "covered": dict(zip(("psnr", "ssim", "lpips_alex", "lpips_vgg"), measures))})
    path.write_text(json.dumps(m))


def _with_floor_and_coverage(root: Path) -> Path:
    results, _ = build(root)
    for (scene, n), values in FLOORS.items():
        _floor(results / "mip360" / scene / f"n{n}" / "floor.json", *values)
    for scene, values in COVERED.items():
        _cover(results / "mip360" / scene / "n3" / "vggt" / "gated" / "metrics.json", values)
    for scene, values in TESTPOSE_COVERED.items():
        _cover(results / "mip360" / scene / "n3" / "vggt" / "gated" / "testpose" / "metrics.json", values)
    # a metrics.json scored without alpha: the four keys present, null
    m = results / "mip360" / "room" / "n3" / "colmap" / "uniform" / "metrics.json"
    m.write_text(json.dumps({**json.loads(m.read_text()), "covered_alpha": None, "coverage": None, "covered": None}))
    return results


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    return _with_floor_and_coverage(tmp_path_factory.mktemp("floor"))


@pytest.fixture(scope="module")
def runs(results):
    return collect_runs(results)


def _one(runs, scene, n, init, mode):
    sel = runs[(runs.scene == scene) & (runs.n == n) & (runs.init == init) & (runs.bridge_mode == mode)]
    assert len(sel) == 1
    return sel.iloc[0]


def test_records_carry_coverage_of_both_protocols_and_the_scene_floor(runs):
    r = _one(runs, "room", 3, "vggt", "gated")
    assert (r.coverage, r.covered_psnr, r.covered_ssim, r.covered_lpips_alex, r.covered_lpips_vgg) == COVERED["room"]
    assert (r.testpose_coverage, r.testpose_covered_psnr) == TESTPOSE_COVERED["room"][:2]
    assert r.covered_alpha == ALPHA
    assert (r.floor_psnr, r.floor_ssim, r.floor_lpips_alex, r.floor_lpips_vgg) == FLOORS[("room", 3)]
    # the floor belongs to the scene and n: every initialiser and mode of it reads the same one
    assert _one(runs, "room", 3, "vggt", "uniform").floor_psnr == _one(runs, "room", 3, "colmap", "uniform").floor_psnr
    g = _one(runs, "garden", 3, "vggt", "gated")
    assert math.isnan(g.testpose_coverage) and g.coverage == COVERED["garden"][0]
    # null keys (scored without alpha), absent keys (an older metrics.json), no floor.json: NaN
    for r in (_one(runs, "room", 3, "colmap", "uniform"), _one(runs, "room", 6, "vggt", "gated")):
        assert math.isnan(r.coverage) and math.isnan(r.covered_psnr) and math.isnan(r.testpose_coverage)
    assert math.isnan(_one(runs, "room", 6, "vggt", "gated").floor_psnr)
    assert math.isnan(_one(runs, "nus", 3, "vggt", "gated").floor_psnr)
    assert _one(runs, "garden", 3, "colmap", "uniform").floor_psnr == FLOORS[("garden", 3)][0]  # a failed run too


def test_table_two_floor_row_and_covered_columns(runs):
    t = table_two(runs)
    floor = t[t["init"] == FLOOR]
    assert list(floor["n"]) == [3]  # n = 6 has no floor.json: no floor row
    f = floor.iloc[0]
    assert f["runs"] == 2  # the scenes with a floor
    for protocol in ("strict", "test-pose"):  # a flat image does not depend on the pose
        assert f[f"PSNR [{protocol}]"] == pytest.approx(np.mean([11.0, 13.0]))
        assert f[f"SSIM [{protocol}]"] == pytest.approx(np.mean([0.21, 0.23]))
        assert f[f"LPIPS-alex [{protocol}]"] == pytest.approx(np.mean([0.61, 0.63]))
        assert f[f"LPIPS-vgg [{protocol}]"] == pytest.approx(np.mean([0.71, 0.73]))
        assert math.isnan(f[f"coverage [{protocol}]"]) and math.isnan(f[f"PSNR covered [{protocol}]"])
    assert f["success (paper)"] == "-"
    assert t.iloc[-1]["init"] == FLOOR  # after the initialisers of its dataset
    v = t[(t["init"] == "vggt") & (t["mode"] == "gated") & (t["n"] == 3)].iloc[0]
    assert v["coverage [strict]"] == pytest.approx(np.mean([c[0] for c in COVERED.values()]))
    assert v["PSNR covered [strict]"] == pytest.approx(np.mean([c[1] for c in COVERED.values()]))
    assert v["SSIM covered [strict]"] == pytest.approx(np.mean([c[2] for c in COVERED.values()]))
    assert v["LPIPS-vgg covered [strict]"] == pytest.approx(np.mean([c[4] for c in COVERED.values()]))
    assert v["coverage [test-pose]"] == pytest.approx(0.9) and v["PSNR covered [test-pose]"] == pytest.approx(31.0)
    c = t[(t["init"] == "colmap") & (t["n"] == 3)].iloc[0]
    assert math.isnan(c["coverage [strict]"]) and math.isnan(c["PSNR covered [strict]"])


def test_table_one_floor_over_the_same_scenes(runs):
    t = table_one(runs).set_index("n")
    r3 = t.loc[3]
    assert r3["matched"] == 1  # room: COLMAP fails on garden, has no held-out metrics on nus
    assert r3["PSNR floor (matched)"] == pytest.approx(13.0)
    assert r3["PSNR floor (all)"] == pytest.approx(12.0)  # garden and room: nus has no floor.json
    r6 = t.loc[6]
    assert math.isnan(r6["PSNR floor (matched)"]) and math.isnan(r6["PSNR floor (all)"])


def test_legends_say_what_the_floor_and_covered_are(runs, tmp_path):
    legends = table_legends(runs)
    assert "flat image of the training views' mean colour, scored like a model" in legends[TABLE_ONE]
    assert "mean colour" in legends[TABLE_TWO]
    assert f"accumulated alpha is at least {ALPHA:g} (metrics.json's covered_alpha)" in legends[TABLE_TWO]
    old = collect_runs(build(tmp_path)[0])
    legends = table_legends(old)
    assert "accumulated alpha is at least - (" in legends[TABLE_TWO]
    assert "no scene here has one (python -m evaluation floor writes it)" in legends[TABLE_ONE]


def _section(md: str, title: str) -> str:
    return md.split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def test_tables_cli_shows_the_floor_row_and_covered_columns(results, tmp_path):
    out = tmp_path / "t"
    proc = run_cli(["-m", "evaluation", "tables", "--results", str(results), "--out", str(out)])
    assert proc.returncode == 0, proc.stderr
    md = (out / "tables.md").read_text()
    two = _section(md, TABLE_TWO)
    header = next(ln for ln in two.splitlines() if ln.startswith("| dataset"))
    cells = [c.strip() for c in header.strip("|").split("|")]
    for col in ("coverage [strict]", "PSNR covered [strict]", "SSIM covered [strict]", "LPIPS-vgg covered [strict]",
                "LPIPS-alex covered [strict]", "coverage [test-pose]", "PSNR covered [test-pose]"):
        assert col in cells
    floor = [ln for ln in two.splitlines() if ln.startswith(f"| mip360 | {FLOOR} |")]
    assert len(floor) == 1
    row = dict(zip(cells, (c.strip() for c in floor[0].strip("|").split("|"))))
    assert row["n"] == "3" and row["PSNR [strict]"] == "12.00" and row["SSIM [strict]"] == "0.220"
    assert row["LPIPS-vgg [strict]"] == "0.720" and row["coverage [strict]"] == "-"
    vggt = next(ln for ln in two.splitlines() if ln.startswith("| mip360 | vggt | gated | 3 |"))
    row = dict(zip(cells, (c.strip() for c in vggt.strip("|").split("|"))))
    assert row["coverage [strict]"] == "0.700" and row["PSNR covered [strict]"] == "25.00"
    assert f"at least {ALPHA:g} (metrics.json's covered_alpha)" in two
    one = _section(md, TABLE_ONE)
    assert "| PSNR floor (matched) | PSNR floor (all) |" in one and "| 13.00 | 12.00 |" in one
    assert "mean colour" in one


def test_old_results_tree_still_builds_with_dashes(tmp_path):
    results, _ = build(tmp_path / "old")
    out = tmp_path / "t"
    proc = run_cli(["-m", "evaluation", "tables", "--results", str(results), "--out", str(out)])
    assert proc.returncode == 0, proc.stderr
    runs = pd.read_parquet(out / "runs.parquet")
    assert runs[["coverage", "covered_psnr", "testpose_coverage", "floor_psnr", "covered_alpha"]].isna().all().all()
    two = _section((out / "tables.md").read_text(), TABLE_TWO)
    assert f"| {FLOOR} |" not in two
    header = next(ln for ln in two.splitlines() if ln.startswith("| dataset"))
    cells = [c.strip() for c in header.strip("|").split("|")]
    vggt = next(ln for ln in two.splitlines() if ln.startswith("| mip360 | vggt | gated | 3 |"))
    row = dict(zip(cells, (c.strip() for c in vggt.strip("|").split("|"))))
    assert row["coverage [strict]"] == "-" and row["PSNR covered [strict]"] == "-" and row["PSNR [strict]"] != "-"
    assert "at least - (" in two


def test_report_cli_shows_the_floor_and_coverage(results, tmp_path):
    out = tmp_path / "r"
    proc = run_cli(["-m", "evaluation", "report", "--results", str(results), "--out", str(out)], timeout=180)
    assert proc.returncode == 0, proc.stderr
    page = (out / "index.html").read_text()
    two = page[page.index(f"<h2>{TABLE_TWO}</h2>"):]
    two = two[: two.index("<h2>", 5)]
    assert "<th>coverage [strict]</th>" in two and "<th>PSNR covered [strict]</th>" in two
    assert f"<td>{FLOOR}</td>" in two and "flat image of the training views&#x27; mean colour" in two
    assert f"at least {ALPHA:g} (metrics.json&#x27;s covered_alpha)" in two
    one = page[page.index(f"<h2>{TABLE_ONE}</h2>"):]
    assert "<th>PSNR floor (all)</th>" in one[: one.index("</table>")]


def test_a_damaged_floor_json_is_treated_as_missing(tmp_path, caplog):
    results, _ = build(tmp_path / "bad")
    (results / "mip360" / "room" / "n3" / "floor.json").write_text('{"psnr": 1')  # cut short
    (results / "mip360" / "garden" / "n3" / "floor.json").write_text('{"psnr": "high", "ssim": null}')
    with caplog.at_level("WARNING"):
        runs = collect_runs(results)
    assert any("floor.json" in r.getMessage() and "treated as missing" in r.getMessage() for r in caplog.records)
    assert runs["floor_psnr"].isna().all() and runs["floor_ssim"].isna().all()
    assert FLOOR not in set(table_two(runs)["init"])


def test_pareto_plot_draws_the_scene_floor(runs, tmp_path, monkeypatch):
    from evaluation.reports import plots

    drawn = {}

    def keep(fig, path, dpi=100):
        ax = fig.axes[0]
        drawn[Path(path).name] = [ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_label().startswith("floor")]
        plots.pyplot().close(fig)
        return path

    monkeypatch.setattr(plots, "save_png", keep)
    plots.pareto_plot(runs, tmp_path)
    assert drawn["pareto__mip360__room__n3.png"] == [13.0]
    assert drawn["pareto__mip360__garden__n3.png"] == [11.0]
    assert drawn["pareto__mip360__room__n6.png"] == [] and drawn["pareto__mip360__nus__n3.png"] == []
