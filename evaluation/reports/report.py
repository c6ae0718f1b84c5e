"""One static HTML report: ``out/index.html`` plus ``out/images/`` (tables, plots, render grids).

Render grids follow the paper's Fig. 2: per scene and n, one row per test view (at most
``max_views``), one column per initialiser (in the registry's order) and the
ground truth last. A cell whose initialiser failed (paper criterion) says "failed" with the
reason; a run without that render says "missing".

Renders are read from each run's ``renders/<name>`` folder (:func:`evaluation.reports.results.find_file`);
ground truth from ``{scenes}/{dataset}/{scene}/test_images/`` (the workflow's results tree),
``{scenes}/{dataset}/{scene}/images/`` or ``{scenes}/{scene}/images/``
(matched by file stem). Thumbnails are downsampled by an integer factor to <= 256 px wide.

A scene with no held-out view (your own photos: its split.json lists no test view) has no
render grid; the photo section (:mod:`evaluation.reports.photos`) shows its training photos
beside their renders instead, and a report of such scenes alone leaves out the held-out tables
and plots with one line that says so.
"""

from __future__ import annotations

import html
import json
import logging
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd

from runtime.atomic import atomic_dir
from evaluation.initialisers import registry
from evaluation.reports import photos
from evaluation.reports.markup import counted, html_page, number_cells
from evaluation.reports.plots import run_plots
from evaluation.metrics.pose import GateConfig, success_criteria_text
from evaluation.reports.report_view import view_section
from evaluation.reports.results import TESTPOSE_DIR, collect_runs, find_file, run_label
from evaluation.reports.tables import (HELDOUT_TABLES, build_tables, has_heldout, protocol_note, table_legends,
                                      table_notes)
from evaluation.reports.thumbs import MAX_VIEWS, images_in, thumb_cell

__all__ = ["guide_html", "render_grid_html", "run_report"]

log = logging.getLogger(__name__)

_CSS = """body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;
margin:1em 0;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px;text-align:left}
td.num{text-align:right}.arg{white-space:nowrap}
th{background:#eee}.grid td{text-align:center;vertical-align:middle}.failed{background:#fdd;
color:#900;width:160px}.missing{background:#eee;color:#666;width:160px}img{max-width:100%}"""


def _gt_folder(scenes_dir: Path | None, dataset: str, scene: str) -> Path | None:
    if scenes_dir is None:
        return None
    # the workflow's results tree keeps the held-out views at {R}/{dataset}/{scene}/test_images
    for cand in (scenes_dir / dataset / scene / "test_images", scenes_dir / dataset / scene / "images",
                 scenes_dir / scene / "images",
                 scenes_dir / f"{dataset}__{scene}" / "images"):
        if cand.is_dir():
            return cand
    return None


def _init_order(runs: dict) -> list[str]:
    """The labels of ``runs`` ({label: row}) in the registry's order of their initialisers
    (evaluation/initialisers/registry.py), then by label (the modes of one initialiser)."""
    return sorted(runs, key=lambda lab: (registry.rank(runs[lab].init), lab))


