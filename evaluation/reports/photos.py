"""The report's section on scenes with no held-out view (your own photos, scripts/photos.py).

Every photo of such a scene trains, so there is no held-out image to score. Per scene and view
count the section shows, for every run:

* each training photo beside the model's render of its camera, with the PSNR of that render
  against the photo: the *training-view fit*, how well the model reproduces a photo it was
  trained on, not held-out quality. Renders are read from ``{mode}/train_renders/``, which the
  workflow's rule ``render_train_views`` writes (``python -m splat_train render``); for a run
  without that folder the section gives the command that makes it (a stage does not import
  another: the report reads the renders, it does not make them);
* the training curve: loss and training-view PSNR against iteration from ``log.parquet``
  (:mod:`splat_train.training.runlog`);
* the cameras seen from above: centres and viewing directions of ``{mode}/bridge/sparse/0``
  (else the initialiser's ``sparse/0``), projected on the plane normal to the cameras' mean up
  direction;
* the model's size: its number of Gaussians (the PLY header) and its file size.

A scene has no held-out view when ``{results}/{dataset}/{scene}/split.json`` lists no test
view (what the workflow writes for a photo folder's manifest); the photos are the prepared
scene's ``images/`` (``{dataset}/{scene}/converted/images`` in the results tree).
"""

from __future__ import annotations

import html
import json
import logging
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from evaluation.reports.markup import command_html, counted
from evaluation.reports.plots import fit_layout, pyplot, save_png
from evaluation.reports.results import find_file, read_log, run_label
from evaluation.reports.thumbs import images_in, thumb_cell

__all__ = ["heldout_views", "photo_scenes", "photo_folder", "training_view_psnr", "top_down", "camera_plot",
           "training_curve", "render_command", "photo_section", "NO_HELDOUT_NOTE"]

log = logging.getLogger(__name__)

#: the one line that stands for the held-out sections of a report with no held-out view
NO_HELDOUT_NOTE = ("No views were held out (every photo trained), so there are no held-out image metrics, "
                   "pose accuracy, held-out PSNR plots or held-out render grids; the photo section below "
                   "shows how well the model fits the photos it was trained on.")
_TRAIN_RENDERS = "train_renders"
_PREPARED = ("converted", "undistorted")  # workflow/rules/scenes.smk prepare_kind


def heldout_views(results: str | Path, dataset: str, scene: str) -> int | None:
    """The number of held-out views ``{results}/{dataset}/{scene}/split.json`` lists; None
    without a readable split (then the scene is reported as a held-out benchmark scene)."""
    path = Path(results) / dataset / scene / "split.json"
    if not path.is_file():
        return None
    try:
        test = json.loads(path.read_text()).get("test")
    except (OSError, ValueError, AttributeError) as exc:
        log.warning("report: cannot read %s (%s)", path, exc)
        return None
    return len(test) if isinstance(test, list) else None


def photo_scenes(results: str | Path, runs: pd.DataFrame) -> set[tuple[str, str]]:
    """The (dataset, scene) pairs of ``runs`` whose split holds no held-out view."""
    pairs = runs[["dataset", "scene"]].drop_duplicates().itertuples(index=False) if len(runs) else []
    return {(ds, sc) for ds, sc in pairs if heldout_views(results, ds, sc) == 0}


def photo_folder(results: Path, scenes_dir: Path | None, dataset: str, scene: str) -> Path | None:
    """The training photos of a scene at the working resolution: the prepared scene's
    ``images/`` under ``scenes_dir`` (``--scenes``) or the results tree; None when absent."""
    for base in dict.fromkeys(b for b in (scenes_dir, results) if b is not None):
        for cand in (*(base / dataset / scene / k / "images" for k in _PREPARED),
                     base / dataset / scene / "images", base / scene / "images"):
            if cand.is_dir():
                return cand
    return None


def training_view_psnr(render: Path, photo: Path) -> float | None:
    """PSNR (dB, capped as ``python -m evaluation images`` caps it) of a render against the
    photo it was rendered for, both read as [H, W, 3] float in [0, 1]; None when either cannot
    be read or their sizes differ."""
    import torch

    from camio.images import ImageReadError, read_image
    from imgmetrics.psnr_ssim import capped_psnr, psnr

    try:
        a, b = read_image(render), read_image(photo)
    except (ImageReadError, OSError) as exc:
        log.warning("report: cannot read %s or %s (%s)", render, photo, exc)
        return None
    if a.shape != b.shape:
        log.warning("report: render %s is %dx%d, photo %s %dx%d: no PSNR", render, a.shape[1], a.shape[0],
                    photo, b.shape[1], b.shape[0])
        return None
    p, g = (torch.from_numpy(x).double().permute(2, 0, 1) for x in (a, b))
    return capped_psnr(float(psnr(p, g)[0]))


