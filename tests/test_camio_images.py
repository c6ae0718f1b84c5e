"""Image I/O through OpenImageIO: formats, alpha, orientation, errors, area downsampling."""

from __future__ import annotations

import numpy as np
import pytest

from camio.images import (
    ImageReadError,
    apply_orientation,
    downsample_area,
    downsample_folder,
    image_size,
    list_images,
    read_image,
    read_image_uint8,
    resize_area,
    working_size,
    write_image,
)


def _raw_write(path, data, fmt, orientation=None, unassoc=False):
    """Write with OpenImageIO directly (independent of camio.write_image)."""
    import OpenImageIO as oiio

    h, w = data.shape[:2]
    if data.ndim == 2:
        data = data[..., None]  # oiio's Python binding misreads 2-D arrays
    c = data.shape[2]
    spec = oiio.ImageSpec(w, h, c, fmt)
    if c in (2, 4):
        spec.alpha_channel = c - 1
    if orientation is not None:
        spec.attribute("Orientation", orientation)
    if unassoc:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data))
    out.close()


@pytest.fixture
def rgb8():
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (12, 20, 3), dtype=np.uint8)


@pytest.mark.parametrize("ext", ["png", "tif"])
def test_8bit_lossless_exact(tmp_path, rgb8, ext):
    p = tmp_path / f"a.{ext}"
    _raw_write(p, rgb8, "uint8")
    img = read_image(p)
    assert img.dtype == np.float32 and img.shape == (12, 20, 3)
    np.testing.assert_array_equal(read_image_uint8(p), rgb8)
    np.testing.assert_allclose(img, rgb8 / 255.0, atol=1e-7)


@pytest.mark.parametrize("ext", ["png", "tif"])
def test_16bit(tmp_path, ext):
    rng = np.random.default_rng(1)
    a = rng.integers(0, 65536, (9, 7, 3), dtype=np.uint16)
    p = tmp_path / f"a.{ext}"
    _raw_write(p, a, "uint16")
    np.testing.assert_allclose(read_image(p), a / 65535.0, atol=1e-7)


def test_jpeg_close(tmp_path):
    smooth = np.tile(np.linspace(0, 1, 32, dtype=np.float32)[None, :, None], (24, 1, 3))
    p = write_image(tmp_path / "a.jpg", smooth)
    assert np.abs(read_image(p) - smooth).mean() < 0.02


def test_exr_keeps_linear_and_clips(tmp_path):
    a = np.array([[[0.25, 0.5, 0.125], [2.0, -1.0, 0.75]]], np.float32)
    p = tmp_path / "a.exr"
    _raw_write(p, a, "float")
    img = read_image(p)
    np.testing.assert_allclose(img, [[[0.25, 0.5, 0.125], [1.0, 0.0, 0.75]]], atol=1e-7)


def test_grayscale_to_rgb(tmp_path):
    g = np.arange(30, dtype=np.uint8).reshape(5, 6) * 8
    p = tmp_path / "g.png"
    _raw_write(p, g, "uint8")
    img = read_image(p)
    assert img.shape == (5, 6, 3)
    for c in range(3):
        np.testing.assert_allclose(img[..., c], g / 255.0, atol=1e-7)


def test_rgba_composited_over_background(tmp_path):
    a = np.zeros((2, 2, 4), np.float32)
    a[..., :3] = [1.0, 0.0, 0.0]
    a[..., 3] = [[1.0, 0.0], [0.5, 0.25]]
    p = tmp_path / "a.png"
    _raw_write(p, np.round(a * 255).astype(np.uint8), "uint8", unassoc=True)
    bg = (0.0, 0.0, 1.0)
    img = read_image(p, background=bg)
    alpha = np.round(a[..., 3] * 255) / 255
    expect = alpha[..., None] * np.array([1.0, 0, 0]) + (1 - alpha[..., None]) * np.array(bg)
    np.testing.assert_allclose(img, expect, atol=1.5 / 255)
    white = read_image(p)  # default background white
    np.testing.assert_allclose(white[0, 1], [1, 1, 1], atol=1e-6)


