"""Nothing a user gives is misread: binary COLMAP models read exactly or refused, camera and
point values checked where they are read (file and line), PLY elements in any order, the
workflow's configuration, and a viewer that answers only its own address.

Model cases go through ``python -m evaluation pose`` (its ``main``), as in
tests/test_colmap_read_checks.py: exit non-zero, one error line naming the file, no traceback.
"""

from __future__ import annotations

import http.client
import os
import resource
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from camio.colmap import camera_problem, read_model, write_text_model
from camio.ply import read_gaussian_ply, write_gaussian_ply

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
sys.path.insert(0, str(ROOT / "workflow" / "scripts"))


def _model(root: Path) -> Path:
    from test_colmap_read_checks import _model as make

    return make(root)


def _pose(pred: Path, ref: Path, out: Path, capsys) -> tuple[int, list[str]]:
    from evaluation.__main__ import main

    rc = main(["pose", "--pred", str(pred), "--ref", str(ref), "--out", str(out)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, [ln for ln in err.splitlines() if " ERROR " in ln or " WARNING " in ln]


@pytest.fixture
def binary(tmp_path) -> Path:
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.read(str(_model(tmp_path / "txt")))
    out = tmp_path / "bin"
    out.mkdir()
    rec.write_binary(str(out))
    return out


# --- binary models -----------------------------------------------------------------------------

@pytest.mark.parametrize("cut", [2, 8, 16, 28])
def test_cameras_bin_cut_short_is_refused_naming_the_file(binary, tmp_path, capsys, cut):
    f = binary / "cameras.bin"
    f.write_bytes(f.read_bytes()[:-cut])
    rc, lines = _pose(binary, _model(tmp_path / "ref"), tmp_path / "pose.json", capsys)
    assert rc == 2 and len(lines) == 1 and str(f) in lines[0] and "truncated" in lines[0], lines


@pytest.mark.parametrize("fname, cut", [("points3D.bin", 48), ("points3D.bin", 3), ("images.bin", 20)])
def test_points_and_images_bin_cut_short_are_refused(binary, tmp_path, capsys, fname, cut):
    f = binary / fname
    f.write_bytes(f.read_bytes()[:-cut])
    rc, lines = _pose(binary, _model(tmp_path / "ref"), tmp_path / "pose.json", capsys)
    assert rc == 2 and len(lines) == 1 and str(f) in lines[0], lines


def test_a_huge_track_length_is_refused_before_anything_is_allocated(binary):
    """A track length of 2^40 (8 TB of track) in points3D.bin: refused in well under a second,
    the reader's memory bounded by the file's size."""
    from camio.colmap_bin import check_binary_model

    f = binary / "points3D.bin"
    raw = bytearray(f.read_bytes())
    off = 8 + 8 + 24 + 3 + 8  # count, then the first point's id, xyz, rgb, error
    raw[off:off + 8] = struct.pack("<Q", 1 << 40)
    f.write_bytes(bytes(raw))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ValueError, match="track of 1099511627776 entries"):
        check_binary_model(binary)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 50_000  # KiB


def test_a_huge_record_count_is_refused_before_the_walk(binary):
    from camio.colmap_bin import check_binary_model

    f = binary / "images.bin"
    raw = bytearray(f.read_bytes())
    raw[0:8] = struct.pack("<Q", 1 << 50)
    f.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="says 1125899906842624 images"):
        check_binary_model(binary)


def test_bytes_after_the_last_record_are_refused(binary):
    from camio.colmap_bin import check_binary_model

    with open(binary / "cameras.bin", "ab") as f:
        f.write(b"\0" * 5)
    with pytest.raises(ValueError, match="5 bytes follow the last record"):
        check_binary_model(binary)


def test_an_unknown_camera_model_id_is_refused(binary):
    from camio.colmap_bin import check_binary_model

    f = binary / "cameras.bin"
    raw = bytearray(f.read_bytes())
    raw[12:16] = struct.pack("<i", 99)
    f.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="unknown camera model id 99"):
        check_binary_model(binary)


def test_an_intact_binary_model_reads_like_its_text_model(binary, tmp_path):
    a, b = read_model(binary), read_model(tmp_path / "txt")
    assert a.names == b.names and np.allclose(a.points, b.points)
    assert all(np.allclose(x.K, y.K) and np.allclose(x.cam_from_world, y.cam_from_world)
               for x, y in zip(a.cameras, b.cameras))


