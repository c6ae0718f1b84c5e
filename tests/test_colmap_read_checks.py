"""Cameras checked at read time (camio.colmap.read_model), through a stage command.

Each hostile text model goes through ``python -m evaluation pose`` (its ``main``): exit
non-zero, one error line that names the file and the line, never pycolmap's own check
message; point ids missing from points3D.txt are dropped with a warning giving their count;
an image name with spaces is refused (COLMAP's text reader keeps it only up to the first
space), never read cut.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from camio.cameras import Camera, look_at
from camio.colmap import read_model, write_text_model


def _model(root: Path, n: int = 3) -> Path:
    cams = []
    for i, a in enumerate(np.linspace(-0.4, 0.4, n)):
        K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
        eye = np.array([3 * np.sin(a), 0.2 * i, -3 * np.cos(a)])
        cams.append(Camera(f"v{i}.png", 32, 24, K, look_at(eye, np.zeros(3))[:3]))
    pts = np.random.default_rng(0).uniform(-1, 1, (5, 3))
    obs = {c.name: (np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([0, 1])) for c in cams}
    return write_text_model(root, cams, pts, observations=obs)


def _edit(f: Path, line_no: int, fn) -> None:
    lines = f.read_text().splitlines()
    lines[line_no - 1] = fn(lines[line_no - 1])
    f.write_text("\n".join(lines) + "\n")


def _first_image_line(f: Path) -> int:
    return next(i for i, ln in enumerate(f.read_text().splitlines(), 1) if not ln.startswith("#"))


def _set_tok(k: int, v: str):
    def fn(line: str) -> str:
        t = line.split(" ")
        t[k] = v
        return " ".join(t)
    return fn


CASES = {
    "negative_focal": ("cameras.txt", 4, "focal length -30"),
    "zero_focal": ("cameras.txt", 4, "focal length 0"),
    "nan_pose": ("images.txt", 1, "not finite"),
    "zero_quaternion": ("images.txt", 0, "zero quaternion"),
    "undefined_camera": ("images.txt", 8, "uses camera 7"),
    "name_with_spaces": ("images.txt", 9, "contains spaces"),
}


def _damage(model: Path, case: str) -> tuple[Path, int]:
    imgs = model / "images.txt"
    first = _first_image_line(imgs)
    if case == "negative_focal":
        _edit(model / "cameras.txt", 4, _set_tok(4, "-30.0"))
        return model / "cameras.txt", 4
    if case == "zero_focal":
        _edit(model / "cameras.txt", 4, _set_tok(4, "0"))
        return model / "cameras.txt", 4
    if case == "nan_pose":
        _edit(imgs, first, _set_tok(5, "nan"))
    elif case == "zero_quaternion":
        _edit(imgs, first, lambda ln: " ".join(ln.split(" ")[:1] + ["0", "0", "0", "0"] + ln.split(" ")[5:]))
    elif case == "undefined_camera":
        _edit(imgs, first, _set_tok(8, "7"))
    elif case == "name_with_spaces":
        _edit(imgs, first, _set_tok(9, "my vue 0.png"))
    return imgs, first


@pytest.mark.parametrize("case", sorted(CASES))
def test_pose_cli_names_file_and_line_of_a_bad_camera(tmp_path, capsys, case):
    from evaluation.__main__ import main

    ref = _model(tmp_path / "ref")
    pred = _model(tmp_path / "pred")
    f, line = _damage(pred, case)
    rc = main(["pose", "--pred", str(pred), "--ref", str(ref), "--out", str(tmp_path / "pose.json")])
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if " ERROR " in ln]
    assert rc != 0 and len(errors) == 1 and "Traceback" not in err, err
    assert f"{f}:{line}:" in errors[0] and CASES[case][2] in errors[0], errors[0]
    assert "Check failed" not in err and "Rig with ID" not in err
    assert not (tmp_path / "pose.json").exists()
    if case == "name_with_spaces":
        assert "'my vue 0.png'" in errors[0] and "'my_vue_0.png'" in errors[0]


def test_missing_point_ids_are_dropped_with_a_count(tmp_path, caplog):
    model = _model(tmp_path / "m")
    pts = model / "points3D.txt"
    lines = pts.read_text().splitlines()
    pts.write_text("\n".join(ln for ln in lines if not ln.startswith(("2 ", "# Number"))) + "\n")  # drop point 2
    with caplog.at_level("WARNING"):
        m = read_model(model)
    assert "3 observations name point ids" in caplog.text
    assert all(len(idx) == 1 for _, idx in m.observations.values())


def test_missing_point_ids_through_posed_cli_no_keyerror(tmp_path, capsys):
    """``evaluation pose`` on a model whose tracks name a deleted point: reads, no KeyError."""
    from evaluation.__main__ import main

    ref = _model(tmp_path / "ref")
    pred = _model(tmp_path / "pred")
    pts = pred / "points3D.txt"
    pts.write_text("\n".join(ln for ln in pts.read_text().splitlines() if not ln.startswith(("1 ", "# Number"))) + "\n")
    rc = main(["pose", "--pred", str(pred), "--ref", str(ref), "--out", str(tmp_path / "pose.json")])
    err = capsys.readouterr().err
    assert rc == 0 and "observations name point ids" in err and "KeyError" not in err, err


def test_cameras_only_model_reads_without_points3d(tmp_path, caplog):
    model = _model(tmp_path / "m")
    (model / "points3D.txt").unlink()
    with caplog.at_level("WARNING"):
        m = read_model(model)
    assert len(m.cameras) == 3 and len(m.points) == 0 and "reading the cameras only" in caplog.text


def test_binary_model_with_a_negative_focal_is_refused_naming_the_folder(tmp_path, capsys):
    """A binary model has no lines to name: the check on what pycolmap read names the folder."""
    import pycolmap

    from evaluation.__main__ import main

    ref = _model(tmp_path / "ref")
    rec = pycolmap.Reconstruction()
    rec.read(str(_model(tmp_path / "txt")))
    cam = rec.cameras[1]
    cam.params = [-30.0, 30.0, 16.0, 12.0]
    rec.cameras[1] = cam
    binary = tmp_path / "bin"
    binary.mkdir()
    rec.write_binary(str(binary))
    rc = main(["pose", "--pred", str(binary), "--ref", str(ref), "--out", str(tmp_path / "pose.json")])
    err = capsys.readouterr().err
    line, = [ln for ln in err.splitlines() if " ERROR " in ln]
    assert rc != 0 and str(binary) in line and "camera 1" in line and "focal" in line, line
