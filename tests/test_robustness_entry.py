"""Hostile inputs that used to give a cut name, a misleading reason or a traceback, each run
through the command a user runs:

* image names with spaces are refused where they enter (``camio convert`` of a folder,
  ``evaluation.initialisers.colmap_baseline``, ``vggt_init``), one line naming the file with a rename;
* the COLMAP baseline records the real reason in ``status.json`` (an EXIF-rotated image, a
  tiny image) instead of only "no initial image pair" (images of several sizes are no
  problem: each size gets its own camera, tests/test_photos.py);
* Ctrl-C in ``python -m splat_train`` is one line and exit code 130;
* a degenerate seed PLY gets a warning naming what is degenerate, a non-finite one a
  refusal naming the file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from camio.images import write_image


def _texture(seed: int, h: int = 48, w: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.kron(rng.random((h // 8, w // 8, 3)), np.ones((8, 8, 1))).astype(np.float32)


def _errors(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if " ERROR " in ln]


def _spaced_folder(root: Path) -> Path:
    images = root / "photos"
    for i, name in enumerate(["vue 1.png", "vue 2.png", "vue 3.png"]):
        write_image(images / name, _texture(i))
    return images


def test_convert_refuses_names_with_spaces(tmp_path, capsys):
    from camio.__main__ import main

    images = _spaced_folder(tmp_path)
    rc = main(["convert", "--src", str(images), "--format", "folder", "--out", str(tmp_path / "scene")])
    line, = _errors(capsys.readouterr().err)
    assert rc == 2 and "vue 1.png" in line and "'vue_1.png'" in line and "whitespace" in line
    assert not (tmp_path / "scene").exists()


def test_colmap_baseline_refuses_names_with_spaces(tmp_path, capsys):
    from evaluation.initialisers.colmap_baseline import main

    images = _spaced_folder(tmp_path)
    rc = main(["--images", str(images), "--names", "vue 1.png", "vue 2.png", "--out", str(tmp_path / "o")])
    line, = _errors(capsys.readouterr().err)
    assert rc == 2 and f"{images / 'vue 1.png'}" in line and "'vue_1.png'" in line
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_vggt_init_refuses_names_with_spaces(tmp_path, capsys):
    from vggt_init.__main__ import main

    images = _spaced_folder(tmp_path)
    rc = main(["--images", str(images), "--out", str(tmp_path / "o"), "--no-retain-memory"])
    err = capsys.readouterr().err
    line, = _errors(err)
    assert rc == 2 and "vue 1.png" in line and "whitespace" in line and "Traceback" not in err


def _write_oriented(path: Path, data: np.ndarray, orientation: int) -> None:
    import OpenImageIO as oiio

    u8 = (np.clip(data, 0, 1) * 255).astype(np.uint8)
    h, w, c = u8.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(u8))
    out.close()


@pytest.mark.parametrize("case", ["exif_rotated", "tiny"])
def test_colmap_baseline_records_the_real_reason(tmp_path, capsys, case):
    from evaluation.initialisers.colmap_baseline import main

    images = tmp_path / "images"
    names = ["a.png", "b.png", "c.png"]
    for i, n in enumerate(names):
        write_image(images / n, _texture(i))
    if case == "exif_rotated":
        names[1] = "b.tif"
        _write_oriented(images / "b.tif", _texture(1), 6)
        want = "EXIF-rotated images: b.tif (orientation 6)"
    else:
        write_image(images / "b.png", np.zeros((1, 1, 3), np.float32))
        want = "images too small for features"
    out = tmp_path / "out"
    rc = main(["--images", str(images), "--names", *names, "--out", str(out), "--threads", "1"])
    status = json.loads((out / "status.json").read_text())
    assert rc == 0 and not status["success_paper"]
    assert want in status["reason"], status["reason"]
    assert want in capsys.readouterr().err  # also said without -v


def test_trainer_ctrl_c_is_one_line_and_exit_130(tmp_path, monkeypatch, capsys):
    import splat_train.__main__ as cli
    import splat_train.training.trainer as trainer
    from _train_scene import write_scene

    sc = write_scene(tmp_path / "scene")

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "train", interrupted)
    monkeypatch.setattr(sys, "argv", ["splat_train", "--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]),
                                      "--images", str(sc["images"]), "--out", str(tmp_path / "out")])
    assert cli._cli() == 130
    err = capsys.readouterr().err
    line, = _errors(err)
    assert "stopped by SIGINT" in line and "run the same command again" in line and "Traceback" not in err


def _seed(tmp_path: Path, **edit) -> Path:
    from _train_scene import make_cloud
    from camio.ply import write_gaussian_ply

    cloud = make_cloud()
    for k, fn in edit.items():
        setattr(cloud, k, fn(getattr(cloud, k)))
    return write_gaussian_ply(tmp_path / "seed.ply", cloud)


@pytest.mark.parametrize("case,needle", [
    ("tiny_scales", "log scales outside"), ("far_positions", "positions lie beyond"),
])
def test_trainer_warns_on_a_degenerate_seed(tmp_path, monkeypatch, capsys, case, needle):
    import splat_train.__main__ as cli
    import splat_train.training.trainer as trainer
    from _train_scene import write_scene

    sc = write_scene(tmp_path / "scene")
    edit = ({"log_scales": lambda a: np.full_like(a, -1e30)} if case == "tiny_scales"
            else {"means": lambda a: a * np.float32(1e30)})
    seed = _seed(tmp_path, **edit)

    def stop(*a, **k):
        raise KeyboardInterrupt  # the warning comes before training starts

    monkeypatch.setattr(trainer, "train", stop)
    monkeypatch.setattr(sys, "argv", ["splat_train", "--seed-ply", str(seed), "--cameras", str(sc["cameras"]),
                                      "--images", str(sc["images"]), "--out", str(tmp_path / "out")])
    assert cli._cli() == 130
    err = capsys.readouterr().err
    warn = [ln for ln in err.splitlines() if "WARNING" in ln and "degenerate seed" in ln]
    assert len(warn) == 1 and needle in warn[0] and str(seed) in warn[0], err


def test_trainer_refuses_a_non_finite_seed_naming_the_file(tmp_path, monkeypatch, capsys):
    import splat_train.__main__ as cli
    from _train_scene import write_scene

    sc = write_scene(tmp_path / "scene")
    seed = _seed(tmp_path, means=lambda a: np.where(np.arange(len(a))[:, None] == 3, np.nan, a).astype(np.float32))
    monkeypatch.setattr(sys, "argv", ["splat_train", "--seed-ply", str(seed), "--cameras", str(sc["cameras"]),
                                      "--images", str(sc["images"]), "--out", str(tmp_path / "out")])
    assert cli._cli() == 2
    err = capsys.readouterr().err
    line, = _errors(err)
    assert str(seed) in line and "positions: 1 of 60" in line and "Traceback" not in err


def test_render_refuses_a_model_with_nan_naming_the_file(tmp_path, monkeypatch, capsys):
    """A trained model.ply holding NaN: one line naming the model (it said "fix the seed PLY")."""
    import splat_train.__main__ as cli
    from _train_scene import write_scene

    sc = write_scene(tmp_path / "scene")
    model = _seed(tmp_path, opacity_logit=lambda a: np.where(np.arange(len(a)) < 2, np.nan, a).astype(np.float32))
    out = tmp_path / "renders"
    monkeypatch.setattr(sys, "argv", ["splat_train", "render", "--model", str(model), "--cameras", str(sc["cameras"]),
                                      "--out", str(out), "--width", "32", "--height", "24"])
    assert cli._cli() == 2
    err = capsys.readouterr().err
    line, = _errors(err)
    assert str(model) in line and "opacities: 2 of 60" in line and "in the model" in line and "seed PLY" not in line, line
    assert not out.exists()