def test_a_folder_with_both_models_reads_the_binary_one_and_says_so(binary, tmp_path, caplog):
    for f in (tmp_path / "txt").iterdir():
        shutil.copy(f, binary / f.name)
    with caplog.at_level("WARNING"):
        read_model(binary)
    assert any("both a binary and a text model" in r.message and "reading the binary one" in r.message
               for r in caplog.records)


def test_a_binary_model_missing_a_file_is_refused(binary):
    (binary / "images.bin").unlink()
    with pytest.raises(ValueError, match="holds cameras.bin but not images.bin"):
        read_model(binary)


def test_duplicate_image_names_in_a_binary_model_are_refused(tmp_path):
    import pycolmap

    from camio.colmap_bin import check_binary_model

    model = _model(tmp_path / "txt")
    lines = (model / "images.txt").read_text().replace("v1.png", "v0.png")
    (model / "images.txt").write_text(lines)
    rec = pycolmap.Reconstruction()
    rec.read(str(model))
    out = tmp_path / "bin"
    out.mkdir()
    rec.write_binary(str(out))
    with pytest.raises(ValueError, match="'v0.png' appears twice"):
        check_binary_model(out)


# --- values checked where they are read ------------------------------------------------------

def _edit_camera(model: Path, params: str, kind: str = "PINHOLE") -> None:
    f = model / "cameras.txt"
    lines = f.read_text().splitlines()
    lines[3] = f"1 {kind} 32 24 {params}"
    f.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("params, kind, needle", [
    ("30 30 400 12", "PINHOLE", "principal point (400, 12)"),
    ("30 30 16 -90", "PINHOLE", "principal point (16, -90)"),
    ("30 30 16 12 1e12 0 0 0", "OPENCV", "shrinks the view"),
    ("30 30 16 12 -2 0 0 0", "OPENCV", "not invertible"),
    ("30 16 12 -5", "SIMPLE_RADIAL", "not invertible"),
])
def test_camera_values_outside_their_range_are_refused_with_file_and_line(tmp_path, capsys, params, kind, needle):
    model = _model(tmp_path / "m")
    _edit_camera(model, params, kind)
    rc, lines = _pose(model, _model(tmp_path / "ref"), tmp_path / "pose.json", capsys)
    assert rc == 2 and len(lines) == 1, lines
    assert f"{model / 'cameras.txt'}:4:" in lines[0] and needle in lines[0], lines


def test_a_principal_point_just_outside_the_image_is_read_with_a_warning(tmp_path, caplog):
    model = _model(tmp_path / "m")
    _edit_camera(model, "30 30 40 12")
    with caplog.at_level("WARNING"):
        m = read_model(model)
    assert m.cameras[0].K[0, 2] == 40
    assert any("cameras.txt:4" in r.getMessage() and "outside its 32x24 image" in r.getMessage()
               for r in caplog.records)


def test_a_bad_principal_point_in_a_binary_model_is_refused(tmp_path):
    import pycolmap

    model = _model(tmp_path / "m")
    rec = pycolmap.Reconstruction()
    rec.read(str(model))
    cam = rec.cameras[1]
    cam.params = [30.0, 30.0, 5000.0, 12.0]
    rec.cameras[1] = cam
    out = tmp_path / "bin"
    out.mkdir()
    rec.write_binary(str(out))
    with pytest.raises(ValueError, match=r"cameras.bin: camera 1 \(PINHOLE\) has the principal point \(5000, 12\)"):
        read_model(out)


def test_ordinary_distortion_passes():
    for model, params in [("OPENCV", [500, 500, 320, 240, -0.3, 0.1, 1e-3, -1e-3]),
                          ("OPENCV_FISHEYE", [300, 300, 320, 240, 0.05, 0.01, 0, 0]),
                          ("FULL_OPENCV", [500, 500, 320, 240, 0.1, 0.01, 0, 0, 0, 0, 0, 0]),
                          ("SIMPLE_RADIAL", [500, 320, 240, 0.05]), ("RADIAL", [500, 320, 240, -0.1, 0.02])]:
        assert camera_problem(model, 640, 480, params) == (None, None), model


