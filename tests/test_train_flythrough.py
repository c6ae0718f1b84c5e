"""``python -m splat_train render --path orbit|interpolate --video out.mp4``: one video frame per
path step (splat_train.flythrough, camio.campath, camio.video)."""

from __future__ import annotations

import os
import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pytest

from _cli import ROOT, refused, run
from _view_scene import write_view_scene
from camio import Camera
from camio.cameras import look_at
from camio.colmap import write_text_model


def _frames(path) -> list[np.ndarray]:
    reader = imageio.get_reader(str(path), format="FFMPEG")
    try:
        return [f for f in reader]
    finally:
        reader.close()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # 41 x 31 cameras: the video is rendered at 40 x 30 (H.264 needs even sizes)
    return write_view_scene(tmp_path_factory.mktemp("fly"), n=150, width=41, height=31)


def _render(scene, out, *extra):
    return run(["-m", "splat_train", "render", "--model", str(scene["model"]), "--cameras", str(scene["cameras"]),
                "--video", str(out), *extra])


def test_interpolate_video_has_one_frame_per_step(scene, tmp_path):
    out = tmp_path / "fly.mp4"
    p = _render(scene, out, "--path", "interpolate", "--frames", "4")
    assert p.returncode == 0, p.stderr[-2000:]
    frames = _frames(out)
    assert len(frames) == (4 - 1) * 4 + 1  # 4 cameras, 4 frames per pair, the last camera closing it
    assert frames[0].shape == (30, 40, 3)
    assert max(f.mean() for f in frames) > 5  # the model is in view, not a black video


def test_orbit_video_has_one_frame_per_step(scene, tmp_path):
    out = tmp_path / "orbit.mp4"
    p = _render(scene, out, "--path", "orbit", "--frames", "9", "--width", "64", "--height", "48",
                "--fps", "12")
    assert p.returncode == 0, p.stderr[-2000:]
    frames = _frames(out)
    assert len(frames) == 9
    assert frames[0].shape == (48, 64, 3)
    assert min(f.mean() for f in frames) > 5  # the centre stays in view all the way round
    assert "frames: 9" in p.stdout


def test_video_refusals(scene, tmp_path):
    refused(_render(scene, tmp_path / "a.mp4"), "--path")
    p = run(["-m", "splat_train", "render", "--model", str(scene["model"]), "--cameras", str(scene["cameras"]),
             "--path", "orbit"])
    refused(p, "--video")
    refused(_render(scene, tmp_path / "b.mp4", "--path", "orbit", "--frames", "0"), "--frames")
    # cameras side by side looking the same way: nothing to orbit, and no file is left
    K = np.array([[40.0, 0, 20], [0, 40, 15], [0, 0, 1]])
    cams = [Camera(f"f{i}.png", 40, 30, K, look_at(np.array([0.4 * i, 0, -3]), np.array([0.4 * i, 0, 0])))
            for i in range(3)]
    flat = write_text_model(tmp_path / "flat", cams)
    p = run(["-m", "splat_train", "render", "--model", str(scene["model"]), "--cameras", str(flat),
             "--path", "orbit", "--video", str(tmp_path / "c.mp4")])
    refused(p, "--path interpolate")
    assert not (tmp_path / "c.mp4").exists()


def test_video_without_imageio_names_the_package(scene, tmp_path):
    block = tmp_path / "block"
    (block / "imageio").mkdir(parents=True)
    (block / "imageio" / "__init__.py").write_text("raise ImportError('blocked for the test', name='imageio')\n")
    env = {**os.environ, "PYTHONPATH": f"{block}{os.pathsep}{ROOT}"}
    p = subprocess.run([sys.executable, "-m", "splat_train", "render", "--model", str(scene["model"]),
                        "--cameras", str(scene["cameras"]), "--path", "orbit", "--video", str(tmp_path / "v.mp4")],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    refused(p, "imageio", "pip install")
    assert not (tmp_path / "v.mp4").exists()
