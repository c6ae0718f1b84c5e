"""``python -m splat_train view`` shows each format ``python -m splat_train export`` writes: a
model exported as .ply, .splat or .spz is served at ``/model.<type>``, exactly the file's bytes,
as a binary download, and ``/state.json`` names its type (Spark's ``fileType``); a file that is
not a model of its suffix's type, a suffix the viewer does not show, and a .spz without the
gsply package are each refused at the start in one line."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from _cli import ROOT, refused, run
from _view_scene import make_model
from _viewer import Viewer
from camio.ply import write_gaussian_ply
from splat_train.view import server
from splat_train.view.source import MODEL_TYPES

N = 30


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    """A tiny trained model and its export in each format, through the export command."""
    tmp = tmp_path_factory.mktemp("formats")
    c = make_model(N)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)  # inside .spz's range
    model = write_gaussian_ply(tmp / "train" / "model.ply", c)
    out = {}
    for fmt in MODEL_TYPES:
        out[fmt] = tmp / "share" / f"model.{fmt}"
        p = run(["-m", "splat_train", "export", "--format", fmt, "--out", str(out[fmt]), str(model)])
        assert p.returncode == 0, p.stdout + p.stderr
    return out


def _skip_without_viewer() -> None:
    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))


@pytest.mark.parametrize("fmt", MODEL_TYPES)
def test_the_viewer_serves_each_exported_format(exported, fmt):
    path = exported[fmt]
    v = Viewer("--model", str(path))
    try:
        r = v.get(f"/model.{fmt}")
        assert r.status == 200 and r.body == path.read_bytes()
        assert r.getheader("Content-Type") == "application/octet-stream"
        assert r.getheader("X-Model-Version") == "1"
        state = json.loads(v.get("/state.json").body)
        assert state["type"] == fmt and state["file"] == path.name and state["version"] == 1
        for other in MODEL_TYPES:  # one model, at one URL
            if other != fmt:
                assert v.get(f"/model.{other}").status == 404
    finally:
        _, err = v.stop()
    assert "Traceback" not in err, err
    assert f"serving {path} at" in v.line


def test_a_garbage_splat_is_refused_at_the_start(tmp_path):
    _skip_without_viewer()
    bad = tmp_path / "garbage.splat"
    bad.write_bytes(b"not a splat file\n" * 3)  # 51 bytes: no whole 32-byte record
    p = run(["-m", "splat_train", "view", "--no-browser", "--port", "0", "--model", str(bad)], timeout=60)
    refused(p, str(bad), "not a .splat file", "32-byte")


def test_a_splat_with_nan_positions_is_refused(tmp_path, exported):
    _skip_without_viewer()
    raw = bytearray(exported["splat"].read_bytes())
    raw[32:36] = np.float32(np.nan).tobytes()  # record 1's x
    bad = tmp_path / "nan.splat"
    bad.write_bytes(bytes(raw))
    p = run(["-m", "splat_train", "view", "--no-browser", "--port", "0", "--model", str(bad)], timeout=60)
    refused(p, str(bad), "not a .splat file", "1 of 30 records", "record 1")


def test_a_garbage_spz_is_refused_at_the_start(tmp_path, exported):
    _skip_without_viewer()
    bad = tmp_path / "torn.spz"
    bad.write_bytes(exported["spz"].read_bytes()[:100])  # a gzip stream cut short
    p = run(["-m", "splat_train", "view", "--no-browser", "--port", "0", "--model", str(bad)], timeout=60)
    refused(p, str(bad), "not a readable .spz file")


@pytest.mark.parametrize("name", ["model.obj", "model"])
def test_a_suffix_the_viewer_does_not_show_is_refused(tmp_path, exported, name):
    _skip_without_viewer()
    other = tmp_path / name
    other.write_bytes(exported["ply"].read_bytes())  # a PLY under another name is still refused
    p = run(["-m", "splat_train", "view", "--no-browser", "--port", "0", "--model", str(other)], timeout=60)
    refused(p, str(other), ".ply, .splat, .spz")


def test_a_spz_without_gsply_names_the_package(tmp_path, exported):
    _skip_without_viewer()
    block = tmp_path / "block"
    (block / "gsply").mkdir(parents=True)
    (block / "gsply" / "__init__.py").write_text("raise ImportError('blocked for the test', name='gsply')\n")
    env = {**os.environ, "PYTHONPATH": f"{block}{os.pathsep}{ROOT}"}
    p = subprocess.run([sys.executable, "-m", "splat_train", "view", "--no-browser", "--port", "0", "--model",
                        str(exported["spz"])], capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
    line = refused(p, str(exported["spz"]), "gsply", "pip install")
    assert "not a readable .spz file" not in line  # the file is fine: the package is missing


def test_a_served_splat_torn_later_is_not_served(tmp_path, exported):
    """The followed file is checked again by its own type's reader: a .splat cut mid-record after
    the start is not served (one warning naming the type); a whole one put there is, as version 2."""
    import time

    from splat_train.view.source import FOLLOW_POLL_S

    path = tmp_path / "model.splat"
    good = exported["splat"].read_bytes()
    path.write_bytes(good)
    v = Viewer("--model", str(path))
    try:
        path.write_bytes(good[:-5])  # a writer caught mid-file
        time.sleep(3 * FOLLOW_POLL_S)
        r = v.get("/model.splat")
        assert r.body == good and r.getheader("X-Model-Version") == "1"
        path.write_bytes(good[:32 * 10])  # ten whole records
        deadline = time.monotonic() + 20
        while (r := v.get("/model.splat")).getheader("X-Model-Version") == "1" and time.monotonic() < deadline:
            time.sleep(0.2)
        assert r.body == good[:32 * 10] and r.getheader("X-Model-Version") == "2"
    finally:
        _, err = v.stop()
    assert "is not a .splat file" in err and "still serving the last good model" in err, err
    assert "Traceback" not in err, err
