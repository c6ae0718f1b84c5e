"""The static HTML report on a fake results tree (tests/eval_fake_results.py)."""

from __future__ import annotations

import re

from eval_fake_results import build


def test_report(tmp_path):
    from evaluation.__main__ import main

    results, scenes = build(tmp_path / "fake")
    out = tmp_path / "report"
    assert main(["report", "--results", str(results), "--out", str(out), "--scenes", str(scenes),
                 "--max-views", "2"]) == 0
    page = (out / "index.html").read_text()
    for title in ("Table I", "Table II", "Pose accuracy", "Run time", "Error against run time", "Renders"):
        assert title in page
    # every image the page references exists and is a PNG
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert srcs
    for s in srcs:
        assert (out / s).read_bytes()[:4] == b"\x89PNG"
    assert "images/pareto.png" in srcs
    # 6 grids (3 scenes x 2 n), 2 views each; the failed COLMAP runs are "failed" cells with reasons
    assert page.count('<table class="grid">') == 6
    grid = page[page.index("mip360 / garden, n = 3"):]
    grid = grid[: grid.index("</table>")]
    assert grid.count('class="failed"') == 2 and "no initial pair" in grid
    assert grid.count("<img") == 4  # vggt + ground truth for two views
    assert "renders/mip360__garden__n3__gt__img000.png" in grid
    nus3 = page[page.index("mip360 / nus, n = 3"):]
    # COLMAP's 2 registered views pass the paper's criterion but cannot be aligned: no renders
    assert nus3[: nus3.index("</table>")].count('class="missing"') == 2
    # thumbnails are downsampled copies, not links into the results tree
    assert not any(str(results) in s for s in srcs)


def test_report_without_ground_truth_or_renders(tmp_path):
    from evaluation.report import run_report

    results, _ = build(tmp_path / "fake")
    for p in results.rglob("renders"):
        for f in p.iterdir():
            f.unlink()
    page = run_report(results, tmp_path / "r", plots=False).read_text()
    assert "(no renders found)" in page and "Table I" in page


def test_report_finds_ground_truth_in_the_workflow_results_tree(tmp_path):
    """The workflow passes --scenes <results>; its held-out views are {dataset}/{scene}/test_images."""
    import shutil

    from evaluation.report import run_report

    results, scenes = build(tmp_path / "fake")
    for img_dir in scenes.glob("*/*/images"):
        shutil.copytree(img_dir, results / img_dir.parent.relative_to(scenes) / "test_images")
    page = run_report(results, tmp_path / "r", scenes_dir=results, plots=False).read_text()
    grid = page[page.index("mip360 / garden, n = 3"):]
    grid = grid[: grid.index("</table>")]
    assert "renders/mip360__garden__n3__gt__img000.png" in grid


def test_plots_folder_exists_with_nothing_to_plot(tmp_path):
    """A declared Snakemake output: the folder is created even for an empty results tree."""
    from evaluation.plots import run_plots

    (tmp_path / "results").mkdir()
    assert run_plots(tmp_path / "results", tmp_path / "plots") == []
    assert (tmp_path / "plots").is_dir()
