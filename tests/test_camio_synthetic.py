"""The synthetic scene: exact ground truth, determinism, file layout."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camio.cameras import project_points
from camio.colmap import read_model
from camio.images import read_image, read_image_uint8
from camio.ply import read_points_ply
from camio.synthetic import build_scene, cast_pixels, make_cameras, write_synthetic_scene


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "scene"
    write_synthetic_scene(out, views=10, width=96, seed=3, n_gt_points=8000, n_ref_points=1500)
    return out


def test_layout_and_split(synth):
    names = sorted(p.name for p in (synth / "images").iterdir())
    assert names == [f"{i:04d}.png" for i in range(10)]
    assert sorted(p.name for p in (synth / "gt" / "depth").iterdir()) == [f"{i:04d}.npy" for i in range(10)]
    split = json.loads((synth / "split.json").read_text())
    assert split["test"] == ["0000.png", "0008.png"]
    assert set(split["train"]) == {"3", "6"}  # 9 and 12 do not fit a pool of 8
    img = read_image(synth / "images" / "0000.png")
    assert img.shape == (72, 96, 3)
    assert img.std() > 0.1  # textured, not flat
    assert not (synth.parent / ".scene.tmp").exists()
    assert [p.name for p in synth.parent.iterdir()] == ["scene"]


def test_reference_model_matches_renders_and_depth(synth):
    model = read_model(synth)
    assert len(model.cameras) == 10 and 100 < len(model.points) <= 1500
    for cam in model.cameras:
        depth = np.load(synth / "gt" / "depth" / (cam.name[:-4] + ".npy"))
        assert depth.shape == (cam.height, cam.width) and depth.dtype == np.float32
        xy, idx = model.observations[cam.name]
        assert len(idx) > 20
        uv, z = project_points(model.points[idx], cam.K, cam.cam_from_world)
        # observations are the exact projections (text model stores shortest-repr floats)
        np.testing.assert_allclose(uv, xy, atol=1e-6)
        # GT depth agrees with the point's depth at the sub-pixel position: inverse depth is
        # affine in (u, v) on a plane, so its bilinear interpolation between the 4 nearest
        # pixel centres is exact inside one planar face (spheres: nearly so). Near occlusion
        # edges the 4 neighbours straddle two surfaces, hence median + loose bound.
        x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
        j0 = np.clip(np.floor(x).astype(int), 0, cam.width - 2)
        i0 = np.clip(np.floor(y).astype(int), 0, cam.height - 2)
        fx, fy = x - j0, y - i0
        inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-9), 0.0)
        inv_i = ((1 - fy) * ((1 - fx) * inv[i0, j0] + fx * inv[i0, j0 + 1])
                 + fy * ((1 - fx) * inv[i0 + 1, j0] + fx * inv[i0 + 1, j0 + 1]))
        rel = np.abs(1.0 / inv_i - z) / z
        assert np.median(rel) < 1e-4, np.median(rel)
        assert np.mean(rel < 1e-3) > 0.9


def test_points_on_rendered_surface_subpixel():
    """A ray cast through the exact projection of a GT point hits that point."""
    scene = build_scene(5)
    cams = make_cameras(scene, views=4, width=128)
    from camio.synthetic import sample_surface_points

    pts, cols, _ = sample_surface_points(scene, 3000, np.random.default_rng(0))
    cam = cams[1]
    uv, z = project_points(pts, cam.K, cam.cam_from_world)
    inside = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
    res = cast_pixels(scene, cam, uv[inside])
    visible = np.abs(res["depth"] - z[inside]) < 1e-3 * z[inside]
    assert visible.mean() > 0.3
    err = np.linalg.norm(res["points"][visible] - pts[inside][visible], axis=1)
    assert err.max() < 1e-4 * z[inside].max()  # float32 ray casting precision
    # the point's colour is the rendered colour of its pixel ray
    # (a sample exactly on a box edge may take the neighbouring face's shading)
    same = np.all(np.abs(res["rgb"][visible] * 255 - cols[inside][visible]) <= 0.51, axis=1)
    assert same.mean() > 0.99


def test_pixel_centre_convention():
    scene = build_scene(0)
    cam = make_cameras(scene, views=1, width=64)[0]
    res = cast_pixels(scene, cam, np.array([[32.0, 24.0]]))  # the principal point
    p = res["points"][0]
    uv, z = project_points(p[None], cam.K, cam.cam_from_world)
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-4)
    np.testing.assert_allclose(z[0], res["depth"][0], rtol=1e-6)


def test_deterministic_from_seed(tmp_path):
    kw = dict(views=3, width=48, n_gt_points=500, n_ref_points=100)
    a = write_synthetic_scene(tmp_path / "a", seed=7, **kw)
    b = write_synthetic_scene(tmp_path / "b", seed=7, **kw)
    c = write_synthetic_scene(tmp_path / "c", seed=8, **kw)
    for name in ("0000.png", "0002.png"):
        np.testing.assert_array_equal(read_image_uint8(a / "images" / name), read_image_uint8(b / "images" / name))
    assert (a / "sparse/0/points3D.txt").read_text() == (b / "sparse/0/points3D.txt").read_text()
    assert not np.array_equal(read_image_uint8(a / "images/0000.png"), read_image_uint8(c / "images/0000.png"))
    xa, ca = read_points_ply(a / "gt/points.ply")
    xb, cb = read_points_ply(b / "gt/points.ply")
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(ca, cb)


def test_gt_ply_read_by_plyfile(synth):
    plyfile = pytest.importorskip("plyfile")
    ply = plyfile.PlyData.read(str(synth / "gt" / "points.ply"))
    v = ply["vertex"]
    assert len(v) == 8000
    xyz, rgb = read_points_ply(synth / "gt" / "points.ply")
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), xyz, atol=0)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), rgb)


def test_bad_arguments():
    scene = build_scene(0)
    with pytest.raises(ValueError, match="layout"):
        make_cameras(scene, views=3, layout="spiral")
    with pytest.raises(ValueError, match="views"):
        make_cameras(scene, views=0)
    sph = make_cameras(scene, views=5, layout="sphere")
    assert len({tuple(np.round(c.center, 6)) for c in sph}) == 5