def test_exr_rgba_associated_alpha(tmp_path):
    a = np.array([[[0.2, 0.1, 0.0, 0.5]]], np.float32)  # premultiplied (EXR convention)
    p = tmp_path / "a.exr"
    _raw_write(p, a, "float")
    img = read_image(p, background=(0.0, 1.0, 0.0))
    np.testing.assert_allclose(img[0, 0], [0.2, 0.6, 0.0], atol=1e-6)


@pytest.mark.parametrize("orientation", list(range(1, 9)))
@pytest.mark.parametrize("ext", ["jpg", "tif", "png"])
def test_exif_orientation_matches_oiio_reorient(tmp_path, ext, orientation):
    import OpenImageIO as oiio

    rng = np.random.default_rng(orientation)
    a = np.kron(rng.integers(0, 256, (3, 5, 3)), np.ones((8, 8, 1))).astype(np.uint8)  # 24 x 40
    p = tmp_path / f"o.{ext}"
    _raw_write(p, a, "uint8", orientation=orientation)
    img = read_image(p)
    ref_buf = oiio.ImageBufAlgo.reorient(oiio.ImageBuf(str(p)))
    ref = ref_buf.get_pixels(oiio.FLOAT)
    assert img.shape == ref.shape
    np.testing.assert_allclose(img, ref, atol=1e-6)
    w, h = image_size(p)
    assert (h, w) == img.shape[:2]
    if orientation in (5, 6, 7, 8):
        assert img.shape[:2] == (40, 24)


def test_orientation_6_is_clockwise():
    a = np.array([[1, 2], [3, 4]])
    # stored top row 1 2; rotating 90 degrees clockwise puts 3 1 on top
    np.testing.assert_array_equal(apply_orientation(a, 6), [[3, 1], [4, 2]])
    np.testing.assert_array_equal(apply_orientation(a, 8), [[2, 4], [1, 3]])
    with pytest.raises(ValueError):
        apply_orientation(a, 9)


