"""Preprocessing: bit-exact with VGGT's Pillow-based loader ('crop' and 'pad').

Oracles: the reference arrays in tests/data/vggt/shared/preprocess_expected.npz (made with
Pillow 13.0.0) and, when Pillow is installed, Pillow itself on random images (an
independent implementation of the same operations). All comparisons are exact (uint8).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _oiio_write import write_raw as _write

from vggt_init.pillow_compat import alpha_composite_over, bicubic_coefficients, resize_bicubic
from vggt_init.preprocess import (
    ImageInputError,
    decode_like_pillow,
    load_and_preprocess,
    preprocess_rgb,
    resized_size,
    to_model_input,
    to_rgb8,
)

DATA = Path(__file__).parent / "data" / "vggt" / "shared"


def _stem(f: str) -> str:
    return Path(f).stem


@pytest.fixture(scope="module")
def expected():
    return np.load(DATA / "preprocess_expected.npz"), json.loads((DATA / "preprocess.json").read_text())


def test_decode_matches_pillow_source(expected):
    z, meta = expected
    for im in meta["images"]:
        data, mode = decode_like_pillow(DATA / im["file"])
        src = z[f"source.{_stem(im['file'])}"]
        assert mode == im["pil_mode"]
        assert data.shape == src.shape
        diff = np.abs(data.astype(int) - src.astype(int)).max()
        if im["format"] == "PNG":
            assert diff == 0, im["file"]
        else:
            # JPEG decoders may differ; OpenImageIO's libjpeg-turbo matched Pillow 13 exactly
            # on these files (measured max difference 0). Allow a couple of levels.
            assert diff <= 2, f"{im['file']}: JPEG decode differs by {diff} levels"


def test_rgb_crop_pad_exact(expected):
    z, meta = expected
    for im in meta["images"]:
        stem = _stem(im["file"])
        rgb = to_rgb8(z[f"source.{stem}"], im["pil_mode"])
        np.testing.assert_array_equal(rgb, z[f"rgb.{stem}"])
        for mode in ("crop", "pad"):
            img, geo = preprocess_rgb(rgb, stem, mode)
            np.testing.assert_array_equal(img.transpose(2, 0, 1), z[f"{mode}.{stem}"], err_msg=f"{mode} {stem}")
            info = im[mode]
            assert [geo.resized_w, geo.resized_h] == info["resized_wh"]
            assert [geo.input_h, geo.input_w] == info["output_hw"]
            if mode == "crop":
                assert geo.offset_y == -(info["crop_rows_from"] or 0)
            else:
                top, _bottom, left, _right = info["pad_top_bottom_left_right"]
                assert (geo.offset_y, geo.offset_x) == (top, left)


def test_files_end_to_end_and_mixed_batch(expected):
    z, meta = expected
    for im in meta["images"]:
        for mode in ("crop", "pad"):
            imgs, _ = load_and_preprocess([DATA / im["file"]], mode)
            np.testing.assert_array_equal(imgs[0].transpose(2, 0, 1), z[f"{mode}.{_stem(im['file'])}"])
    files = [DATA / f for f in meta["crop_batch"]["files"]]
    imgs, geos = load_and_preprocess(files, "crop")
    np.testing.assert_array_equal(imgs.transpose(0, 3, 1, 2), z["crop_batch"])
    assert list(imgs.transpose(0, 3, 1, 2).shape) == meta["crop_batch"]["output_shape"]
    # the shorter image is centred: its offset is the top padding
    assert geos[1].offset_y == (geos[0].resized_h - geos[1].resized_h) // 2
    x = to_model_input(imgs)
    assert x.dtype.is_floating_point and x.shape == (2, 3, imgs.shape[1], imgs.shape[2])
    assert float(x.max()) == 1.0 and np.array_equal(x[0, 0, 0].numpy(), np.float32(imgs[0, 0, :, 0]) / np.float32(255))


def test_round_half_to_even():
    assert resized_size(74, 25, "crop") == (518, 168)  # 12.5 -> 12, not 13
    assert resized_size(25, 74, "pad") == (168, 518)
    assert resized_size(640, 480, "crop") == (518, 392)
    assert resized_size(1920, 1080, "crop") == (518, 294)
    with pytest.raises(ValueError, match="unknown preprocessing mode"):
        resized_size(10, 10, "stretch")


def test_too_small_images_are_rejected(tmp_path):
    with pytest.raises(ImageInputError, match="smaller than one 14 px patch"):
        preprocess_rgb(np.zeros((13, 40, 3), np.uint8), "tiny.png")
    with pytest.raises(ImageInputError, match="too elongated"):
        preprocess_rgb(np.zeros((14, 2000, 3), np.uint8), "strip.png")
    with pytest.raises(ImageInputError, match="does not exist"):
        load_and_preprocess([tmp_path / "missing.png"])


def test_geometry_maps_intrinsics_back(expected):
    z, meta = expected
    _, geos = load_and_preprocess([DATA / f for f in meta["crop_batch"]["files"]], "crop")
    g = geos[1]
    K_net = np.array([[400.0, 0, g.input_w / 2], [0, 410.0, g.input_h / 2], [0, 0, 1]])
    K = g.intrinsics_to_original(K_net)
    # a point projecting to original pixel (u, v) projects to sx*u+ox, sy*v+oy in the input
    x = np.array([0.3, -0.2, 2.0])
    uv = (K @ x)[:2] / x[2]
    uv_net = (K_net @ x)[:2] / x[2]
    np.testing.assert_allclose(uv_net, [g.scale_x * uv[0] + g.offset_x, g.scale_y * uv[1] + g.offset_y], rtol=1e-12)
    m = g.valid_mask()
    assert m.shape == (g.input_h, g.input_w)
    assert m.sum() == g.resized_w * g.resized_h


# ----------------------------------------------------------------------- Pillow cross-checks


def _pillow():
    return pytest.importorskip("PIL.Image")


@pytest.mark.parametrize("seed", range(3))
def test_resize_matches_pillow_random(seed):
    Image = _pillow()
    rng = np.random.default_rng(seed)
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(1, 150, 2))
        H, W = (int(v) for v in rng.integers(1, 220, 2))
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        ref = np.asarray(Image.fromarray(img).resize((W, H), Image.BICUBIC))
        np.testing.assert_array_equal(resize_bicubic(img, W, H), ref, err_msg=f"{w}x{h} -> {W}x{H}")


def test_resize_matches_pillow_large_downscale():
    Image = _pillow()
    rng = np.random.default_rng(7)
    img = rng.integers(0, 256, (600, 800, 3), dtype=np.uint8)
    for W, H in ((518, 392), (100, 30), (37, 500)):
        ref = np.asarray(Image.fromarray(img).resize((W, H), Image.BICUBIC))
        np.testing.assert_array_equal(resize_bicubic(img, W, H), ref)


def test_coefficients_are_normalised():
    for n_in, n_out in ((64, 518), (600, 37), (25, 25)):
        _, count, k = bicubic_coefficients(n_in, n_out)
        assert np.all(np.abs(k.sum(axis=1) - (1 << 22)) <= k.shape[1])
        assert np.all(count >= 1)


def test_alpha_composite_matches_pillow():
    Image = _pillow()
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, (30, 41, 4), dtype=np.uint8)
    rgba[..., 3][rgba[..., 3] < 60] = 0
    bg = Image.new("RGBA", (41, 30), (255, 255, 255, 255))
    ref = np.asarray(Image.alpha_composite(bg, Image.fromarray(rgba, "RGBA")))
    np.testing.assert_array_equal(alpha_composite_over(rgba), ref)




def _pillow_loader(path: Path, mode: str) -> np.ndarray:
    """The reference loader's steps with Pillow (independent oracle): [H, W, 3] uint8."""
    Image = _pillow()
    img = Image.open(path)
    if img.mode == "RGBA":
        bg = Image.new("RGBA", img.size, (255, 255, 255, 255))
        img = Image.alpha_composite(bg, img)
    img = img.convert("RGB")
    w, h = img.size
    nw, nh = resized_size(w, h, mode)
    arr = np.asarray(img.resize((nw, nh), Image.BICUBIC))
    if mode == "crop" and nh > 518:
        s = (nh - 518) // 2
        arr = arr[s:s + 518]
    if mode == "pad":
        out = np.full((518, 518, 3), 255, np.uint8)
        t, l = (518 - arr.shape[0]) // 2, (518 - arr.shape[1]) // 2
        out[t:t + arr.shape[0], l:l + arr.shape[1]] = arr
        arr = out
    return arr


