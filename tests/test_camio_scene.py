"""Scene readers: conventions checked by projecting known points; bad input gives clear errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from camio.cameras import invert_cam_from_world, project_points
from camio.colmap import UnsupportedCameraModelError, read_model, write_text_model
from camio.images import ImageReadError, write_image
from camio.scene import SceneError, check_same_size, detect_format, load_scene
from camio.synthetic import write_synthetic_scene


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "synth"
    write_synthetic_scene(out, views=6, width=64, seed=1, n_gt_points=3000, n_ref_points=400)
    return out


@pytest.fixture
def ref(synth):
    return read_model(synth)


def _world_points(ref):
    return ref.points[:200]


def _assert_same_projection(cams_a, cams_b, pts, scale=1.0):
    for a, b in zip(cams_a, cams_b):
        assert a.name == b.name
        ua, za = project_points(pts, a.K, a.cam_from_world)
        ub, zb = project_points(pts, b.K, b.cam_from_world)
        np.testing.assert_allclose(ub, ua * scale, atol=1e-6)
        np.testing.assert_allclose(zb, za, rtol=1e-9, atol=1e-9)


def test_colmap_scene(synth, ref):
    assert detect_format(synth) == "colmap"
    s = load_scene(synth)
    assert s.source_format == "colmap" and s.names == [f"{i:04d}.png" for i in range(6)]
    _assert_same_projection(ref.cameras, s.model.cameras, _world_points(ref))


def test_bare_folder(synth, tmp_path):
    shutil.copytree(synth / "images", tmp_path / "imgs")
    s = load_scene(tmp_path / "imgs")
    assert s.source_format == "folder" and s.model is None and len(s) == 6
    assert check_same_size(s.image_dir, s.names) == (64, 48)


def _llff_rows(ref, scale):
    rows = []
    for c in ref.cameras:
        c2w = invert_cam_from_world(c.cam_from_world)[:3]
        right, down, fwd, centre = c2w[:, 0], c2w[:, 1], c2w[:, 2], c2w[:, 3]
        m = np.stack([down, right, -fwd, centre, [c.height * scale, c.width * scale, c.K[0, 0] * scale]], 1)
        rows.append(np.r_[m.ravel(), 0.1, 100.0])
    return np.array(rows)


def test_llff_poses_bounds_rescaled_to_images(synth, ref, tmp_path):
    """poses_bounds written for 4x larger images; the folder holds the real ones."""
    root = tmp_path / "llff"
    shutil.copytree(synth / "images", root / "images_4")
    np.save(root / "poses_bounds.npy", _llff_rows(ref, 4.0))
    assert detect_format(root) == "llff"
    s = load_scene(root, images_subdir="images_4")
    assert s.source_format == "llff"
    _assert_same_projection(ref.cameras, s.model.cameras, _world_points(ref))
    np.save(root / "poses_bounds.npy", _llff_rows(ref, 1.0)[:5])
    with pytest.raises(SceneError, match="5 poses but"):
        load_scene(root, images_subdir="images_4")


def test_nex_layout_rows_of_14_with_shared_intrinsics(synth, ref, tmp_path):
    """NeX's layout (its Shiny dataset; NeX-format copies of LLFF scenes): poses_bounds rows of
    14 (the 3x4 pose in LLFF's axes, then the bounds) and hwf_cxcy.npy (H, W, fx, fy, cx, cy)
    beside it. The cameras are the reference's with the file's principal point, off the image
    centre here: every projection moves by exactly that offset. Without hwf_cxcy.npy, or with a
    malformed one, a clear error."""
    root = tmp_path / "nex"
    shutil.copytree(synth / "images", root / "images")
    rows = _llff_rows(ref, 1.0)
    np.save(root / "poses_bounds.npy", np.c_[rows[:, :15].reshape(-1, 3, 5)[:, :, :4].reshape(-1, 12), rows[:, 15:]])
    c = ref.cameras[0]
    assert all(np.array_equal(o.K, c.K) for o in ref.cameras)
    dx, dy = 1.5, -2.25
    np.save(root / "hwf_cxcy.npy", np.array([[c.height], [c.width], [c.K[0, 0]], [c.K[1, 1]], [c.K[0, 2] + dx],
                                              [c.K[1, 2] + dy]]))
    assert detect_format(root) == "llff"
    s = load_scene(root)
    assert s.source_format == "llff" and s.names == ref.names
    pts = _world_points(ref)
    for a, b in zip(ref.cameras, s.model.cameras):
        np.testing.assert_allclose(b.cam_from_world, a.cam_from_world, atol=1e-12)
        ua, za = project_points(pts, a.K, a.cam_from_world)
        ub, zb = project_points(pts, b.K, b.cam_from_world)
        np.testing.assert_allclose(ub, ua + [dx, dy], atol=1e-9)
        np.testing.assert_allclose(zb, za, rtol=1e-12)
    np.save(root / "hwf_cxcy.npy", np.array([c.height, c.width, c.K[0, 0], c.K[0, 2], c.K[1, 2]]))
    with pytest.raises(SceneError, match="6 finite numbers"):
        load_scene(root)
    (root / "hwf_cxcy.npy").unlink()
    with pytest.raises(SceneError, match="hwf_cxcy.npy"):
        load_scene(root)


def _transforms(ref, per_frame=False, angle=False, ext=True, scale=1.0):
    frames = []
    for c in ref.cameras:
        c2w = invert_cam_from_world(c.cam_from_world)
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL axes
        f = {"file_path": "images/" + (c.name if ext else c.name[:-4]), "transform_matrix": c2w.tolist()}
        if per_frame:
            f.update(fl_x=c.K[0, 0] * scale, fl_y=c.K[1, 1] * scale, cx=c.K[0, 2] * scale, cy=c.K[1, 2] * scale,
                     w=c.width * scale, h=c.height * scale)
        frames.append(f)
    c = ref.cameras[0]
    meta = {"frames": frames}
    if angle:
        meta["camera_angle_x"] = 2 * np.arctan(c.width / (2 * c.K[0, 0]))
    elif not per_frame:
        meta.update(fl_x=c.K[0, 0], fl_y=c.K[1, 1], cx=c.K[0, 2], cy=c.K[1, 2], w=c.width, h=c.height)
    return meta


@pytest.mark.parametrize("variant", [dict(), dict(per_frame=True, scale=2.0), dict(angle=True, ext=False)])
def test_transforms_json(synth, ref, tmp_path, variant):
    root = tmp_path / "tj"
    shutil.copytree(synth / "images", root / "images")
    (root / "transforms.json").write_text(json.dumps(_transforms(ref, **variant)))
    assert detect_format(root) == "transforms"
    s = load_scene(root)
    assert s.names == ref.names and s.image_path(s.names[0]).is_file()
    _assert_same_projection(ref.cameras, s.model.cameras, _world_points(ref))


def test_transforms_distortion_refused(synth, ref, tmp_path):
    root = tmp_path / "tj"
    shutil.copytree(synth / "images", root / "images")
    meta = _transforms(ref)
    meta["k1"] = 0.1
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(UnsupportedCameraModelError, match="k1"):
        load_scene(root)
    meta = _transforms(ref)
    meta["frames"][0]["file_path"] = "images/missing.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match="missing"):
        load_scene(root)


def test_empty_folder(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(SceneError, match="no images"):
        load_scene(tmp_path)
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope")
    with pytest.raises(SceneError, match="unknown scene format"):
        load_scene(tmp_path, format="nerf")


def test_truncated_image(synth, tmp_path):
    shutil.copytree(synth / "images", tmp_path / "images")
    p = tmp_path / "images" / "0003.png"
    p.write_bytes(p.read_bytes()[:300])
    with pytest.raises(ImageReadError, match="0003.png"):
        load_scene(tmp_path)


def test_mixed_sizes(synth, tmp_path):
    shutil.copytree(synth / "images", tmp_path / "images")
    write_image(tmp_path / "images" / "0009.png", np.zeros((10, 12, 3), np.float32))
    with pytest.raises(SceneError, match="mixed sizes.*12x10: 1 image"):
        check_same_size(tmp_path / "images", sorted(p.name for p in (tmp_path / "images").iterdir()))


def test_model_names_missing_image(synth, ref, tmp_path):
    shutil.copytree(synth, tmp_path / "s")
    (tmp_path / "s" / "images" / "0002.png").unlink()
    with pytest.raises(SceneError, match="missing.*0002.png"):
        load_scene(tmp_path / "s")


def _write_model_with(path, model_name, params, ref):
    write_text_model(path, ref.cameras)
    lines = (path / "cameras.txt").read_text().splitlines()
    out = [ln if ln.startswith("#") else ln.split()[0] + f" {model_name} " + " ".join(ln.split()[2:4])
           + " " + " ".join(map(str, params)) for ln in lines]
    (path / "cameras.txt").write_text("\n".join(out) + "\n")


def test_unsupported_camera_model(synth, ref, tmp_path):
    shutil.copytree(synth / "images", tmp_path / "images")
    c = ref.cameras[0]
    _write_model_with(tmp_path / "sparse" / "0", "OPENCV_FISHEYE",
                      [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], 0.01, 0, 0, 0], ref)
    with pytest.raises(UnsupportedCameraModelError, match="OPENCV_FISHEYE"):
        load_scene(tmp_path, undistort=True, work_dir=tmp_path / "w")


def test_distorted_refused_then_undistorted(synth, ref, tmp_path):
    shutil.copytree(synth / "images", tmp_path / "images")
    c = ref.cameras[0]
    _write_model_with(tmp_path / "sparse" / "0", "SIMPLE_RADIAL", [c.K[0, 0], c.K[0, 2], c.K[1, 2], 0.05], ref)
    with pytest.raises(UnsupportedCameraModelError, match="SIMPLE_RADIAL.*undistort"):
        load_scene(tmp_path)
    s = load_scene(tmp_path, undistort=True, work_dir=tmp_path / "und")
    assert s.undistorted and s.names == ref.names
    assert {m for m, _ in s.model.camera_models.values()} == {"PINHOLE"}
    for cam, r in zip(s.model.cameras, ref.cameras):
        np.testing.assert_allclose(cam.cam_from_world, r.cam_from_world, atol=1e-9)
        assert (cam.width, cam.height) == check_same_size(s.image_dir, [cam.name])