@pytest.mark.parametrize("rgb", ["300 0 0", "-5 0 0", "1.5 0 0"])
def test_point_colours_outside_0_255_are_refused_with_file_and_line(tmp_path, capsys, rgb):
    model = _model(tmp_path / "m")
    f = model / "points3D.txt"
    lines = f.read_text().splitlines()
    t = lines[3].split(" ")
    t[4:7] = rgb.split()
    lines[3] = " ".join(t)
    f.write_text("\n".join(lines) + "\n")
    rc, errs = _pose(model, _model(tmp_path / "ref"), tmp_path / "pose.json", capsys)
    assert rc == 2 and len(errs) == 1 and f"{f}:4:" in errs[0] and "colour" in errs[0], errs


@pytest.mark.parametrize("what", ["image_name", "image_id", "camera_id", "point_id"])
def test_a_duplicate_in_a_text_model_is_refused_with_its_line(tmp_path, capsys, what):
    model = _model(tmp_path / "m")
    if what == "image_name":
        f = model / "images.txt"
        f.write_text(f.read_text().replace("v1.png", "v0.png"))
    elif what == "image_id":
        f = model / "images.txt"
        lines = f.read_text().splitlines()
        k = [i for i, ln in enumerate(lines) if ln.endswith("v1.png")][0]
        lines[k] = "1" + lines[k][1:]
        f.write_text("\n".join(lines) + "\n")
    elif what == "camera_id":
        f = model / "cameras.txt"
        lines = f.read_text().splitlines()
        f.write_text("\n".join(lines[:3] + ["1 PINHOLE 32 24 31 31 16 12"] + lines[3:]).replace(
            "# Number of cameras: 1", "# Number of cameras: 2") + "\n")
    else:
        f = model / "points3D.txt"
        lines = f.read_text().splitlines()
        lines[4] = "1" + lines[4][1:]
        f.write_text("\n".join(lines) + "\n")
    rc, errs = _pose(model, _model(tmp_path / "ref"), tmp_path / "pose.json", capsys)
    assert rc == 2 and len(errs) == 1 and str(f) in errs[0] and ("twice" in errs[0]), errs


# --- PLY ---------------------------------------------------------------------------------------

def test_a_ply_with_another_element_before_vertex_is_read_exactly(tmp_path):
    from _view_scene import make_model

    cloud = make_model(20, sh_degree=1)
    plain = write_gaussian_ply(tmp_path / "a.ply", cloud)
    raw = plain.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    extra = b"element camera 1\nproperty float view_px\nproperty uchar flag\nelement face 2\n" \
            b"property list uchar int vertex_indices\n"
    head = head.replace(b"element vertex", extra + b"element vertex", 1)
    # the header order is camera, face, vertex: their records come first in the body
    pre = struct.pack("<fB", 1.5, 7) + struct.pack("<B3i", 3, 0, 1, 2) + struct.pack("<B4i", 4, 0, 1, 2, 3)
    (tmp_path / "b.ply").write_bytes(head + b"end_header\n" + pre + body)
    a, b = read_gaussian_ply(plain), read_gaussian_ply(tmp_path / "b.ply")
    for k in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