def test_truncated_and_missing_raise_naming_file(tmp_path, rgb8):
    for ext in ("png", "jpg"):
        good = write_image(tmp_path / f"g.{ext}", np.kron(rgb8, np.ones((8, 8, 1), np.uint8)))
        raw = good.read_bytes()
        bad = tmp_path / f"bad.{ext}"
        bad.write_bytes(raw[: len(raw) // 2])
        with pytest.raises(ImageReadError, match=f"bad.{ext}"):
            read_image(bad)
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    with pytest.raises(ImageReadError, match="junk.png"):
        read_image(junk)
    with pytest.raises(ImageReadError, match="nope.png"):
        read_image(tmp_path / "nope.png")


def test_write_image_roundtrip_and_atomic(tmp_path, rgb8):
    p = write_image(tmp_path / "w.png", rgb8)
    np.testing.assert_array_equal(read_image_uint8(p), rgb8)
    f = rgb8 / 255.0
    p16 = write_image(tmp_path / "w16.png", f, bits=16)
    np.testing.assert_allclose(read_image(p16), f, atol=1e-5)
    with pytest.raises(ValueError):
        write_image(tmp_path / "bad.png", np.zeros((4, 4, 5)))
    with pytest.raises(ValueError):
        write_image(tmp_path / "bad.jpg", f, bits=16)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["w.png", "w16.png"]


def test_downsample_area_box_mean_and_crop():
    rng = np.random.default_rng(2)
    a = rng.random((19, 26, 3))
    out = downsample_area(a.astype(np.float32), 4)
    assert out.shape == (4, 6, 3) and out.dtype == np.float32
    for i in range(4):
        for j in range(6):
            np.testing.assert_allclose(out[i, j], a[4 * i:4 * i + 4, 4 * j:4 * j + 4].mean(axis=(0, 1)), atol=1e-6)
    u8 = (a * 255).astype(np.uint8)
    o8 = downsample_area(u8, 2)
    assert o8.dtype == np.uint8
    np.testing.assert_array_equal(o8, np.round(u8[:18, :26].astype(float).reshape(9, 2, 13, 2, 3).mean((1, 3))))
    np.testing.assert_array_equal(downsample_area(u8, 1), u8)
    with pytest.raises(ValueError):
        downsample_area(a, 0)
    with pytest.raises(ValueError):
        downsample_area(a, 2.5)
    with pytest.raises(ValueError):
        downsample_area(a, 32)


def test_resize_area_is_the_box_mean_at_any_ratio():
    """Integer ratios give downsample_area's blocks; any other ratio weights the pixels an output
    pixel covers in part by the part covered: the mean is kept, 1-pixel stripes become grey."""
    rng = np.random.default_rng(3)
    a = rng.random((24, 36, 3)).astype(np.float32)
    np.testing.assert_allclose(resize_area(a, (12, 8)), downsample_area(a, 3), atol=1e-6)
    out = resize_area(a, (14, 10))
    assert out.shape == (10, 14, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out.mean((0, 1)), a.mean((0, 1)), atol=1e-6)
    # the first output pixel covers 36/14 columns and 24/10 rows: weights by the part covered
    wx, wy = np.array([1, 1, 36 / 14 - 2]), np.array([1, 1, 2.4 - 2])
    np.testing.assert_allclose(out[0, 0], np.einsum("i,j,ijc->c", wy, wx, a[:3, :3]) / (wx.sum() * wy.sum()), atol=1e-6)
    stripes = np.zeros((30, 40), np.uint8)
    stripes[:, ::2] = 255
    grey = resize_area(stripes, (16, 12))  # 2.5 columns a pixel: 1.5 or 1 of them white
    assert set(np.unique(grey)) == {102, 153}
    np.testing.assert_array_equal(resize_area(a, (36, 24)), a)
    with pytest.raises(ValueError, match="downsamples only"):
        resize_area(a, (37, 24))
    assert working_size(4032, 3024, 1600) == (1600, 1200) and working_size(3024, 4032, 1600) == (1200, 1600)
    assert working_size(400, 300, 1600) == (400, 300) and working_size(4032, 3024, 0) == (4032, 3024)


def test_downsample_folder(tmp_path, rgb8):
    src = tmp_path / "src"
    big = np.kron(rgb8, np.ones((4, 4, 1), np.uint8))  # 48 x 80
    write_image(src / "b.png", big)
    write_image(src / "a.png", big[::-1])
    (src / "notes.txt").write_text("x")
    assert list_images(src) == ["a.png", "b.png"]
    sizes = downsample_folder(src, tmp_path / "dst", 4)
    assert sizes == {"a.png": (20, 12), "b.png": (20, 12)}
    np.testing.assert_array_equal(read_image_uint8(tmp_path / "dst" / "b.png"), rgb8)
    same = downsample_folder(src, tmp_path / "copy", 1)
    assert (tmp_path / "copy" / "a.png").read_bytes() == (src / "a.png").read_bytes()
    assert same["a.png"] == (80, 48)
    capped = downsample_folder(src, tmp_path / "capped", 1, max_size=30)
    assert capped == {"a.png": (30, 18), "b.png": (30, 18)}
    kept = downsample_folder(src, tmp_path / "kept", 1, max_size=80)  # within the cap: copied
    assert kept["b.png"] == (80, 48) and (tmp_path / "kept" / "b.png").read_bytes() == (src / "b.png").read_bytes()


def test_downsample_folder_leaves_nothing_on_error(tmp_path, rgb8):
    src = tmp_path / "src"
    write_image(src / "a.png", rgb8)
    (src / "b.png").write_bytes((src / "a.png").read_bytes()[:40])
    with pytest.raises(ImageReadError, match="b.png"):
        downsample_folder(src, tmp_path / "dst", 2)
    assert list((tmp_path / "dst").iterdir()) == []
    with pytest.raises(FileNotFoundError):
        downsample_folder(tmp_path / "dst", tmp_path / "x", 2)
