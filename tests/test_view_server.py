"""``python -m splat_train view``'s server: answers only the files of its view, read-only, on
127.0.0.1 by default; traversal in every spelling gets 404 and never a byte of another file."""

from __future__ import annotations

import http.client
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _view_scene import write_view_scene
from splat_train.view import cli, server

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def view(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("view")
    files = write_view_scene(tmp / "scene", n=20, width=32, height=24)
    secret = tmp / "secret.txt"
    secret.write_text("SECRET-CONTENT")
    (files["root"] / "link.ply").symlink_to(secret)
    routes = server.build_routes(files["model"], files["seed"],
                                 server.cameras_json(files["cameras"], files["test_cameras"]))
    srv = server.make_server(routes, port=0)
    server.serve_in_thread(srv)
    yield {"port": srv.server_port, "files": files, "secret": secret, "host": srv.server_address[0]}
    srv.shutdown()
    srv.server_close()


def _get(port: int, path: str, method: str = "GET") -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest(method, path, skip_accept_encoding=True)  # path sent byte for byte, unnormalised
    conn.endheaders()
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, body


def test_binds_loopback_by_default(view):
    assert server.DEFAULT_HOST == "127.0.0.1"
    assert view["host"] == "127.0.0.1"
    assert cli.parser().parse_args(["--model", "m.ply"]).host == "127.0.0.1"


def test_serves_the_view(view):
    status, body = _get(view["port"], "/")
    assert status == 200 and b"/viewer.js" in body and b"importmap" in body
    assert b"https://" not in body and b"http://" not in body  # nothing from a CDN
    assert _get(view["port"], "/model.ply")[1] == view["files"]["model"].read_bytes()
    assert _get(view["port"], "/seed.ply")[1] == view["files"]["seed"].read_bytes()
    cams = json.loads(_get(view["port"], "/cameras.json")[1])["cameras"]
    assert [c["role"] for c in cams] == ["train"] * 4 + ["test"] * 2
    c0 = cams[0]
    assert (c0["width"], c0["height"]) == (32, 24)
    assert c0["K"][0][2] != 16.0 and c0["K"][1][2] != 12.0  # the off-centre principal point travels
    assert np.asarray(c0["cam_from_world"]).shape == (3, 4)
    assert json.loads(_get(view["port"], "/view.json")[1]) == {"seed": True, "background": [0.0, 0.0, 0.0]}


@pytest.mark.parametrize("name", ["viewer.js", "shfix.js", "index.html"])
def test_page_has_no_remote_url(name):
    text = (server.STATIC_DIR / name).read_text()
    assert "https://" not in text and "http://" not in text


TRAVERSALS = [
    "/../secret.txt", "/..%2fsecret.txt", "/..%2Fsecret.txt", "/%2e%2e/secret.txt", "/%2e%2e%2fsecret.txt",
    "/..\\secret.txt", "/..%5csecret.txt", "//etc/passwd", "/etc/passwd", "/%2fetc%2fpasswd",
    "/static/../../secret.txt", "/vendor/../../../secret.txt", "/vendor/%2e%2e/%2e%2e/secret.txt",
    "/%252e%252e/secret.txt", "/model.ply/../secret.txt", "/model.ply%00", "/link.ply", "/scene/link.ply",
    "/server.py", "/static/index.html", "/npm/package.json", "/vendor/", "/vendor/three/package.json",
    "/..", "/.", "/%2e", "http://127.0.0.1/../secret.txt",
]


@pytest.mark.parametrize("path", TRAVERSALS)
def test_refuses_paths_outside_the_view(view, path):
    status, body = _get(view["port"], path)
    # an absolute URL carries its own Host (127.0.0.1, port 80): refused as another host's request
    assert status == (403 if path.startswith("http://") else 404), (path, status)
    assert b"SECRET" not in body and b"root:" not in body


def test_absolute_model_path_in_url_is_refused(view):
    status, body = _get(view["port"], "/" + str(view["files"]["model"]).lstrip("/"))
    assert status == 404
    status, body = _get(view["port"], str(view["secret"]))
    assert status == 404 and b"SECRET" not in body


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH"])
def test_read_only(view, method):
    assert _get(view["port"], "/model.ply", method)[0] == 405
    assert view["files"]["model"].is_file()


def test_head_has_no_body(view):
    status, body = _get(view["port"], "/model.ply", "HEAD")
    assert status == 200 and body == b""


def test_help_without_node_modules():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "splat_train", "view", "--help"], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "--model" in r.stdout and "--no-browser" in r.stdout


def test_view_says_how_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(server, "NODE_MODULES", tmp_path / "node_modules")
    rc = cli.main(["--model", str(tmp_path / "m.ply"), "--no-browser"])
    assert rc == 2
    assert "make install" in capsys.readouterr().err


def test_cli_serves_until_stopped(tmp_path):
    """`python -m splat_train view ... --port 0 --no-browser` prints its address and serves the view."""
    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    files = write_view_scene(tmp_path / "scene", n=10, width=32, height=24)
    # the trainer's record beside the model: the view clears to the colour it trained against
    (files["model"].parent / "train.json").write_text(json.dumps({"config": {"background": [0.25, 0.5, 0.75]}}))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "splat_train", "view", "--model", str(files["model"]),
                             "--cameras", str(files["cameras"]), "--port", "0", "--no-browser"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        line = proc.stdout.readline()
        assert "http://127.0.0.1:" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        assert _get(port, "/model.ply")[1] == files["model"].read_bytes()
        assert "on background 0.25,0.5,0.75 (" in line and "train.json" in line, line
        assert json.loads(_get(port, "/view.json")[1]) == {"seed": False, "background": [0.25, 0.5, 0.75]}
        assert _get(port, "/seed.ply")[0] == 404
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_background_is_the_models_unless_told(tmp_path, capsys):
    """The view clears to the train.json's colour, black without one; ``--background`` wins, in
    ``render``'s spelling, and a malformed one is one line and exit 2."""
    files = write_view_scene(tmp_path / "scene", n=10, width=32, height=24)
    model = str(files["model"])
    assert cli.view_background(model, None) == ((0.0, 0.0, 0.0), "default")
    tj = files["model"].parent / "train.json"
    tj.write_text(json.dumps({"config": {"background": [1, 1, 1]}}))
    assert cli.view_background(model, None) == ((1.0, 1.0, 1.0), str(tj))
    assert cli.view_background(model, "0.5,0,1") == ((0.5, 0.0, 1.0), "--background")
    for bad in ("1,1", "0,0,0,0", "a,b,c", "0,0,1.5", "nan,0,0", "-0.1,0,0"):
        with pytest.raises(ValueError, match="three numbers in"):
            cli.view_background(model, bad)
    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    assert cli.main(["--model", model, "--background", "2,0,0", "--no-browser", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "--background must be three numbers in [0, 1]" in err and "'2,0,0'" in err