@pytest.mark.parametrize("header, needle", [
    (b"ply\nformat binary_little_endian 1.0\nelement vertex x\nproperty float x\nend_header\n", "element NAME COUNT"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n",
     "appears twice"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quaternion x\nend_header\n", "unsupported"),
    (b"ply\nformat binary_little_endian 1.0\nelement face 5\nproperty list uchar int i\nelement vertex 1\n"
     b"property float x\nend_header\n\x09", "truncated"),
])
def test_a_damaged_ply_header_is_one_clear_error(tmp_path, header, needle):
    from camio.ply import PlyFormatError

    f = tmp_path / "x.ply"
    f.write_bytes(header)
    with pytest.raises(PlyFormatError, match=needle):
        read_gaussian_ply(f)


# --- workflow configuration ----------------------------------------------------------------------

@pytest.mark.parametrize("value, needle", [('"/"', "root"), ('""', "empty"), ('"/../.."', "root")])
def test_results_at_the_root_or_empty_is_refused(tmp_path, value, needle):
    cfg = tmp_path / "c.yaml"
    cfg.write_text((ROOT / "config.yaml").read_text() + f"\n# override\n")
    proc = subprocess.run([sys.executable, str(ROOT / "workflow/scripts/check_config.py"), str(cfg),
                           "--set", f"results={value}"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


@pytest.mark.parametrize("value, needle", [(".", "which is or holds the repository"),
                                           ("..", "which is or holds the repository"),
                                           (str(ROOT), "which is or holds the repository"),
                                           ("camio", "in camio/, which its .gitignore does not set aside"),
                                           ("docs/out", "in docs/, which its .gitignore does not set aside"),
                                           ("results/../workflow", "in workflow/"),
                                           ("~/out", "in camio/")])
def test_results_in_the_repository_is_refused_and_tilde_is_expanded(tmp_path, value, needle):
    """``results: .`` (or the repository, or a folder of its own) would plan the outputs among
    its code; ``~`` is the user's home (here the repository's camio/), not a folder named ``~``."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text((ROOT / "config.yaml").read_text().replace("\nresults: results\n", f"\nresults: '{value}'\n"))
    env = {**os.environ, "HOME": str(ROOT / "camio")}
    proc = subprocess.run([sys.executable, str(ROOT / "workflow/scripts/check_config.py"), str(cfg)],
                          capture_output=True, text=True, timeout=60, cwd=ROOT, env=env)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    listing = lambda: [sorted(p.name for p in d.iterdir() if not p.name.startswith(".")) for d in (ROOT, ROOT / "camio")]  # noqa: E731
    before = listing()
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "1", "--configfile", str(cfg)],
                          capture_output=True, text=True, cwd=ROOT, timeout=120, env=env)
    text = proc.stdout + proc.stderr
    errors = [ln for ln in text.splitlines() if "config error" in ln]
    assert proc.returncode == 2 and len(errors) == 1 and needle in errors[0] and "Traceback" not in text, text[-2000:]
    assert listing() == before  # nothing planned among the repository's files


def test_results_folders_the_repository_ignores_and_home_are_accepted(tmp_path, monkeypatch):
    import check_config
    import yaml

    monkeypatch.chdir(ROOT)
    monkeypatch.setenv("HOME", str(tmp_path))
    base = yaml.safe_load((ROOT / "config.yaml").read_text())
    for value in ("results", "results/x", ".test/results", "results_photos/mine", str(tmp_path / "r"), "~/r"):
        assert check_config.config_problems({**base, "results": value}) == [], value


@pytest.mark.parametrize("text, line, key", [
    ("views: [3]\nresults: r\nviews: [6]\n", 3, "views"),
    ("datasets:\n  a:\n    x: 1\n  a:\n    y: 2\n", 4, "a"),
])
def test_a_key_given_twice_is_refused_with_its_line(tmp_path, text, line, key):
    import check_config

    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=rf"c.yaml:{line}: the key '{key}' is given twice"):
        check_config.read_yaml(f)
    proc = subprocess.run([sys.executable, str(ROOT / "workflow/scripts/check_config.py"), str(f)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and f"c.yaml:{line}:" in proc.stderr and "Traceback" not in proc.stderr


def test_the_workflow_refuses_a_duplicate_key_before_planning(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text((ROOT / "config.yaml").read_text() + "\nresults: elsewhere\n")
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "1", "--configfile", str(cfg)],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "the key 'results' is given twice" in text and "Traceback" not in text, text[-2000:]


# --- the viewer ----------------------------------------------------------------------------------

def test_host_rule():
    from splat_train.view.server import host_allowed

    for ok in ("127.0.0.1:8765", "localhost:8765", "[::1]:8765", "LOCALHOST:8765"):
        assert host_allowed(ok, "127.0.0.1", 8765), ok
    assert host_allowed("192.168.1.5:8765", "192.168.1.5", 8765)
    for bad in ("evil.example:8765", "127.0.0.1:80", "127.0.0.1", "", None, "localhost:8765:1", "[::1]x",
                "192.168.1.6:8765", "localhost.evil.example:8765", "127.0.0.1:+8765"):
        assert not host_allowed(bad, "192.168.1.5", 8765), bad


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    from _view_scene import write_view_scene

    return write_view_scene(tmp_path_factory.mktemp("view"), n=40, width=32, height=24)


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _serve(args: list[str]) -> subprocess.Popen:
    """The viewer started as a non-interactive shell starts `cmd &`: with SIGINT ignored, which
    Python then leaves ignored unless the program installs its own handler."""
    from splat_train.view import server

    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    return subprocess.Popen([sys.executable, "-m", "splat_train", "view", "--no-browser", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV,
                            preexec_fn=_ignore_sigint)


def _get(port: int, host: str | None) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", "/model.ply", skip_host=True, skip_accept_encoding=True)
    if host is not None:
        conn.putheader("Host", host)
    conn.endheaders()
    status = conn.getresponse().status
    conn.close()
    return status


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_viewer_answers_only_its_own_host_and_stops_quietly(scene, sig):
    proc = _serve(["--model", str(scene["model"]), "--cameras", str(scene["cameras"]), "--port", "0"])
    try:
        line = proc.stdout.readline()
        port = int(line.split("127.0.0.1:")[1].split("/")[0])
        assert _get(port, f"127.0.0.1:{port}") == 200 and _get(port, f"localhost:{port}") == 200
        assert _get(port, f"attacker.example:{port}") == 403  # DNS rebinding
        assert _get(port, None) == 403
    finally:
        proc.send_signal(sig)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # it did not stop: fail, leaving no server behind
            proc.kill()
            proc.communicate()
            raise
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "***" not in err and "SIGTERM" not in err, err


def test_viewer_warns_when_it_serves_the_network(scene):
    proc = _serve(["--model", str(scene["model"]), "--host", "0.0.0.0", "--port", "0"])
    try:
        assert "0.0.0.0" in proc.stdout.readline()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "warning: --host 0.0.0.0 serves the model to the network" in err


@pytest.mark.parametrize("case", ["not_ply", "link_to_text", "port_low", "port_high", "seed_not_ply"])
def test_viewer_bad_input_is_one_line(scene, tmp_path, case):
    from splat_train.view import cli, server

    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    text = tmp_path / "passwd.ply"  # text under a model's suffix (a file without one: test_view_formats.py)
    text.write_text("root:x:0:0:root:/root:/bin/bash\n")
    link = tmp_path / "model.ply"
    link.symlink_to(text)
    args = {"not_ply": ["--model", str(text)], "link_to_text": ["--model", str(link)],
            "port_low": ["--model", str(scene["model"]), "--port", "-1"],
            "port_high": ["--model", str(scene["model"]), "--port", "70000"],
            "seed_not_ply": ["--model", str(scene["model"]), "--seed-ply", str(text)]}[case]
    proc = _serve(args)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert ("not a 3DGS PLY" in err) if "port" not in case else ("not a port" in err)


# --- no traceback where a user meets these ---------------------------------------------------------

def test_convert_refuses_an_image_name_that_is_not_utf8(tmp_path):
    from PIL import Image

    src = tmp_path / "src"
    src.mkdir()
    for name in (b"a.png", b"b.png", b"c.png", b"bad\xff.png"):
        Image.fromarray(np.full((12, 16, 3), 90, np.uint8)).save(os.fsdecode(os.fsencode(src) + b"/" + name))
    proc = subprocess.run([sys.executable, "-m", "camio", "convert", "--src", str(src), "--out", str(tmp_path / "o"),
                           "--n", "1"], capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "not UTF-8" in proc.stderr and not (tmp_path / "o").exists()


def test_the_workflow_refuses_a_scene_path_that_does_not_exist_in_one_line(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"results: {tmp_path / 'r'}\ndatasets:\n  mine:\n    scenes:\n      room:\n"
                   f"        path: {tmp_path / 'nowhere'}\nviews: [3]\ninitialisers: [colmap]\n")
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-n", "--cores", "1", "--configfile", str(cfg)],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "Traceback" not in text, text[-2000:]
    assert f"config error: datasets.mine.scenes.room: the scene path {tmp_path / 'nowhere'} does not exist" in text


def test_a_full_disk_while_writing_a_checkpoint_is_one_oserror(tmp_path, monkeypatch):
    import torch

    from splat_train.training import checkpoint

    def full(obj, f):
        raise RuntimeError("[enforce fail at inline_container.cc:626] . unexpected pos 128 vs 64")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(OSError, match="cannot write the checkpoint .*the previous checkpoint is intact"):
        checkpoint.save_checkpoint(tmp_path, 10, {"x": 1})
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # no temporary left