def render_grid_html(group: pd.DataFrame, images_dir: Path, scenes_dir: Path | None,
                     max_views: int = MAX_VIEWS) -> str:
    """The HTML table of one (dataset, scene, n) group of runs; thumbnails go to ``images_dir``.

    A column per run's strict renders; where a run has the test-pose protocol's renders
    (``testpose/refine/renders``), a second column beside it, and every run column then names its
    protocol (``[strict]``, ``[test-pose]``)."""
    dataset, scene, n = group["dataset"].iloc[0], group["scene"].iloc[0], int(group["n"].iloc[0])
    runs = {run_label(row.init, row.bridge_mode): row for row in group.itertuples()}
    columns = []  # (label, row, {stem: image})
    for init in _init_order(runs):
        row = runs[init]
        folder = find_file(Path(row.run_dir), "renders")
        strict = images_in(folder) if folder is not None and folder.is_dir() else {}
        tp_folder = Path(row.run_dir) / TESTPOSE_DIR / "refine" / "renders"
        columns.append([init, "strict", row, strict])
        if tp_folder.is_dir():
            columns.append([init, "test-pose", row, images_in(tp_folder)])
    both = any(c[1] == "test-pose" for c in columns)
    gt = images_in(_gt_folder(scenes_dir, dataset, scene))
    views = sorted(set().union(*[set(c[3]) for c in columns]))[:max_views]
    if not views:
        return ""
    labels = [f"{init} [{protocol}]" if both else init for init, protocol, _, _ in columns]
    head = "".join(f"<th>{html.escape(lab)}</th>" for lab in labels) + "<th>ground truth</th>"
    rows = []
    for stem in views:
        cells = []
        for label, (init, protocol, row, images) in zip(labels, columns):
            if not bool(row.success_paper):
                reason = row.reason
                why = f"<br><small>{html.escape(str(reason))}</small>" if isinstance(reason, str) and reason else ""
                cells.append(f'<td class="failed">failed{why}</td>')
                continue
            tag = re.sub(r"[^A-Za-z0-9_.-]+", "_", init.strip("_")).strip("_")
            tag += "__testpose" if protocol == "test-pose" else ""
            cells.append(thumb_cell(images.get(stem), images_dir,
                                    f"renders/{dataset}__{scene}__n{n}__{tag}__{stem}.png", f"{label} {stem}"))
        cells.append(thumb_cell(gt.get(stem), images_dir, f"renders/{dataset}__{scene}__n{n}__gt__{stem}.png",
                                f"ground truth {stem}"))
        rows.append(f"<tr><th>{html.escape(stem)}</th>{''.join(cells)}</tr>")
    return (f"<h3>{html.escape(dataset)} / {html.escape(scene)}, n = {n}</h3>\n<table class=\"grid\">"
            f"<tr><th>view</th>{head}</tr>\n" + "\n".join(rows) + "</table>")


# What the report's names mean, shown once at its top (the image metrics only where views were
# held out: guide_html).
_GUIDE_METRICS = (
    "<li><b>Image metrics</b>: PSNR / SSIM / LPIPS are scored on the 8-bit renders of the held-out views "
    "after the last iteration; <i>log PSNR final</i> and <i>log PSNR best</i> are the training log's "
    "held-out PSNR at the last and at the best evaluated iteration (<i>best it.</i>).</li>")
_GUIDE_HEAD = (
    "<h2>What you are looking at</h2><ul>"
    "<li><b>Initialisers</b> give the training cameras and the seed points: <code>vggt</code> "
    "(VGGT-1B from the unposed photos), <code>colmap</code> (COLMAP structure-from-motion on the same "
    "training views), <code>posed</code> (the scene's reference cameras with points triangulated from the "
    "training views) and <code>oracle</code> (synthetic scenes only: the exact ground-truth cameras and "
    "depth, written as VGGT's output, optionally with seeded noise; an upper bound, not a method). "
    "A <code>_ba</code> suffix: the same cameras refined by bundle adjustment.</li>"
    "<li><b>Bridge modes</b> (the <i>mode</i> column) say how Gaussians are seeded from the points: "
    "<code>gated</code> gives each Gaussian an initial opacity that grows with the initialiser's "
    "per-point confidence (Eq. 2); <code>uniform</code> gives every Gaussian the same opacity (what a "
    "COLMAP model, which has no confidence, always gets); <code>filtered</code> is <code>gated</code> "
    "after dropping the least confident points.</li>"
    "<li><b>Success</b>: <i>success (paper)</i> is the paper's criterion; <i>success (accurate)</i> adds the "
    "accuracy gate on pose error (both defined above). Neither is a Bridge mode.</li>")
_GUIDE_TIMES = (
    "<li><b>Run times</b> are wall seconds per stage; one-time builds (the C++ kernel) are not "
    "included.</li>")


def guide_html(heldout: bool = True) -> str:
    """The report's "What you are looking at" list; the image metrics only with ``heldout``."""
    return _GUIDE_HEAD + (_GUIDE_METRICS if heldout else "") + _GUIDE_TIMES + "</ul>"


