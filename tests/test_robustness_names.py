"""Names read from files never lead a command outside its folders (runtime.names, the one rule).

Each case runs the command a user runs (``python -m ...`` in a subprocess) on a tiny input
whose file names an image ``../victim.png``, an absolute path, or two images one render would
share, and checks: exit 2, one error line naming the file, no traceback, no ``--out`` made and
the file outside it (``victim.png``) byte for byte.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from camio import Camera
from camio.colmap import write_text_model
from camio.images import write_image

from _cli import refused as _refused
from _cli import run as _run

VICTIM = b"a user's file beside --out"


def _victim(tmp_path: Path) -> Path:
    victim = tmp_path / "victim.png"
    victim.write_bytes(VICTIM)
    return victim


def _untouched(tmp_path: Path, out: Path, victim: Path, before: set[str]) -> None:
    """Nothing written: no --out, the victim intact, no new file anywhere under tmp_path."""
    assert not out.exists()
    assert victim.read_bytes() == VICTIM
    assert {str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")} == before


def _listing(tmp_path: Path) -> set[str]:
    return {str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")}


def _cameras(names: list[str], width: int = 16, height: int = 12) -> list[Camera]:
    from _view_scene import make_cameras

    return [Camera(n, c.width, c.height, c.K, c.cam_from_world)
            for n, c in zip(names, make_cameras(width, height, len(names)))]


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    from _view_scene import make_model
    from camio.ply import write_gaussian_ply

    return write_gaussian_ply(tmp_path_factory.mktemp("model") / "model.ply", make_model(50))


# --- COLMAP image names -> splat_train render ----------------------------------------------------

@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
@pytest.mark.parametrize("name", ["../victim.png", "renders/../../victim.png", "sub/v1.png"])
def test_render_refuses_a_model_image_name_that_leaves_out(model, tmp_path, name, binary):
    """A model naming ``../victim.png`` made ``render`` write over the file beside ``--out``."""
    victim = _victim(tmp_path)
    cams = write_text_model(tmp_path / "cams", _cameras(["v0.png", name]))
    where = "images.txt:"
    if binary:
        import pycolmap

        rec = pycolmap.Reconstruction()
        rec.read(str(cams))
        (tmp_path / "bin").mkdir()
        rec.write_binary(str(tmp_path / "bin"))
        cams, where = tmp_path / "bin", "images.bin"
    out = tmp_path / "out"
    before = _listing(tmp_path)
    proc = _run(["-m", "splat_train", "render", "--model", str(model), "--cameras", str(cams), "--out", str(out)])
    _refused(proc, where, repr(name), "not a plain file name")
    _untouched(tmp_path, out, victim, before)


def test_render_refuses_two_images_that_differ_only_by_extension(model, tmp_path):
    """``v0.png`` and ``v0.jpg`` would both render to ``v0.png``: one clear error, not one file."""
    cams = write_text_model(tmp_path / "cams", _cameras(["v0.png", "v0.jpg", "v1.png"]))
    out = tmp_path / "out"
    victim = _victim(tmp_path)
    before = _listing(tmp_path)
    proc = _run(["-m", "splat_train", "render", "--model", str(model), "--cameras", str(cams), "--out", str(out)])
    _refused(proc, str(cams), "'v0.jpg' and 'v0.png' differ only by their extension", "'v0.png'")
    _untouched(tmp_path, out, victim, before)


# --- predictions.npz image_names -> the Bridge, the bundle-adjustment step ----------------------

def _predictions(path: Path, names: list[str]) -> Path:
    from bridge.synthetic import write_synthetic_predictions
    from runtime.atomic import save_npz

    p = write_synthetic_predictions(path, n_views=len(names), height=6, width=8)
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["image_names"] = np.array(names)
    return save_npz(path, **arrays)


@pytest.mark.parametrize("name", ["../victim.png", "/tmp/victim.png", "a\\b.png", ""])
def test_bridge_refuses_a_predictions_name_that_leaves_out(tmp_path, name):
    """The Bridge wrote such a name into sparse/0, from where ``render`` wrote outside ``--out``."""
    victim = _victim(tmp_path)
    npz = _predictions(tmp_path / "predictions.npz", ["view_000.png", name])
    out = tmp_path / "out"
    before = _listing(tmp_path)
    proc = _run(["-m", "bridge", "--pred", str(npz), "--out", str(out)])
    _refused(proc, str(npz), "not a plain file name")
    _untouched(tmp_path, out, victim, before)


def test_bridge_refuses_a_name_listed_twice_in_predictions(tmp_path):
    npz = _predictions(tmp_path / "predictions.npz", ["view_000.png", "view_000.png"])
    proc = _run(["-m", "bridge", "--pred", str(npz), "--out", str(tmp_path / "out")])
    _refused(proc, str(npz), "listed twice")
    assert not (tmp_path / "out").exists()


def test_ba_init_refuses_a_predictions_name_that_leaves_out(tmp_path):
    init = tmp_path / "init"
    write_text_model(init / "sparse" / "0", _cameras(["view_000.png", "view_001.png"]))
    npz = _predictions(init / "predictions.npz", ["view_000.png", "../victim.png"])
    (tmp_path / "images").mkdir()
    lst = tmp_path / "train.txt"
    lst.write_text("view_000.png\nview_001.png\n")
    victim = _victim(tmp_path)
    out = tmp_path / "out"
    before = _listing(tmp_path)
    proc = _run(["-m", "evaluation.initialisers.ba_init", "--init", str(init), "--images", str(tmp_path / "images"),
                 "--image-list", str(lst), "--out", str(out)])
    _refused(proc, str(npz), "not a plain file name")
    _untouched(tmp_path, out, victim, before)


# --- transforms.json frame paths -> camio convert ------------------------------------------------

def _transforms_scene(tmp_path: Path, paths: list[str]) -> Path:
    """A scene folder ``tmp_path/scene`` with images/0000.png, 0001.png and a transforms.json
    whose frames name ``paths``; ``tmp_path/victim.png`` (a real image) lies outside it."""
    scene = tmp_path / "scene"
    img = np.full((12, 16, 3), 0.5, np.float32)
    for i in range(2):
        write_image(scene / "images" / f"{i:04d}.png", img)
    write_image(tmp_path / "outside.png", img)
    frames = [{"file_path": p, "transform_matrix": np.eye(4).tolist()} for p in paths]
    (scene / "transforms.json").write_text(json.dumps({"camera_angle_x": 1.0, "frames": frames}))
    return scene


@pytest.mark.parametrize("path", ["../outside.png", "images/../../outside.png", "OUTSIDE", "/etc/passwd"])
def test_convert_refuses_a_transforms_frame_outside_the_scene(tmp_path, path):
    path = str(tmp_path / "outside.png") if path == "OUTSIDE" else path
    scene = _transforms_scene(tmp_path, ["images/0000.png", path])
    victim = _victim(tmp_path)
    out = tmp_path / "out"
    before = _listing(tmp_path)
    proc = _run(["-m", "camio", "convert", "--src", str(scene), "--out", str(out)])
    _refused(proc, str(scene / "transforms.json"), "lies outside", "inside the scene's folder")
    _untouched(tmp_path, out, victim, before)


def test_convert_reads_frames_in_a_subfolder_of_the_scene(tmp_path):
    """``images/x.png``, ``./images/x.png`` and an absolute path inside the scene are fine."""
    scene = _transforms_scene(tmp_path, ["./images/0000.png", str(tmp_path / "scene" / "images" / "0001.png")])
    out = tmp_path / "out"
    proc = _run(["-m", "camio", "convert", "--src", str(scene), "--out", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in (out / "images").iterdir()) == ["0000.png", "0001.png"]


def test_convert_refuses_frames_in_two_folders_in_one_line(tmp_path):
    """Frames in ``train/`` and ``test/`` would give names with folders (``train/r_0.png``),
    which every later stage refuses: refused here, where the scene is read."""
    scene = _transforms_scene(tmp_path, ["images/0000.png"])
    write_image(scene / "more" / "0002.png", np.full((12, 16, 3), 0.5, np.float32))
    meta = json.loads((scene / "transforms.json").read_text())
    meta["frames"].append({"file_path": "more/0002.png", "transform_matrix": np.eye(4).tolist()})
    (scene / "transforms.json").write_text(json.dumps(meta))
    out = tmp_path / "out"
    proc = _run(["-m", "camio", "convert", "--src", str(scene), "--out", str(out)])
    _refused(proc, "transforms.json", "lie in 2 folders", "--images-subdir")
    assert not out.exists()
