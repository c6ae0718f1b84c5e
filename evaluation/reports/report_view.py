"""The report's "Look at the trained models" section: one ``python -m splat_train view`` command
and link per trained run.

A browser blocks ``fetch`` from ``file://``, so the report cannot open a model itself: each run
gets its own port, the command that serves it there, and a link to that address.
"""

from __future__ import annotations

import html
from pathlib import Path

from evaluation.reports.markup import command_html
from runtime.view_defaults import VIEW_HOST as DEFAULT_HOST, VIEW_PORT as DEFAULT_PORT

# R/{dataset}/{scene}/n{n}/{init}/{mode}/train/model.ply (workflow/rules/common.smk)
MODEL_GLOB = "*/*/n*/*/*/train/model.ply"


def view_command(model: Path, port: int) -> list[str]:
    """The viewer command of one run: its training cameras (refined ones when trained with pose
    refinement), its held-out cameras in the model frame and its seed, where they exist."""
    mode = model.parent.parent
    cmd = ["python", "-m", "splat_train", "view", "--model", str(model)]
    refined = model.parent / "cameras_refined"
    train_cams = refined if refined.is_dir() else mode / "bridge" / "sparse"
    if train_cams.is_dir():
        cmd += ["--cameras", str(train_cams)]
    for test in (mode / "align_refined" / "sparse", mode / "align" / "sparse"):
        if test.is_dir():
            cmd += ["--test-cameras", str(test)]
            break
    if (mode / "bridge" / "seed.ply").is_file():
        cmd += ["--seed-ply", str(mode / "bridge" / "seed.ply")]
    return cmd + ["--port", str(port)]


def view_section(results: str | Path) -> list[str]:
    """HTML paragraphs: how to open each trained model in the browser viewer."""
    results = Path(results).resolve()
    models = sorted(results.glob(MODEL_GLOB))
    parts = ["<h2>Look at the trained models</h2>"]
    if not models:
        return parts + ["<p>(no trained model in this results tree)</p>"]
    parts.append("<p>Browsers do not load models from a <code>file://</code> page, so each model is served "
                 "by a small local server: run a row's command (in this project's environment; "
                 "<code>make install</code> installs the viewer), then open its link. The page draws the "
                 "training cameras green and the held-out ones orange, can jump to any of them and "
                 "toggles the seed.</p>")
    rows = []
    for i, model in enumerate(models):
        port = DEFAULT_PORT + i
        label = "/".join(model.relative_to(results).parts[:-2])
        url = f"http://{DEFAULT_HOST}:{port}/"
        rows.append(f'<tr><td>{html.escape(label)}</td><td><a href="{url}">{url}</a></td>'
                    f"<td><code>{command_html(view_command(model, port))}</code></td></tr>")
    parts.append("<table><tr><th>run</th><th>view</th><th>command</th></tr>" + "".join(rows) + "</table>")
    return parts
