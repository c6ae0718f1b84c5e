"""The viewer in a real browser: headless Chromium with software WebGL (SwiftShader) opens a
small model at a training camera (off-centre principal point, SH degree 3 colour in every band,
base colours above 1, trained against a colour other than black) and its screenshot matches
``python -m splat_train render`` of that camera, the colour showing through where the model is
transparent; with the seed toggled on, the same camera shows the seed instead. The model's .splat
and .spz exports draw every Gaussian where the PLY does."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _view_scene import write_view_scene
from camio.images import read_image
from splat_train.view import cli, server
from splat_train.view.headless import Chromium, find_chromium

ROOT = Path(__file__).resolve().parents[1]
MIN_PSNR = 45.0  # measured 58 dB (SwiftShader); 37 dB without the SH re-encoding of shfix.js
# an export against the PLY it came from, SwiftShader: measured .splat 58 dB, .spz 33 dB (its SH
# bands at Spark's own precision, which shfix.js lifts only for a PLY: 45 dB with the PLY's at
# that precision too); the PLY without its SH bands 23 dB, a .spz left in its frame 12 dB (SH 0)
MIN_FORMAT_PSNR = 28.0
W, H = 160, 120
BACKGROUND = (0.2, 0.45, 0.7)  # what the model was trained against (its train.json)


def _skip_reason() -> str | None:
    if find_chromium() is None:
        return "no Chromium on this machine (Debian: apt-get install chromium; .ci/run installs it)"
    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        return str(e)
    return None


@pytest.mark.slow
@pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")
def test_browser_matches_render_at_a_training_camera(tmp_path):
    files = write_view_scene(tmp_path / "scene", n=400, width=W, height=H)
    (files["model"].parent / "train.json").write_text(json.dumps({"config": {"background": list(BACKGROUND)}}))
    name = "view01.png"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-m", "splat_train", "render", "--model", str(files["model"]),
                    "--cameras", str(files["cameras"]), "--out", str(tmp_path / "renders")],
                   check=True, env=env, cwd=ROOT, timeout=300, capture_output=True)
    ref = read_image(tmp_path / "renders" / name)[..., :3].astype(np.float64)

    cams = server.cameras_json(files["cameras"], files["test_cameras"])
    background = cli.view_background(str(files["model"]), None)[0]  # as `python -m splat_train view` does
    srv = server.make_server(server.build_routes(files["model"], files["seed"], cams, background), port=0)
    server.serve_in_thread(srv)
    try:
        with Chromium(W, H) as browser:
            browser.open(f"http://127.0.0.1:{srv.server_port}/?camera={name}&ui=0")
            browser.wait_for("window.viewerReady", timeout=240, error_expression="window.viewerError")
            assert browser.evaluate("window.viewerShFix['/model.ply']") == "applied"
            assert browser.evaluate("[document.getElementById('view').width, "
                                    "document.getElementById('view').height]") == [W, H]
            shot = read_image(browser.screenshot(tmp_path / "shot.png", W, H))[..., :3].astype(np.float64)
            # the seed toggle shows another cloud from the same camera
            browser.open(f"http://127.0.0.1:{srv.server_port}/?camera={name}&ui=0&seed=1")
            browser.wait_for("window.viewerReady", timeout=240, error_expression="window.viewerError")
            seed_shot = read_image(browser.screenshot(tmp_path / "seed.png", W, H))[..., :3].astype(np.float64)
    finally:
        srv.shutdown()
        srv.server_close()
    assert shot.shape == ref.shape
    assert ref.mean() > 0.05  # the model is in view
    # where no Gaussian reaches (a corner), both show the training colour
    np.testing.assert_allclose(ref[0, 0], BACKGROUND, atol=2 / 255)
    np.testing.assert_allclose(shot[0, 0], BACKGROUND, atol=2 / 255)
    psnr = 10 * np.log10(1.0 / np.mean((shot - ref) ** 2))
    print(f"browser vs render at {name}: PSNR {psnr:.2f} dB")
    assert psnr >= MIN_PSNR, psnr
    seed_psnr = 10 * np.log10(1.0 / np.mean((seed_shot - ref) ** 2))
    assert seed_shot.mean() > 0.01 and seed_psnr < 25.0, seed_psnr


@pytest.mark.slow
@pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")
def test_page_shows_the_snapshots_iteration_and_loads_a_newer_one(tmp_path):
    """`python -m splat_train view --model OUT` on a training run's folder: the page shows the
    snapshot's iteration and, when the trainer replaces it, loads the new one and its iteration."""
    from _view_scene import make_model
    from splat_train.training.snapshot import write_snapshot

    out = tmp_path / "out"
    write_snapshot(out, make_model(200, seed=1), 10)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "splat_train", "view", "--model", str(out), "--no-browser",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=ROOT)
    try:
        port = int(proc.stdout.readline().split("http://127.0.0.1:")[1].split("/")[0])
        with Chromium(W, H) as browser:
            browser.open(f"http://127.0.0.1:{port}/")
            browser.wait_for("window.viewerReady", timeout=240, error_expression="window.viewerError")
            assert browser.evaluate("window.viewerIteration") == 10
            assert browser.evaluate("document.getElementById('iteration').textContent") == "iteration 10"
            write_snapshot(out, make_model(300, seed=2), 20)
            browser.wait_for("window.viewerIteration === 20", timeout=120, error_expression="window.viewerError")
            assert browser.evaluate("document.getElementById('iteration').textContent") == "iteration 20"
            assert browser.evaluate("window.viewerModelVersion") == 2
            browser.wait_for("document.getElementById('status').textContent === 'ready: 300 Gaussians'",
                             timeout=120)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "Traceback" not in err, err


