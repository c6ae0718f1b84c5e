"""Plots whose labels fit: with very wide tick labels the y-axis label (and every other label)
still lies inside the figure (evaluation/reports/plots.py)."""

from __future__ import annotations

import matplotlib
import pandas as pd

from evaluation.reports import plots


def test_axis_labels_stay_inside_the_figure_with_long_tick_labels(tmp_path, monkeypatch):
    figures = []

    def keep(fig, path, dpi=100):
        figures.append(fig)
        return path

    monkeypatch.setattr(plots, "save_png", keep)
    runs = pd.DataFrame({
        "dataset": ["d"] * 3, "scene": ["s"] * 3, "n": [3] * 3, "init": ["vggt", "colmap", "oracle"],
        "bridge_mode": ["gated", "uniform", "gated"], "total_s": [1.5, 2.5, 3.5],
        "psnr": [123456789.123456, 123456789.123457, 123456789.123458], "final_test_psnr": [None] * 3,
    })
    # full numbers on the ticks (no offset, no scientific notation): long tick labels
    with matplotlib.rc_context({"axes.formatter.useoffset": False, "axes.formatter.limits": (-30, 30)}):
        assert len(plots.pareto_plot(runs, tmp_path)) == 1
    fig = figures[0]
    fig.canvas.draw()  # as saving does: labels placed for the final layout
    renderer = fig.canvas.get_renderer()
    box = fig.bbox
    (ax,) = fig.axes
    ticks = [t.get_window_extent(renderer) for t in ax.get_yticklabels() if t.get_text()]
    assert max(t.width for t in ticks) > 0.15 * box.width  # the tick labels are long indeed
    for label in (ax.yaxis.label, ax.xaxis.label, ax.title):
        ext = label.get_window_extent(renderer)
        assert ext.x0 >= box.x0 and ext.x1 <= box.x1 and ext.y0 >= box.y0 and ext.y1 <= box.y1, (label, ext, box)
    plots.pyplot().close(fig)
