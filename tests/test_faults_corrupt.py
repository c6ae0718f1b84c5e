"""Fault: a corrupted intermediate (truncated npz, PLY, COLMAP text, checkpoint, weights) is
detected when it is loaded, with an error that names the file and says what to do; it is
never read as a smaller but valid-looking input.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from _train_scene import make_cameras, write_scene
from camio.colmap import read_model, write_text_model
from camio.ply import PlyFormatError, read_gaussian_ply


def _truncate(path: Path, keep: float | int) -> Path:
    raw = path.read_bytes()
    n = keep if isinstance(keep, int) else int(len(raw) * keep)
    path.write_bytes(raw[:n])
    return path


@pytest.fixture(scope="module")
def predictions(tmp_path_factory):
    from bridge.synthetic import write_synthetic_predictions

    return write_synthetic_predictions(tmp_path_factory.mktemp("pred") / "predictions.npz", n_views=3,
                                       height=8, width=10)


@pytest.mark.parametrize("keep", [0, 0.3, 0.99], ids=["empty", "cut30", "cut99"])
def test_bridge_truncated_predictions_npz(predictions, tmp_path, keep):
    from bridge.inputs import load_predictions

    bad = _truncate(Path(shutil.copy(predictions, tmp_path / "predictions.npz")), keep)
    with pytest.raises(ValueError, match=r"predictions\.npz is damaged or truncated.*re-run `python -m vggt_init`"):
        load_predictions(bad)


def test_bridge_cli_reports_truncated_npz_without_traceback(predictions, tmp_path, capsys):
    from bridge.__main__ import main

    bad = _truncate(Path(shutil.copy(predictions, tmp_path / "predictions.npz")), 0.5)
    assert main(["--pred", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "damaged or truncated" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "seed.ply").exists()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("scene"), n_views=3, width=16, height=12)


@pytest.mark.parametrize("keep,match", [pytest.param(0, "not a PLY file", id="empty"),
                                        pytest.param(0.3, "not a PLY file|truncated", id="cut30"),
                                        pytest.param(0.97, "truncated: header promises 60 vertices", id="cut97")])
def test_trainer_truncated_seed_ply(scene, tmp_path, keep, match):
    from splat_train.config import TrainConfig
    from splat_train.training.trainer import train

    bad = _truncate(Path(shutil.copy(scene["seed"], tmp_path / "seed.ply")), keep)
    with pytest.raises(PlyFormatError, match=match) as err:
        train(bad, scene["cameras"], scene["images"], tmp_path / "out",
              TrainConfig(iterations=2, device="cpu", num_threads=1))
    assert str(bad) in str(err.value)
    assert not (tmp_path / "out" / "model.ply").exists()


def test_truncated_model_ply_is_refused(scene, tmp_path):
    """What evaluation and `splat_train render` read: the same reader, the same error."""
    bad = _truncate(Path(shutil.copy(scene["seed"], tmp_path / "model.ply")), 0.5)
    with pytest.raises(PlyFormatError, match="truncated"):
        read_gaussian_ply(bad)


@pytest.fixture
def model_dir(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(12, 3))
    cams = make_cameras(4)
    obs = {c.name: (rng.uniform(0, 30, (3, 2)), np.array([0, 5, 11])) for c in cams}
    return write_text_model(tmp_path / "sparse" / "0", cams, pts, rng.integers(0, 255, (12, 3)), observations=obs)


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines(keepends=True)


@pytest.mark.parametrize("fname", ["images.txt", "points3D.txt", "cameras.txt"])
def test_camio_truncated_text_model_mid_line(model_dir, fname):
    assert len(read_model(model_dir).cameras) == 4
    f = model_dir / fname
    f.write_text(f.read_text()[:-7])  # cut inside the last line
    with pytest.raises(ValueError, match=rf"{fname} does not end with a newline: the file is truncated"):
        read_model(model_dir)


def test_camio_images_txt_cut_at_a_line_boundary_with_tracks(model_dir):
    """With observations, the points' tracks name the lost image: pycolmap's error, wrapped."""
    f = model_dir / "images.txt"
    f.write_text("".join(_lines(f)[:-2]))
    with pytest.raises(ValueError, match=r"cannot read the COLMAP model in .*damaged or inconsistent"):
        read_model(model_dir)


def test_camio_images_txt_cut_at_a_line_boundary(tmp_path):
    """pycolmap alone reads this as a valid 3-image model; the header count catches it."""
    model_dir = write_text_model(tmp_path / "m", make_cameras(4))
    f = model_dir / "images.txt"
    f.write_text("".join(_lines(f)[:-2]))  # the last image's two lines are gone
    with pytest.raises(ValueError, match=r"images.txt: the header says 4 images but 3 were read"):
        read_model(model_dir)


def test_camio_points3d_txt_cut_at_a_line_boundary(model_dir):
    f = model_dir / "points3D.txt"
    f.write_text("".join(_lines(f)[:-3]))  # the last three points are gone
    with pytest.raises(ValueError, match=r"points3D.txt: the header says 12 points but 9 were read"):
        read_model(model_dir)


def test_camio_text_model_without_count_headers_still_reads(model_dir):
    """Hand-written models (no '# Number of' lines, as in LLFF fern's published export) stay valid."""
    for fname in ("cameras.txt", "images.txt", "points3D.txt"):
        f = model_dir / fname
        f.write_text("".join(line for line in _lines(f) if not line.startswith("# Number")))
    m = read_model(model_dir)
    assert len(m.cameras) == 4 and len(m.points) == 12


def test_trainer_truncated_checkpoint_is_a_clear_error(scene, tmp_path):
    from splat_train.training.checkpoint import list_checkpoints
    from splat_train.config import TrainConfig
    from splat_train.training.trainer import train

    out = tmp_path / "run"
    cfg = TrainConfig(iterations=4, checkpoint_every=2, densify_until=0, device="cpu", num_threads=1)
    n = torch.get_num_threads()
    try:
        train(scene["seed"], scene["cameras"], scene["images"], out, cfg)
        last = list_checkpoints(out)[-1][1]
        _truncate(last, 0.5)
        cfg8 = TrainConfig(**{**cfg.to_dict(), "iterations": 8})
        with pytest.raises(ValueError, match=rf"cannot read checkpoint {last}.*delete it to resume from an older one"):
            train(scene["seed"], scene["cameras"], scene["images"], out, cfg8)
    finally:
        torch.set_num_threads(n)


def test_vggt_truncated_safetensors_checkpoint(tmp_path):
    from safetensors.torch import save_file

    from vggt_init.checkpoint import CheckpointFormatError, read_state_dict

    path = tmp_path / "model.safetensors"
    save_file({"w": torch.zeros(1000)}, str(path))
    _truncate(path, 0.5)
    with pytest.raises(CheckpointFormatError, match=str(path)):
        read_state_dict(path)


def test_lpips_truncated_weights_are_refused(tmp_path):
    from safetensors.torch import save_file

    from imgmetrics.lpips import LPIPS, load_lpips

    path = tmp_path / "alex.safetensors"
    save_file(LPIPS("alex").state_dict(), str(path), metadata={"net": "alex"})
    _truncate(path, 0.5)
    with pytest.raises(Exception, match="incomplete|truncated"):
        load_lpips("alex", path)


def test_lpips_truncated_weights_error_names_the_file(tmp_path):
    """(Was a bare SafetensorError 'incomplete metadata'; fixed in 7dbcb10.)"""
    from safetensors.torch import save_file

    from imgmetrics.lpips import LPIPS, load_lpips

    path = tmp_path / "alex.safetensors"
    save_file(LPIPS("alex").state_dict(), str(path), metadata={"net": "alex"})
    _truncate(path, 0.5)
    with pytest.raises(ValueError, match=rf"{path}.*lpips_convert"):
        load_lpips("alex", path)