def _run_dirs(row) -> tuple[Path, Path]:
    """(the run's initialiser folder ``{init}``, its mode folder ``{init}/{mode}``; the same
    folder for a flat run or an initialiser-only one). ``row.run_dir`` is the mode folder
    where there is one (:func:`evaluation.reports.results.read_run`)."""
    folder = Path(row.run_dir)
    if isinstance(row.bridge_mode, str) and folder.name == row.bridge_mode and folder.parent.name == row.init:
        return folder.parent, folder
    return folder, folder


def _mode_dir(row) -> Path:
    return _run_dirs(row)[1]


def _cameras_dir(row) -> Path | None:
    """The run's training cameras: in the model's frame (``bridge/sparse/0``), else the
    initialiser's ``sparse/0``."""
    init_dir, mode_dir = _run_dirs(row)
    for cand in (mode_dir / "bridge" / "sparse" / "0", init_dir / "sparse" / "0"):
        if cand.is_dir():
            return cand
    return None


def top_down(cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres and viewing directions seen from above.

    Args:
        cam_from_world: [S, 3, 4] OpenCV extrinsics (x right, y down, z forward).

    Returns:
        (centres [S, 2], directions [S, 2]) in the plane normal to the cameras' mean up
        direction (-y of each camera, in world coordinates): the second axis along the mean
        viewing direction, the first to its right.
    """
    R, t = cam_from_world[:, :, :3], cam_from_world[:, :, 3]
    centres = -np.einsum("sji,sj->si", R, t)
    forward, up = R[:, 2, :], -R[:, 1, :]
    u = up.mean(axis=0)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-9 else np.array([0.0, 0.0, 1.0])
    f = forward.mean(axis=0) - forward.mean(axis=0) @ u * u
    if np.linalg.norm(f) < 1e-9:  # cameras looking straight down (or up): any axis in the plane
        f = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    f = f / np.linalg.norm(f)
    right = np.cross(f, u)
    basis = np.stack([right, f], axis=1)  # [3, 2]
    return centres @ basis, forward @ basis


def camera_plot(cameras: dict[str, Path], path: Path, title: str) -> Path | None:
    """One panel per run (label -> COLMAP model folder): camera centres and viewing directions
    from above (:func:`top_down`), each camera named when there are at most 20; None when no
    model can be read."""
    from camio.colmap import read_model

    models = {}
    for label, folder in cameras.items():
        try:
            cams = read_model(folder).cameras
        except (ValueError, OSError) as exc:
            log.warning("report: cannot read the cameras %s (%s)", folder, exc)
            continue
        if cams:
            models[label] = cams
    if not models:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, len(models), figsize=(max(6.0, 4.5 * len(models)), 5.0), squeeze=False)
    for ax, (label, cams) in zip(axes[0], models.items()):
        centres, dirs = top_down(np.stack([c.cam_from_world for c in cams]))
        extent = float(np.ptp(centres, axis=0).max()) if len(cams) > 1 else 0.0
        length = 0.2 * extent if extent > 0 else 1.0
        ax.scatter(centres[:, 0], centres[:, 1], s=12, c="C0", zorder=3)
        ax.quiver(centres[:, 0], centres[:, 1], dirs[:, 0] * length, dirs[:, 1] * length, angles="xy",
                  scale_units="xy", scale=1, width=0.004, color="C1")
        ax.update_datalim(centres + dirs * length)  # quiver leaves the arrow tips out of the limits
        ax.autoscale_view()
        if len(cams) <= 20:
            for c, (x, y) in zip(cams, centres):
                ax.annotate(Path(c.name).stem, (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{label}: {counted(len(cams), 'camera')}", fontsize=9)
        ax.set_xlabel("right of the mean viewing direction")
        ax.set_ylabel("along the mean viewing direction")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{title}: cameras from above\n(dots: centres; arrows: viewing directions)", fontsize=10)
    fit_layout(fig, top=0.9)
    return save_png(fig, path)


def training_curve(logs: dict[str, pd.DataFrame], path: Path, title: str) -> Path | None:
    """Training loss and training-view PSNR against iteration, one line per run (label ->
    ``log.parquet`` rows); the per-iteration values (one photo each) faint, their running mean
    over about a fiftieth of the run drawn over them. None when no log has either column."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    drawn = False
    for ax, (col, ylab) in zip(axes, (("loss", "training loss"), ("train_psnr", "training-view PSNR (dB)"))):
        for k, (label, lg) in enumerate(sorted(logs.items())):
            if col not in lg or "iteration" not in lg:
                continue
            d = lg[["iteration", col]].dropna()
            d = d[np.isfinite(d[col])]
            if d.empty:
                continue
            window = max(1, len(d) // 50)
            ax.plot(d["iteration"], d[col], color=f"C{k}", alpha=0.25, lw=0.8)
            ax.plot(d["iteration"], d[col].rolling(window, min_periods=1).mean(), color=f"C{k}", lw=1.5,
                    label=label if window == 1 else f"{label} (mean over {window} it.)")
            drawn = True
        ax.set_xlabel("iteration")
        ax.set_ylabel(ylab)
        ax.xaxis.get_major_locator().set_params(integer=True)
        low, high = ax.get_ylim()
        if col == "loss" and low > 0 and high > 10 * low:  # a loss over decades: log axis
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    if not drawn:
        pyplot().close(fig)
        return None
    axes[1].legend(fontsize=7)
    fig.suptitle(f"{title}: training (each iteration scores the one photo it trained on)", fontsize=10)
    fit_layout(fig, top=0.9)
    return save_png(fig, path)


def _size(nbytes: int) -> str:
    return f"{nbytes / 1e6:.1f} MB" if nbytes >= 1e6 else f"{nbytes / 1e3:.1f} kB"


def _model_size(model: Path) -> str:
    """"N Gaussians, S MB" of a model PLY."""
    from camio.ply import PlyFormatError, ply_vertex_count

    try:
        return f"{counted(ply_vertex_count(model), 'Gaussian')}, {_size(model.stat().st_size)}"
    except (PlyFormatError, OSError) as exc:
        return f"unreadable ({html.escape(str(exc))})"


def render_command(row, photos: Path | None) -> list[str]:
    """The command that writes a run's ``train_renders/`` (the workflow's rule
    ``render_train_views``): its model rendered into its training cameras at the photos' size."""
    mode_dir = _mode_dir(row)
    cams = _cameras_dir(row) or mode_dir / "bridge" / "sparse" / "0"
    return ["python", "-m", "splat_train", "render", "--model", str(mode_dir / "train" / "model.ply"),
            "--cameras", str(cams), "--images", str(photos or "PHOTOS"), "--out", str(mode_dir / _TRAIN_RENDERS)]


def _renders(row, photos: Path | None) -> tuple[dict[str, Path], str]:
    """(stem -> render of that training camera, where they come from: HTML) for one run."""
    folder = _mode_dir(row) / _TRAIN_RENDERS
    if folder.is_dir():
        return images_in(folder), f"<code>{html.escape(_TRAIN_RENDERS)}/</code> of the run"
    return {}, (f"none: the run has no <code>{_TRAIN_RENDERS}/</code>; make it with "
                f"<code>{command_html(render_command(row, photos))}</code>")


def _group_section(results: Path, scenes_dir: Path | None, g: pd.DataFrame, images_dir: Path) -> list[str]:
    ds, sc, n = g["dataset"].iloc[0], g["scene"].iloc[0], int(g["n"].iloc[0])
    key = f"{ds}__{sc}__n{n}"
    title = f"{ds} / {sc}, n = {n}"
    photos_dir = photo_folder(results, scenes_dir, ds, sc)
    photos = images_in(photos_dir)
    parts = [f"<h3>{html.escape(title)}</h3>",
             f"<p>{counted(len(photos), 'photo')} from <code>{html.escape(str(photos_dir))}</code>.</p>"
             if photos_dir else "<p>The photos were not found (no prepared <code>images/</code> folder of this "
                                "scene under <code>--scenes</code> or the results tree).</p>"]
    rows, columns, logs, cameras = [], [], {}, {}
    for row in g.itertuples():
        label = run_label(row.init, row.bridge_mode)
        mode_dir = _mode_dir(row)
        cell = html.escape(label)
        model = mode_dir / "train" / "model.ply"
        lg = read_log(find_file(mode_dir, "log.parquet"))
        if lg is not None:
            logs[label] = lg
        if (cams := _cameras_dir(row)) is not None:
            cameras[label] = cams
        if not model.is_file():
            why = row.reason if isinstance(row.reason, str) and row.reason else "see the run status"
            rows.append([cell, f"no trained model ({html.escape(why)})", "-", "-", "-", "-"])
            continue
        renders, source = _renders(row, photos_dir)
        scores = {s: training_view_psnr(renders[s], photos[s]) for s in photos if s in renders}
        finite = [v for v in scores.values() if v is not None]
        its = int(lg["iteration"].max()) if lg is not None and "iteration" in lg and len(lg) else None
        loss = float(lg["loss"].dropna().iloc[-1]) if lg is not None and "loss" in lg and lg["loss"].notna().any() \
            else math.nan
        rows.append([cell, _model_size(model), "-" if its is None else str(its),
                     "-" if math.isnan(loss) else f"{loss:.4f}",
                     f"{np.mean(finite):.2f} dB over {counted(len(finite), 'photo')}" if finite else "-", source])
        columns.append((label, renders, scores))
    parts.append("<table><tr><th>run</th><th>model</th><th>iterations</th><th>final loss</th>"
                 "<th>training-view PSNR (mean)</th><th>renders</th></tr>"
                 + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows) + "</table>")
    curve = training_curve(logs, images_dir / "photos" / f"{key}__curve.png", title)
    cams = camera_plot(cameras, images_dir / "photos" / f"{key}__cameras.png", title)
    for p, what, source in ((curve, "training curve", "log.parquet"), (cams, "camera plot", "camera model")):
        parts.append(f'<p><img src="{html.escape(p.relative_to(images_dir.parent).as_posix())}" '
                     f'alt="{html.escape(f"{title} {what}")}"></p>' if p is not None
                     else f"<p>No {what}: no run has a readable {source}.</p>")
    if columns and photos:
        head = "".join(f"<th>{html.escape(lab)}: render of the photo's camera</th>" for lab, _, _ in columns)
        grid = []
        for stem, photo in photos.items():
            cells = [thumb_cell(photo, images_dir, f"photos/{key}__photo__{stem}.png", f"photo {stem}")]
            for lab, renders, scores in columns:
                why_none = "no camera for this photo" if renders else "see the run's renders above"
                tag = re.sub(r"[^A-Za-z0-9_.-]+", "_", lab).strip("_")
                v = scores.get(stem)
                cap = "training-view PSNR " + ("-" if v is None else f"{v:.2f} dB")
                cells.append(thumb_cell(renders.get(stem), images_dir, f"photos/{key}__{tag}__{stem}.png",
                                         f"{lab} render {stem}", cap) if stem in renders
                             else f'<td class="missing">no render ({why_none})</td>')
            grid.append(f"<tr><th>{html.escape(stem)}</th>{''.join(cells)}</tr>")
        parts.append(f'<table class="grid"><tr><th>name</th><th>training photo</th>{head}</tr>'
                     + "\n".join(grid) + "</table>")
    return parts


def photo_section(results: str | Path, scenes_dir: str | Path | None, runs: pd.DataFrame,
                  scenes: set[tuple[str, str]], images_dir: Path) -> list[str]:
    """HTML of the photo section for the runs of ``scenes`` (no held-out view); thumbnails and
    plots go to ``images_dir/photos/``. [] when no run belongs to those scenes."""
    results = Path(results)
    scenes_dir = Path(scenes_dir) if scenes_dir is not None else None
    mine = runs[[(ds, sc) in scenes for ds, sc in zip(runs["dataset"], runs["scene"])]] if len(runs) else runs
    if not len(mine):
        return []
    parts = ["<h2>Your photos: the model against the photos it was trained on</h2>",
             "<p>Every photo of these scenes trained. Beside each photo is the trained model's render of that "
             "photo's camera, and the PSNR between them: the <b>training-view fit</b>, how well the model "
             "reproduces a photo it has seen, not how well it renders a new view (no view was held out to "
             "measure that). Then the training curve, the cameras seen from above and the model's size.</p>"]
    for _, g in mine.groupby(["dataset", "scene", "n"], sort=True):
        parts += _group_section(results, scenes_dir, g, images_dir)
    return parts