@pytest.mark.parametrize("kind", ["gray8", "rgb16", "rgba16", "rgba8", "gray_alpha8", "gray16_low"])
def test_formats_match_pillow_loader(tmp_path, kind):
    _pillow()
    rng = np.random.default_rng(3)
    h, w = 37, 52
    if kind == "gray8":
        data, fmt = rng.integers(0, 256, (h, w), dtype=np.uint8), "uint8"
    elif kind == "rgb16":
        data, fmt = rng.integers(0, 65536, (h, w, 3), dtype=np.uint16), "uint16"
    elif kind == "rgba16":
        data, fmt = rng.integers(0, 65536, (h, w, 4), dtype=np.uint16), "uint16"
    elif kind == "rgba8":
        data, fmt = rng.integers(0, 256, (h, w, 4), dtype=np.uint8), "uint8"
    elif kind == "gray_alpha8":
        data, fmt = rng.integers(0, 256, (h, w, 2), dtype=np.uint8), "uint8"
    else:  # 16-bit gray whose values fit in 8 bits (Pillow saturates larger ones)
        data, fmt = rng.integers(0, 256, (h, w), dtype=np.uint16), "uint16"
    path = tmp_path / f"{kind}.png"
    _write(path, data, fmt)
    for mode in ("crop", "pad"):
        ours, _ = load_and_preprocess([path], mode)
        np.testing.assert_array_equal(ours[0], _pillow_loader(path, mode), err_msg=f"{kind} {mode}")


def test_gray16_saturates_like_pillow(tmp_path, caplog):
    data = np.full((20, 20), 1000, np.uint16)
    data[:10] = 100
    path = tmp_path / "g16.png"
    _write(path, data, "uint16")
    arr, mode = decode_like_pillow(path)
    assert mode == "L"
    assert arr[0, 0, 0] == 100 and arr[15, 0, 0] == 255
    assert "saturate" in caplog.text