GUIDE_HTML = guide_html()


def _table_html(df: pd.DataFrame) -> str:
    if df.empty:
        return "<p>(no runs)</p>"
    from evaluation.reports.tables import _DIGITS

    def fmt(x):
        return "-" if pd.isna(x) else (f"{x:.3f}" if abs(x) < 10 else f"{x:.2f}")

    shown = df.copy()
    for c in shown.columns:
        if _DIGITS.get(c) == 0 and shown[c].dtype.kind == "f":  # counts (iterations, runs) as integers
            shown[c] = shown[c].map(lambda v: "-" if pd.isna(v) else f"{v:.0f}")
        elif shown[c].dtype == bool:  # the Markdown tables' words, not True/False
            shown[c] = shown[c].map(lambda v: "yes" if v else "no")
        elif shown[c].dtype == object:
            shown[c] = shown[c].map(lambda v: "-" if v is None or (isinstance(v, float) and pd.isna(v))
                                    else ("yes" if isinstance(v, (bool, np.bool_)) and v
                                          else "no" if isinstance(v, (bool, np.bool_)) else v))
    return number_cells(shown.to_html(index=False, na_rep="-", float_format=fmt, escape=True, border=0))


def _reference_source(runs: pd.DataFrame) -> str | None:
    """Where an initialiser's cameras come from when it says so (its status.json's
    ``reference_source``, e.g. the posed initialiser's), from the first of its runs that does."""
    for run_dir in runs.get("run_dir", pd.Series(dtype=object)).dropna():
        status = Path(run_dir) / "status.json"
        try:
            source = json.loads(status.read_text()).get("reference_source") if status.is_file() else None
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(source, str) and source:
            return source
    return None


def _initialiser_notes(results: Path, runs: pd.DataFrame) -> list[str]:
    """Where an initialiser's cameras come from (:func:`_reference_source`), and the configured
    initialisers a scene could not have (``results/initialisers.json``, written by the workflow)."""
    out = []
    for init in sorted(set(runs["init"]) if len(runs) else (), key=lambda i: (registry.rank(i), i)):
        source = _reference_source(runs[runs["init"] == init])
        if source:
            out.append(f"<p>{html.escape(registry.label(init))}: {html.escape(source)}.</p>")
    notes = results / "initialisers.json"
    skipped = json.loads(notes.read_text()).get("skipped", []) if notes.is_file() else []
    if skipped:
        items = "".join(f"<li>{html.escape(s['init'])} on {html.escape(s['dataset'])}/{html.escape(s['scene'])}: "
                        f"{html.escape(s['reason'])}</li>" for s in skipped)
        out.append(f"<p>Configured initialisers not run:</p><ul>{items}</ul>")
    return out


def _heldout_cameras_note(runs: pd.DataFrame) -> list[str]:
    """Which training cameras the held-out Sim(3) alignments used, and the test-pose protocol's
    settings (:func:`evaluation.reports.tables.protocol_note`) where it ran."""
    note = protocol_note(runs)
    out = [f"<p>{html.escape(note)}</p>"] if note else []
    if "heldout_cameras" not in runs or runs["heldout_cameras"].isna().all():
        return out
    counts = runs["heldout_cameras"].dropna().value_counts().sort_index()
    words = {"initialiser": "the initialiser's training cameras",
             "refined": "the training cameras refined during training (pose refinement)"}
    text = "; ".join(f"{words.get(k, k)}: {v} run{'s' if v != 1 else ''}" for k, v in counts.items())
    return out + [f"<p>Held-out test cameras were aligned (Sim(3) on the training-camera centres) with "
                  f"{html.escape(text)}.</p>"]


def _study_section(results: Path, images: Path) -> list[str]:
    """The initialisation study's section (``results/study/report/section.html``, written by
    ``python -m evaluation study``) with its plots copied to ``images/study/``; [] without one."""
    import shutil

    study = results / "study" / "report"
    section = study / "section.html"
    if not section.is_file():
        return []
    if (study / "plots").is_dir():
        shutil.copytree(study / "plots", images / "study")
    return [section.read_text().replace('src="plots/', 'src="images/study/')]


