"""The initialisation study's report: per-run records (:mod:`evaluation.study.collect`) -> per-cell
means with 95 % intervals over seeds and paired mode differences (:mod:`evaluation.study.stats`),
Markdown tables (:mod:`evaluation.study.tables`), plots (:mod:`evaluation.study.plots`) and an
HTML section (``python -m evaluation study``)."""

from __future__ import annotations

import html
import logging
import time
from pathlib import Path

import pandas as pd

from runtime.atomic import atomic_dir, write_json
from evaluation.initialisers import registry
from evaluation.reports.markup import counted, html_page, html_table, markdown_table
from evaluation.study.collect import STUDY_INITS, collect_curves, collect_references, collect_study
from evaluation.study.plots import study_plots
from evaluation.study.stats import summarise
from evaluation.study.tables import all_tables, cell_order

__all__ = ["study_markdown", "study_section_html", "run_study"]

log = logging.getLogger(__name__)

_CSS = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #ccc;padding:3px 6px}")

def _init_note(runs: pd.DataFrame) -> str:
    """What the cells are: the registry's ``study_note`` of each studied initialiser in ``runs``."""
    inits = set(runs["init"]) if "init" in runs else set(registry.studied()[:1])
    return " ".join(registry.get(i).study_note for i in registry.studied() if i in inits)


REFERENCE_NOTE = ("Reference initialisers (e.g. the COLMAP baseline) are the regular runs of the same views and "
                  "training budget: one run each, no seeds, no interval, Bridge mode uniform (COLMAP has no "
                  "confidence, so gated and filtered do not apply); a failed COLMAP is reported as such.")


def study_markdown(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, plots: list[Path],
                   out_dir: Path, curves: pd.DataFrame | None = None, refs: pd.DataFrame | None = None) -> str:
    order = cell_order(runs, cells)
    k = runs.groupby(["dataset", "scene", "n", "cell", "bridge_mode"])["seed"].nunique()
    lpips_nets = sorted(set(runs["lpips_net"]))
    parts = ["# Initialisation study", "", _init_note(runs), "",
             f"{counted(len(runs), 'run')}; {counted(runs['cell'].nunique(), 'cell')}; seeds per cell and mode: "
             f"{int(k.min())}-{int(k.max())}; training iterations: "
             f"{', '.join(str(int(i)) for i in sorted(runs['iterations'].dropna().unique()))}; "
             f"LPIPS network: {', '.join(lpips_nets)}. Every entry: mean ± 95 % t-interval half-width "
             "over seeds (evaluation/study/stats.py). \"Final\" is `python -m evaluation images` on the final "
             "model's PNG renders; \"best it.\" is the best of the trainer's held-out evaluations along the "
             "run (`train/log.parquet`; float renders): the highest PSNR, the highest SSIM, the lowest "
             "LPIPS, each at its own iteration.", "", "## Cells", ""]
    rows = []
    for c in order:
        info = cells.get(c, {})
        noise = info.get("noise") or {}
        rows.append([c, str(info.get("axis") or "-"), str(info.get("base") or "-")]
                    + [str(noise.get(key, "-")) for key in ("rot_deg", "trans_frac", "depth_rel", "outlier_frac",
                                                            "conf_noise", "conf_mode")])
    parts.append(markdown_table(["cell", "axis", "base", "rot_deg", "trans_frac", "depth_rel", "outlier_frac",
                            "conf_noise", "conf_mode"], rows))
    if refs is not None and not refs.empty:
        parts += ["", REFERENCE_NOTE]
    for title, (header, rows) in all_tables(runs, summary, cells, curves, refs).items():
        parts += ["", f"## {title}", "", markdown_table(header, rows)]
    if plots:
        parts += ["", "## Plots", ""]
        parts += [f"![{p.stem}]({p.relative_to(out_dir).as_posix()})" for p in plots]
    return "\n".join(parts) + "\n"


def study_section_html(runs: pd.DataFrame, summary: pd.DataFrame, cells: dict, plots: list[Path],
                       img_prefix: str, curves: pd.DataFrame | None = None,
                       refs: pd.DataFrame | None = None) -> str:
    """The study as an HTML section (h2 + tables + plots); images at ``img_prefix + name``."""
    inits = ", ".join(sorted(set(runs["init"]))) if "init" in runs else registry.studied()[0]
    parts = [f"<h2>Initialisation study ({html.escape(inits)} cells; mean ± 95 % interval over seeds)</h2>",
             f"<p>{html.escape(_init_note(runs))}</p>"]
    if refs is not None and not refs.empty:
        parts.append(f"<p>{html.escape(REFERENCE_NOTE)}</p>")
    for title, (header, rows) in all_tables(runs, summary, cells, curves, refs).items():
        parts += [f"<h3>{html.escape(title)}</h3>", html_table(header, rows)]
    for p in plots:
        parts.append(f'<p><img src="{html.escape(img_prefix + p.name)}" alt="{html.escape(p.stem)}"></p>')
    return "\n".join(parts)


def run_study(root: str | Path, out: str | Path, cells: dict | None = None, references=None,
              seeds=None, views=None) -> Path:
    """Write ``out/``: study.md, runs.csv, summary.csv, curves.csv (:func:`collect_curves`),
    references.csv (:func:`collect_references` of the ``references`` run folders), plots/*.png,
    section.html, index.html. Only the runs the grid plans are read (``cells``, ``seeds``,
    ``views``: :func:`planned_runs`)."""
    root, out = Path(root), Path(out)
    cells = cells or {}
    runs = collect_study(root, cells, seeds, views)
    if runs.empty:
        raise ValueError(f"no study runs under {root} "
                         f"({{cell}}/s{{seed}}/{{dataset}}/{{scene}}/n{{n}}/{{init}}/{{mode}}, init one of {STUDY_INITS})")
    summary = summarise(runs)
    t0 = time.perf_counter()
    curves = collect_curves(runs)
    refs = collect_references(references)
    with atomic_dir(out) as tmp:
        plots = study_plots(runs, summary, cells, tmp / "plots", curves)
        runs.to_csv(tmp / "runs.csv", index=False)
        summary.to_csv(tmp / "summary.csv", index=False)
        curves.to_csv(tmp / "curves.csv", index=False)
        refs.to_csv(tmp / "references.csv", index=False)
        (tmp / "study.md").write_text(study_markdown(runs, summary, cells, plots, tmp, curves, refs))
        section = study_section_html(runs, summary, cells, plots, "plots/", curves, refs)
        (tmp / "section.html").write_text(section)
        (tmp / "index.html").write_text(html_page("Initialisation study", _CSS, section))
        write_json(tmp / "cells.json", cells)
    log.info("study: %d runs, %d cells, %d reference runs (%d succeeded), %d plots -> %s (%.1f s)", len(runs),
             runs["cell"].nunique(), len(refs), int(refs["success_paper"].sum()) if len(refs) else 0, len(plots),
             out, time.perf_counter() - t0)
    return out / "study.md"
