"""convert (prepare_scene) and the camio CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from camio.__main__ import main
from camio.cameras import project_points
from camio.colmap import read_model
from camio.images import downsample_area, read_image, read_image_uint8, write_image
from camio.prepare import PHOTO_MAX_SIZE, prepare_scene
from camio.scene import SceneError


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("prep") / "synth"
    assert main(["-q", "synth", "--out", str(out), "--views", "9", "--width", "64", "--seed", "2"]) == 0
    return out


def test_cli_synth_layout(synth):
    assert sorted(p.name for p in synth.iterdir()) == [".stage", "gt", "images", "sparse", "split.json", "synthetic.json"]
    meta = json.loads((synth / "synthetic.json").read_text())
    assert meta["seed"] == 2 and meta["views"] == 9 and meta["width"] == 64


def test_convert_downsample_scales_cameras_exactly(synth, tmp_path):
    out = prepare_scene(synth, tmp_path / "out", downsample=2)
    ref, got = read_model(synth), read_model(out)
    assert got.names == ref.names
    pts = ref.points
    for a, b in zip(ref.cameras, got.cameras):
        assert (b.width, b.height) == (32, 24)
        ua, _ = project_points(pts, a.K, a.cam_from_world)
        ub, _ = project_points(pts, b.K, b.cam_from_world)
        np.testing.assert_allclose(ub, ua / 2, atol=1e-9)
        np.testing.assert_allclose(got.observations[b.name][0], ref.observations[a.name][0] / 2, atol=1e-9)
    img = read_image_uint8(synth / "images" / "0004.png")
    # float path then 8-bit rounding: an exact .5 mean may round either way
    got_img = read_image_uint8(out / "images" / "0004.png").astype(int)
    assert np.abs(got_img - downsample_area(img, 2).astype(int)).max() <= 1
    split = json.loads((out / "split.json").read_text())
    assert split["test"] == ["0000.png", "0008.png"] and set(split["train"]) == {"3", "6"}
    meta = json.loads((out / "scene.json").read_text())
    assert meta["format"] == "colmap" and meta["image_size"] == [32, 24] and meta["n_reference_cameras"] == 9


def test_convert_copy_is_byte_exact(synth, tmp_path):
    assert main(["-q", "convert", "--src", str(synth), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o/images/0001.png").read_bytes() == (synth / "images/0001.png").read_bytes()


def test_convert_mixed_sizes_leaves_nothing(synth, tmp_path):
    """A dataset with reference cameras needs one image size (a photo folder may mix them:
    test_convert_turns_exif_rotated_photos_upright_and_says_so)."""
    src = tmp_path / "src"
    shutil.copytree(synth, src)
    write_image(src / "images" / "0005.png", downsample_area(read_image(src / "images" / "0005.png"), 2))
    with pytest.raises(SceneError, match="mixed sizes"):
        prepare_scene(src, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]
    assert main(["-q", "convert", "--src", str(src), "--out", str(tmp_path / "out")]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_cli_convert_sizes_a_photo_folder(tmp_path, capsys):
    """A photo folder is converted at its working resolution (long side at most PHOTO_MAX_SIZE,
    or --max-size; 0 = the photos' own size), area-downsampled, and the command says so."""
    src = tmp_path / "photos"
    w, h = PHOTO_MAX_SIZE + 400, (PHOTO_MAX_SIZE + 400) * 3 // 4
    stripes = np.zeros((h, w, 3), np.uint8)
    stripes[:, ::2] = 255  # 1-pixel stripes: antialiased, they become grey; sampled, they would not
    for i in range(3):
        write_image(src / f"IMG_{i}.jpg", np.roll(stripes, i, axis=1))
    ww, wh = PHOTO_MAX_SIZE, PHOTO_MAX_SIZE * 3 // 4
    capsys.readouterr()
    assert main(["-q", "convert", "--src", str(src), "--format", "folder", "--out", str(tmp_path / "a")]) == 0
    assert f"3 photos {w}x{h} -> {ww}x{wh} working resolution" in capsys.readouterr().out
    meta = json.loads((tmp_path / "a" / "scene.json").read_text())
    assert meta["image_size"] == [ww, wh] and meta["max_size"] == PHOTO_MAX_SIZE and meta["source_image_size"] == [w, h]
    img = read_image_uint8(tmp_path / "a" / "images" / "IMG_1.jpg").astype(int)
    inner = img[8:-8, 8:-8]  # 1.25 columns a pixel: a quarter to three quarters of it white
    assert img.shape == (wh, ww, 3) and inner.min() > 32 and inner.max() < 223 and abs(inner.mean() - 128) < 8

    assert main(["-q", "convert", "--src", str(src), "--max-size", "200", "--out", str(tmp_path / "b")]) == 0
    assert "3 photos" in capsys.readouterr().out
    assert json.loads((tmp_path / "b" / "scene.json").read_text())["image_size"] == [200, 150]
    assert main(["-q", "convert", "--src", str(src), "--max-size", "0", "--out", str(tmp_path / "c")]) == 0
    assert (tmp_path / "c" / "images" / "IMG_0.jpg").read_bytes() == (src / "IMG_0.jpg").read_bytes()


def test_cli_convert_max_size_is_for_photo_folders(synth, tmp_path, capsys):
    """A dataset's cameras scale by an integer factor: --max-size on it is one line, exit 2, nothing
    written; its default leaves a dataset at its own size."""
    assert main(["-q", "convert", "--src", str(synth), "--max-size", "32", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--downsample K" in err[0] and not (tmp_path / "o").exists()
    assert main(["-q", "convert", "--src", str(synth), "--max-size", "0", "--out", str(tmp_path / "o")]) == 0
    assert json.loads((tmp_path / "o" / "scene.json").read_text())["max_size"] == 0


def test_cli_split(synth, tmp_path):
    out = tmp_path / "split.json"
    assert main(["-q", "split", "--scene", str(synth), "--n", "3", "6", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["rule"] == "every8" and data["train"]["3"] == ["0001.png", "0004.png", "0007.png"]
    man = tmp_path / "m.json"
    man.write_text(json.dumps({"test": ["0003.png"], "train": ["0001.png", "0002.png"]}))
    assert main(["-q", "split", "--scene", str(synth), "--manifest", str(man), "--n", "2", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["rule"] == "manifest"
    assert main(["-q", "split", "--scene", str(synth), "--n", "12", "--out", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()


def test_convert_turns_exif_rotated_photos_upright_and_says_so(tmp_path, capsys):
    """A photo stored sideways with EXIF Orientation 6 (a phone held upright) is written
    upright, with no tag left, and convert names it; the photo folder may mix sizes."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(0)
    src = tmp_path / "shots"
    src.mkdir()
    upright = (rng.random((48, 32, 3)) * 255).astype(np.uint8)  # portrait 32x48
    for name, stored, o in (("a.png", upright, 6), ("b.png", np.rot90(upright, k=1).copy(), 1),
                            ("c.png", upright, 1)):
        data = np.rot90(stored, k=1) if o == 6 else stored  # stored sideways: the viewer turns it back
        spec = oiio.ImageSpec(data.shape[1], data.shape[0], 3, "uint8")
        spec.attribute("Orientation", o)
        f = oiio.ImageOutput.create(str(src / name))
        assert f.open(str(src / name), spec) and f.write_image(np.ascontiguousarray(data))
        f.close()
    assert main(["-q", "convert", "--src", str(src), "--format", "folder", "--out", str(tmp_path / "o")]) == 0
    said = capsys.readouterr().out
    assert "EXIF orientation applied: 1 of 3 image(s) turned upright: a.png (turned 90 degrees clockwise)" in said
    assert "3 photos of 2 sizes" in said
    a = tmp_path / "o" / "images" / "a.png"
    np.testing.assert_array_equal(read_image_uint8(a), upright)
    inp = oiio.ImageInput.open(str(a))
    assert int(inp.spec().get_int_attribute("Orientation", 1)) == 1
    inp.close()