def run_report(results: str | Path, out: str | Path, scenes_dir: str | Path | None = None,
               gate: GateConfig = GateConfig(), max_views: int = MAX_VIEWS, plots: bool = True) -> Path:
    """Build ``out/index.html`` and ``out/images/`` from a results tree; returns the HTML path.

    ``plots=False`` leaves out the plots (``python -m evaluation plots`` makes them alone).
    Scenes with no held-out view (your own photos) get the photo section
    (:mod:`evaluation.reports.photos`); when no scene has one, the held-out tables, plots and
    render grids are left out with one line that says so.
    """
    t0 = time.perf_counter()
    out = Path(out)
    scenes_dir = Path(scenes_dir) if scenes_dir is not None else None
    runs = collect_runs(results, gate)
    photo_scenes = photos.photo_scenes(results, runs)
    heldout = has_heldout(runs, photo_scenes)
    with atomic_dir(out) as tmp:
        images = tmp / "images"
        images.mkdir()
        plots = run_plots(results, images, runs) if plots and heldout else []
        tables = build_tables(runs, gate, results=results)
        if not heldout:
            tables = {t: df for t, df in tables.items() if t not in HELDOUT_TABLES}
        notes = table_notes(tables)
        legends = table_legends(runs)
        page_title = "Evaluation report" if heldout else "Report on your photos"
        parts = [f"<h1>{page_title}</h1>",
                 f"<p>{counted(len(runs), 'run')} from <code>{html.escape(str(results))}</code>. "
                 + " ".join(success_criteria_text(gate, html=True)) + "</p>", guide_html(heldout)]
        parts += _initialiser_notes(Path(results), runs)
        if heldout:
            parts += _heldout_cameras_note(runs)
        else:
            parts.append(f"<p>{html.escape(photos.NO_HELDOUT_NOTE)}</p>")
        empty = []
        for title, df in tables.items():
            if title in notes:
                parts += [f"<h2>{html.escape(title)}</h2>", f"<p>{html.escape(notes[title])}</p>"]
            elif df.empty:
                empty.append(title)
            else:
                parts += [f"<h2>{html.escape(title)}</h2>", _table_html(df)]
                if legends.get(title):
                    parts.append(f"<p>{html.escape(legends[title])}</p>")
        if empty:
            parts.append(f"<p>Nothing to show (no runs of that kind): {html.escape('; '.join(empty))}.</p>")
        if plots:
            parts.append("<h2>Plots: training curves and error against run time</h2>")
            for p in plots:
                rel = p.relative_to(tmp).as_posix()
                parts.append(f'<p><img src="{html.escape(rel)}" alt="{html.escape(p.stem)}"></p>')
        elif heldout:
            parts.append("<p>No plots: no run has a training log or both a run time and a held-out "
                         "PSNR (training off?).</p>")
        parts += photos.photo_section(results, scenes_dir, runs, photo_scenes, images)
        parts += _study_section(Path(results), images)
        parts += view_section(results)
        n_grids = 0
        if heldout:
            parts.append("<h2>Renders (one column per initialiser that produced them, as headed, a second "
                         "one where the test-pose protocol ran; then the ground truth)</h2>")
            for (ds, sc, _), g in runs.groupby(["dataset", "scene", "n"], sort=True):
                grid = render_grid_html(g, images, scenes_dir, max_views) if (ds, sc) not in photo_scenes else ""
                if grid:
                    parts.append(grid)
                    n_grids += 1
            if not n_grids:
                parts.append("<p>(no renders found)</p>")
        (tmp / "index.html").write_text(html_page(page_title, _CSS, "\n".join(parts)))
    log.info("report: %s, %s, %s, %s -> %s (%.2f s)", counted(len(runs), "run"), counted(len(tables), "table"),
             counted(len(plots), "plot"), counted(n_grids, "render grid"), out / "index.html",
             time.perf_counter() - t0)
    return out / "index.html"
