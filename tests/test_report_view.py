"""The report's viewer section: every trained run gets the exact ``splat_train view`` command
(its cameras, held-out cameras and seed) on its own port, and a link to that port."""

from __future__ import annotations

import html
import re
import shlex

from evaluation.reports.report_view import view_command, view_section
from splat_train.view import cli


def _run(root, name, refined=False, heldout=True):
    mode = root / "synthetic" / "cube" / "n3" / name / "gated"
    (mode / "train").mkdir(parents=True)
    (mode / "train" / "model.ply").write_bytes(b"ply")
    (mode / "bridge" / "sparse" / "0").mkdir(parents=True)
    (mode / "bridge" / "seed.ply").write_bytes(b"ply")
    if heldout:
        (mode / "align" / "sparse" / "0").mkdir(parents=True)
    if refined:
        (mode / "train" / "cameras_refined").mkdir()
    return mode


def test_each_run_has_its_command_and_link(tmp_path):
    a = _run(tmp_path, "oracle")
    b = _run(tmp_path, "vggt", refined=True, heldout=False)
    html_text = "\n".join(view_section(tmp_path))
    assert "http://127.0.0.1:8765/" in html_text and "http://127.0.0.1:8766/" in html_text
    assert "file://" in html_text  # says why a server is needed
    cmd_a = view_command(a / "train" / "model.ply", 8765)
    assert cmd_a[:4] == ["python", "-m", "splat_train", "view"]
    args = cli.parser().parse_args(cmd_a[4:])  # the command parses as the viewer's CLI
    assert args.cameras == str(a / "bridge" / "sparse") and args.test_cameras == str(a / "align" / "sparse")
    assert args.seed_ply == str(a / "bridge" / "seed.ply") and args.port == 8765
    cmd_b = view_command(b / "train" / "model.ply", 8766)
    args_b = cli.parser().parse_args(cmd_b[4:])
    assert args_b.cameras == str(b / "train" / "cameras_refined") and args_b.test_cameras is None
    # the command as written, wrapping only between arguments: each flag with its value in one
    # unbreakable span
    row = next(ln for ln in html_text.split("<tr>") if "8765/" in ln)
    code = re.search(r"<code>(.*?)</code>", row).group(1)
    assert html.unescape(re.sub(r"<[^>]+>", "", code)) == shlex.join(cmd_a)
    spans = [html.unescape(s) for s in re.findall(r'<span class="arg">(.*?)</span>', code)]
    assert f"--port 8765" in spans and f"--cameras {a / 'bridge' / 'sparse'}" in spans


def test_no_runs(tmp_path):
    assert "no trained model" in "".join(view_section(tmp_path))
