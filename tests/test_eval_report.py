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
    for title in ("Run status", "Table I", "Table II", "Pose accuracy", "Run time", "error against run time",
                  "Renders"):
        assert title in page
    # every image the page references exists and is a PNG
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert srcs
    for s in srcs:
        assert (out / s).read_bytes()[:4] == b"\x89PNG"
    # one Pareto plot per scene and view count (never one front across scenes)
    assert "images/pareto__mip360__garden__n3.png" in srcs
    assert sum("pareto__" in s for s in srcs) == 6
    # the same words as the Markdown tables: yes/no, never True/False
    assert ">True<" not in page and ">False<" not in page
    # 6 grids (3 scenes x 2 n), 2 views each; the failed COLMAP runs are "failed" cells with reasons
    assert page.count('<table class="grid">') == 6
    grid = page[page.index("mip360 / garden, n = 3"):]
    grid = grid[: grid.index("</table>")]
    assert grid.count('class="failed"') == 2 and "no initial pair" in grid
    # vggt under both protocols + ground truth for two views; with test-pose renders present,
    # every run column names its protocol
    assert grid.count("<img") == 6
    assert "<th>vggt (gated) [strict]</th><th>vggt (gated) [test-pose]</th>" in grid
    assert "colmap (uniform) [strict]" in grid and "renders/mip360__garden__n3__vggt_gated__testpose__img000.png" in grid
    assert "renders/mip360__garden__n3__gt__img000.png" in grid
    nus3 = page[page.index("mip360 / nus, n = 3"):]
    # COLMAP's 2 registered views pass the paper's criterion but cannot be aligned: no renders
    assert nus3[: nus3.index("</table>")].count('class="missing"') == 2
    # thumbnails are downsampled copies, not links into the results tree
    assert not any(str(results) in s for s in srcs)


def test_report_without_ground_truth_or_renders(tmp_path):
    from evaluation.reports.report import run_report

    results, _ = build(tmp_path / "fake")
    for p in results.rglob("renders"):
        for f in p.iterdir():
            f.unlink()
    page = run_report(results, tmp_path / "r", plots=False).read_text()
    assert "(no renders found)" in page and "Table I" in page


def test_report_finds_ground_truth_in_the_workflow_results_tree(tmp_path):
    """The workflow passes --scenes <results>; its held-out views are {dataset}/{scene}/test_images."""
    import shutil

    from evaluation.reports.report import run_report

    results, scenes = build(tmp_path / "fake")
    for img_dir in scenes.glob("*/*/images"):
        shutil.copytree(img_dir, results / img_dir.parent.relative_to(scenes) / "test_images")
    page = run_report(results, tmp_path / "r", scenes_dir=results, plots=False).read_text()
    grid = page[page.index("mip360 / garden, n = 3"):]
    grid = grid[: grid.index("</table>")]
    assert "renders/mip360__garden__n3__gt__img000.png" in grid


def test_plots_folder_exists_with_nothing_to_plot(tmp_path):
    """A declared Snakemake output: the folder is created even for an empty results tree."""
    from evaluation.reports.plots import run_plots

    (tmp_path / "results").mkdir()
    assert run_plots(tmp_path / "results", tmp_path / "plots") == []
    assert (tmp_path / "plots").is_dir()


def test_report_says_what_was_skipped_and_drops_empty_sections(tmp_path):
    """An initialiser the demo skipped (skipped.json) is named with its reason in the run status;
    Table I, which needs it, says why it is not shown instead of a row of dashes; no plots
    means no empty plot heading."""
    import shutil

    from evaluation.reports.report import run_report
    from evaluation.reports.run_status import write_skipped

    results, _ = build(tmp_path / "fake")
    for d in list(results.glob("*/*/n*/vggt")):
        shutil.rmtree(d)
    write_skipped(results, {"vggt": "no VGGT-1B checkpoint and the Hugging Face Hub cannot be reached"})
    page = run_report(results, tmp_path / "r", plots=False).read_text()
    status = page[page.index("Run status"):page.index("Table I")]
    assert status.count(">skipped<") == 6 and "Hugging Face Hub cannot be reached" in status
    assert ">ran<" in status or ">ran, no model<" in status
    table_one = page[page.index("Table I"):]
    assert "vggt did not run" in table_one[:600]
    assert "error against run time" not in page and "No plots" in page


def test_report_says_what_the_names_mean_and_prints_counts_as_integers(tmp_path):
    from evaluation.reports.report import run_report

    results, _ = build(tmp_path / "fake")
    page = run_report(results, tmp_path / "r", plots=False).read_text()
    guide = page[page.index("What you are looking at"):]
    guide = guide[: guide.index("</ul>")]
    for word in ("oracle", "<code>gated</code>", "<code>uniform</code>", "success (accurate)"):
        assert word in guide
    # the accuracy gate is never named like the Bridge mode "gated"
    assert "success (gated)" not in page.lower()
    assert "success (accurate)" in page
    # Table II's best iteration is a whole number, not 1000.00
    table = page[page.index("Table II"):]
    table = table[: table.index("</table>")]
    assert '<td class="num">1000</td>' in table and "1000.00" not in table
    assert table.count("held-out PSNR") == 0 and "log PSNR final" in table


def test_report_tables_left_align_text_and_right_align_numbers(tmp_path):
    from evaluation.reports.report import run_report

    results, _ = build(tmp_path / "fake")
    page = run_report(results, tmp_path / "r", plots=False).read_text()
    assert "text-align:left" in page and "td.num{text-align:right}" in page
    table = page[page.index("Table II"):]
    table = table[: table.index("</table>")]
    assert '<td class="num">1000</td>' in table  # a number
    assert re.search(r"<td>[a-z]+</td>", table)  # a word: the style sheet's left alignment
    assert 'style="text-align: right;"' not in page


def test_plots_command_keeps_its_empty_folder(tmp_path):
    """Nothing to plot (every run failed before training): the command's folder is still its
    output after the process ends (the workflow's plots rule declares it)."""
    import subprocess
    import sys

    failed = tmp_path / "results" / "synthetic" / "s" / "n3" / "colmap"
    failed.mkdir(parents=True)
    (failed / "status.json").write_text('{"success": false, "reason": "no model"}')
    proc = subprocess.run([sys.executable, "-m", "evaluation", "plots", "--results", str(tmp_path / "results"),
                           "--out", str(tmp_path / "plots"), "-q"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "plots").is_dir()