@pytest.mark.slow
@pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")
def test_page_draws_each_exported_format_where_the_ply_is(tmp_path):
    """`python -m splat_train view` on a model's .splat and .spz exports: the page draws every
    Gaussian of each, and at a training camera each lines up with the PLY's image: the .spz (SH
    degree 3, stored in the right-up-back frame, turned back by the page) with the PLY's, the
    .splat (no SH bands) with that of the PLY without its bands. The model sits off the cameras'
    centre, so a frame left turned shows it elsewhere (measured: 12 dB)."""
    from _view_scene import make_cameras, make_model
    from _viewer import Viewer
    from camio.colmap import write_text_model
    from camio.ply import write_gaussian_ply

    n, name = 150, "view01.png"
    c = make_model(n, seed=4, sh_degree=3)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)  # inside .spz's range
    c.sh_dc = np.clip(c.sh_dc, -1.5, 1.5)  # base colours inside [0, 1]: what .splat keeps
    c.means = c.means * 0.6 + np.array([0.35, 0.3, 0.0])  # off centre: up-down and left-right tell
    cams = write_text_model(tmp_path / "cams", make_cameras(W, H, 4))
    model = write_gaussian_ply(tmp_path / "train" / "model.ply", c)
    c.sh_rest = c.sh_rest[:, :0]
    dc_only = write_gaussian_ply(tmp_path / "dc" / "model.ply", c)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    shots = {}
    with Chromium(W, H) as browser:
        for key, fmt, src in (("ply", "ply", model), ("dc", "ply", dc_only), ("splat", "splat", model),
                              ("spz", "spz", model)):
            path = tmp_path / "share" / key / f"model.{fmt}"
            subprocess.run([sys.executable, "-m", "splat_train", "export", "--format", fmt, "--out", str(path),
                            str(src)], check=True, env=env, cwd=ROOT, timeout=120, capture_output=True)
            v = Viewer("--model", str(path), "--cameras", str(cams))
            try:
                browser.open(f"http://127.0.0.1:{v.port}/?camera={name}&ui=0")
                browser.wait_for("window.viewerReady", timeout=240, error_expression="window.viewerError")
                assert browser.evaluate("window.viewerModelType") == fmt
                assert browser.evaluate("document.getElementById('status').textContent") == f"ready: {n} Gaussians"
                shots[key] = read_image(browser.screenshot(tmp_path / f"{key}.png", W, H))[..., :3].astype(np.float64)
            finally:
                _, err = v.stop()
            assert "Traceback" not in err, err
    assert shots["ply"].mean() > 0.03  # the model is in view
    psnr = {f"{a} vs {b}": 10 * np.log10(1.0 / np.mean((shots[a] - shots[b]) ** 2))
            for a, b in (("spz", "ply"), ("splat", "dc"), ("dc", "ply"))}
    print(f"at {name}: " + ", ".join(f"{k} {v:.2f} dB" for k, v in psnr.items()))
    assert psnr["spz vs ply"] >= MIN_FORMAT_PSNR and psnr["splat vs dc"] >= MIN_FORMAT_PSNR, psnr
    assert psnr["dc vs ply"] < MIN_FORMAT_PSNR  # the SH bands show: the .spz kept them
