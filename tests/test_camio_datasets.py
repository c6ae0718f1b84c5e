"""Benchmark layouts: each is generated here in its exact on-disk form, converted, and the
reference camera centres and focal lengths must round-trip to 1e-6 relative; layouts that
cannot be read correctly must fail with an error naming what to fix."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from camio.cameras import Camera, invert_cam_from_world, look_at, project_points, rotmat_to_qvec
from camio.colmap import UnsupportedCameraModelError, read_model
from camio.datasets import decompose_projection
from camio.images import read_image, write_image
from camio.scene import SceneError, detect_format, load_scene

W, H = 64, 48
RTOL = 1e-6


def _cameras(n=6, w=W, h=H, f=55.0, seed=0):
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 0.4 * rng.standard_normal(), 3 * np.sin(a)])
        K = np.array([[f * (1 + 0.01 * i), 0, w / 2 + 0.3 * i], [0, f * (1 + 0.012 * i), h / 2 - 0.2 * i],
                      [0, 0, 1]])
        cams.append(Camera(f"{i:04d}.png", w, h, K, look_at(eye, rng.normal(0, 0.1, 3))[:3]))
    return cams


def _img(path, w=W, h=H, seed=0, channels=3, bits=8):
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, channels)).astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, a[..., 0] if channels == 1 else a, bits=bits)


def _close_centre(g, r):
    np.testing.assert_allclose(g.center, r.center, rtol=0, atol=RTOL * np.linalg.norm(r.center))


def _assert_roundtrip(ref, got, scale=(1.0, 1.0), shift=(0.0, 0.0)):
    """Centres and focal lengths (relative 1e-6); principal points after scale and crop."""
    assert len(ref) == len(got)
    for r, g in zip(ref, got):
        _close_centre(g, r)
        np.testing.assert_allclose(g.R, r.R, atol=1e-9)
        np.testing.assert_allclose([g.K[0, 0], g.K[1, 1]], [r.K[0, 0] * scale[0], r.K[1, 1] * scale[1]], rtol=RTOL)
        np.testing.assert_allclose([g.K[0, 2], g.K[1, 2]],
                                   [(r.K[0, 2] - shift[0]) * scale[0], (r.K[1, 2] - shift[1]) * scale[1]],
                                   rtol=RTOL, atol=1e-9)


def _convert(src, out, *extra):
    r = subprocess.run([sys.executable, "-m", "camio", "convert", "--src", str(src), "--out", str(out), *extra],
                       capture_output=True, text=True)
    return r


# ------------------------------------------------------------------------------------ DTU
def test_decompose_projection_roundtrip():
    c = _cameras(1)[0]
    P = -3.7 * c.K @ c.cam_from_world
    K, R, C = decompose_projection(P)
    np.testing.assert_allclose(K, c.K, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(R, c.R, atol=1e-12)
    np.testing.assert_allclose(C, c.center, atol=1e-12)


def _dtu_npz(path, cams, frame_scale):
    """IDR cameras.npz for cameras in the normalised frame: world_mat = P_norm @ inv(scale_mat)."""
    rng = np.random.default_rng(3)
    data = {}
    for i, c in enumerate(cams):
        S = np.diag([250.0, 250.0, 250.0, 1.0])
        S[:3, 3] = rng.normal(0, 50, 3)
        K = c.K.copy()
        K[:2] *= frame_scale
        P = np.eye(4)
        P[:3] = K @ c.cam_from_world
        data[f"world_mat_{i}"] = 2.5 * P @ np.linalg.inv(S)
        data[f"scale_mat_{i}"] = S
        data[f"world_mat_inv_{i}"] = np.linalg.inv(data[f"world_mat_{i}"])
    np.savez(path, **data)


def test_dtu_idr_layout(tmp_path):
    """IDR: image/NNNNNN.png at 1600x1200, mask/, cameras.npz (world_mat_i, scale_mat_i)."""
    cams = _cameras(w=160, h=120, f=140.0)
    root = tmp_path / "scan65"
    for i in range(len(cams)):
        _img(root / "image" / f"{i:06d}.png", 1600, 1200, seed=i)
        _img(root / "mask" / f"{i:03d}.png", 16, 12, seed=i)
    _dtu_npz(root / "cameras.npz", cams, 10.0)  # K for the 1600x1200 frame
    assert detect_format(root) == "dtu"
    s = load_scene(root, verify_images=False)
    assert s.source_format == "dtu" and s.names == [f"{i:06d}.png" for i in range(6)]
    _assert_roundtrip(cams, s.model.cameras, scale=(10.0, 10.0))


def test_dtu_monosdf_layout_crop(tmp_path):
    """MonoSDF: NNNNNN_rgb.png 384x384 (centre crop of the 1600x1200 frame) beside depth and
    normal maps (.npy and .png) and cameras.npz for the uncropped frame."""
    cams = _cameras(w=1600, h=1200, f=2800.0)
    root = tmp_path / "scan24"
    for i in range(len(cams)):
        _img(root / f"{i:06d}_rgb.png", 384, 384, seed=i)
        _img(root / f"{i:06d}_depth.png", 384, 384, seed=i, channels=1, bits=16)
        _img(root / f"{i:06d}_normal.png", 384, 384, seed=i)
        np.save(root / f"{i:06d}_depth.npy", np.ones((384, 384), np.float32))
        np.save(root / f"{i:06d}_normal.npy", np.ones((3, 384, 384), np.float32))
    _dtu_npz(root / "cameras.npz", cams, 1.0)
    s = load_scene(root)
    assert s.names == [f"{i:06d}_rgb.png" for i in range(6)]
    _assert_roundtrip(cams, s.model.cameras, scale=(0.32, 0.32), shift=(200.0, 0.0))
    assert all((c.width, c.height) == (384, 384) for c in s.model.cameras)
    out = tmp_path / "out"
    r = _convert(root, out)
    assert r.returncode == 0, r.stderr
    assert "detected format dtu: 6 images, 6 reference cameras" in r.stdout
    assert sorted(p.name for p in (out / "images").iterdir()) == s.names
    _assert_roundtrip(cams, read_model(out).cameras, scale=(0.32, 0.32), shift=(200.0, 0.0))
    # the same folder forced to be a bare folder: photographs only, no depth/normal maps
    f = load_scene(root, format="folder")
    assert f.names == s.names and f.model is None


def test_dtu_refuses_other_sizes_and_missing_matrix(tmp_path):
    cams = _cameras(w=1600, h=1200, f=2800.0, n=3)
    root = tmp_path / "scan1"
    for i in range(3):
        _img(root / "image" / f"{i:06d}.png", 300, 100, seed=i)
    _dtu_npz(root / "cameras.npz", cams, 1.0)
    with pytest.raises(SceneError, match="000000.png is 300x100"):
        load_scene(root)
    _img(root / "image" / "000007.png", 1600, 1200)
    for i in range(3):
        (root / "image" / f"{i:06d}.png").unlink()
    with pytest.raises(SceneError, match="world_mat_7"):
        load_scene(root)


# --------------------------------------------------------------------------------- MVSNet
def _mvsnet_cam(path, c, K=None):
    E = np.eye(4)
    E[:3] = c.cam_from_world
    K = c.K if K is None else K
    txt = "extrinsic\n" + "\n".join(" ".join(repr(float(x)) for x in row) for row in E)
    txt += "\n\nintrinsic\n" + "\n".join(" ".join(repr(float(x)) for x in row) for row in K)
    txt += "\n\n425.0 2.5 192 905.0\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(txt)


def test_mvsnet_layout(tmp_path):
    cams = _cameras()
    root = tmp_path / "scan4"
    for i, c in enumerate(cams):
        _img(root / "images" / f"{i:08d}.jpg", seed=i)
        _mvsnet_cam(root / "cams" / f"{i:08d}_cam.txt", c)
    (root / "cams" / "pair.txt").write_text("6\n")
    assert detect_format(root) == "mvsnet"
    s = load_scene(root)
    assert s.names == [f"{i:08d}.jpg" for i in range(6)]
    _assert_roundtrip(cams, s.model.cameras)
    # intrinsics for a quarter of the resolution (MVSNet's training cams) are refused
    K4 = cams[0].K.copy()
    K4[:2] /= 4
    _mvsnet_cam(root / "cams" / "00000000_cam.txt", cams[0], K4)
    with pytest.raises(SceneError, match="00000000_cam.txt.*another resolution"):
        load_scene(root)
    (root / "cams" / "00000000_cam.txt").unlink()
    (root / "cams" / "00000001_cam.txt").unlink()
    with pytest.raises(SceneError, match="2 of 6 image"):
        load_scene(root, format="mvsnet")


# -------------------------------------------------------------------------------- Strecha
def _strecha_file(path, c, size, dist=(0.0, 0.0, 0.0)):
    s = size[0] / c.width
    K = c.K.copy()
    K[:2] *= s
    vals = [*K.ravel(), *dist, *c.R.T.ravel(), *c.center, size[0], size[1]]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(repr(float(v)) for v in vals[k:k + 3]) for k in range(0, 24, 3))
                    + f"\n{size[0]} {size[1]}\n")


def test_strecha_layout(tmp_path):
    """images/NNNN.jpg + gt_dense_cameras/NNNN.jpg.camera, cameras for 4x larger images:
    R in the file is camera-to-world and C the centre (not t)."""
    cams = _cameras()
    root = tmp_path / "fountain-P11"
    for i, c in enumerate(cams):
        _img(root / "images" / f"{i:04d}.jpg", seed=i)
        _strecha_file(root / "gt_dense_cameras" / f"{i:04d}.jpg.camera", c, (4 * W, 4 * H))
    assert detect_format(root) == "strecha"
    s = load_scene(root)
    assert s.source_format == "strecha" and len(s.model.cameras) == 6
    _assert_roundtrip(cams, s.model.cameras)
    r = _convert(root, tmp_path / "out")
    assert r.returncode == 0, r.stderr
    assert "detected format strecha: 6 images, 6 reference cameras (PINHOLE)" in r.stdout
    _assert_roundtrip(cams, read_model(tmp_path / "out").cameras)


def test_strecha_distortion_undistorted_on_request(tmp_path):
    cams = _cameras()
    root = tmp_path / "herzjesu"
    for i, c in enumerate(cams):
        _img(root / "images" / f"{i:04d}.jpg", seed=i)
        _strecha_file(root / "images" / f"{i:04d}.jpg.camera", c, (W, H), dist=(-0.05, 0.01, 0.0))
    with pytest.raises(UnsupportedCameraModelError, match="distortion.*--undistort"):
        load_scene(root)
    s = load_scene(root, undistort=True, work_dir=tmp_path / "und")
    assert s.undistorted and s.source_models == ("OPENCV",)
    for r, g in zip(cams, s.model.cameras):
        _close_centre(g, r)
    _strecha_file(root / "images" / "0000.jpg.camera", cams[0], (W, H), dist=(0.1, 0, 0.2))
    with pytest.raises(SceneError, match="third distortion"):
        load_scene(root)


def test_strecha_forced_without_camera_files_is_one_clear_error(tmp_path):
    """--format strecha on a folder with no .camera file (a COLMAP copy of a Strecha scene):
    a SceneError naming what is missing, and the convert CLI exits with it, not a TypeError."""
    root = tmp_path / "fountain-colmap"
    for i in range(3):
        _img(root / "images" / f"{i:04d}.jpg", seed=i)
    with pytest.raises(SceneError, match="needs the .camera files"):
        load_scene(root, format="strecha")
    r = _convert(root, tmp_path / "out", "--format", "strecha")
    assert r.returncode != 0 and "needs the .camera files" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------- COLMAP layouts (360, T&T, MVImgNet)
def _write_colmap_binary(model_dir, cams, model="PINHOLE", extra=()):
    """A binary COLMAP model, as Mip-NeRF 360 / Tanks and Temples / MVImgNet ship it."""
    import pycolmap

    txt = model_dir.parent / "_txt"
    txt.mkdir(parents=True)
    lines = []
    for i, c in enumerate(cams, 1):
        p = ([c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]] if model in ("PINHOLE", "OPENCV")
             else [c.K[0, 0], c.K[0, 2], c.K[1, 2]])
        lines.append(f"{i} {model} {c.width} {c.height} " + " ".join(repr(float(x)) for x in (*p, *extra)))
    (txt / "cameras.txt").write_text("\n".join(lines) + "\n")
    imgs = []
    for i, c in enumerate(cams, 1):
        imgs += [f"{i} " + " ".join(repr(float(x)) for x in (*rotmat_to_qvec(c.R), *c.t)) + f" {i} {c.name}", ""]
    (txt / "images.txt").write_text("\n".join(imgs) + "\n")
    (txt / "points3D.txt").write_text("")
    rec = pycolmap.Reconstruction()
    rec.read(str(txt))
    model_dir.mkdir(parents=True)
    rec.write_binary(str(model_dir))
    import shutil

    shutil.rmtree(txt)


@pytest.mark.parametrize("layout,factor", [("mipnerf360", 4), ("tanks_and_temples", 2)])
def test_colmap_folders_with_downsampled_copies(tmp_path, layout, factor):
    """images/ at full size, images_N/ downsampled copies, sparse/0/*.bin for the full size."""
    cams = [Camera(f"DSC{i:05d}.JPG", 4 * W, 4 * H, c.K * np.array([[4], [4], [1]]), c.cam_from_world)
            for i, c in enumerate(_cameras())]
    root = tmp_path / layout
    for i, c in enumerate(cams):
        _img(root / "images" / c.name, 4 * W, 4 * H, seed=i)
        _img(root / f"images_{factor}" / c.name, 4 * W // factor, 4 * H // factor, seed=i)
    _write_colmap_binary(root / "sparse" / "0", cams)
    np.save(root / "poses_bounds.npy", np.zeros((6, 17)))  # 360 ships both; COLMAP wins
    assert detect_format(root) == "colmap"
    s = load_scene(root, images_subdir=f"images_{factor}")
    _assert_roundtrip(cams, s.model.cameras, scale=(1 / factor, 1 / factor))
    r = _convert(root, tmp_path / "out", "--images-subdir", f"images_{factor}")
    assert r.returncode == 0, r.stderr
    _assert_roundtrip(cams, read_model(tmp_path / "out").cameras, scale=(1 / factor, 1 / factor))


def test_mvimgnet_colmap_simple_radial(tmp_path):
    """MVImgNet: <class>/<object>/images/NNN.jpg + sparse/0/*.bin, SIMPLE_RADIAL cameras."""
    cams = [Camera(f"{i:03d}.jpg", c.width, c.height, np.diag([c.K[0, 0]] * 2 + [1.0]) + np.array(
        [[0, 0, c.K[0, 2]], [0, 0, c.K[1, 2]], [0, 0, 0]]), c.cam_from_world) for i, c in enumerate(_cameras())]
    root = tmp_path / "mvimgnet" / "7" / "0a1b2c3d"
    for i, c in enumerate(cams):
        _img(root / "images" / c.name, seed=i)
    _write_colmap_binary(root / "sparse" / "0", cams, "SIMPLE_RADIAL", (0.02,))
    with pytest.raises(UnsupportedCameraModelError, match="SIMPLE_RADIAL"):
        load_scene(root)
    s = load_scene(root, undistort=True, work_dir=tmp_path / "und")
    assert s.source_models == ("SIMPLE_RADIAL",) and s.undistorted
    for r, g in zip(cams, s.model.cameras):
        _close_centre(g, r)


# ----------------------------------------------------------------------- transforms.json
def _c2w_gl(c):
    m = invert_cam_from_world(c.cam_from_world)
    m[:3, 1:3] *= -1  # OpenCV -> OpenGL axes
    return m.tolist()


def test_nerf_synthetic_layout(tmp_path):
    """transforms_{train,val,test}.json, file_path './train/r_N' without extension, RGBA PNG,
    camera_angle_x only, OpenGL axes."""
    cams = [Camera(f"r_{i}.png", W, W, np.array([[60.0, 0, W / 2], [0, 60.0, W / 2], [0, 0, 1]]), c.cam_from_world)
            for i, c in enumerate(_cameras())]
    root = tmp_path / "lego"
    for split, sub in (("train", cams[:4]), ("test", cams[4:])):
        frames = []
        for c in sub:
            rgba = np.zeros((W, W, 4), np.float32)
            rgba[8:20, 8:20] = [1, 0, 0, 1]
            (root / split).mkdir(parents=True, exist_ok=True)
            write_image(root / split / c.name, rgba)
            frames.append({"file_path": f"./{split}/{c.name[:-4]}", "rotation": 0.0, "transform_matrix": _c2w_gl(c)})
        (root / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": 2 * np.arctan(W / 2 / 60.0), "frames": frames}))
    assert detect_format(root) == "transforms"
    s = load_scene(root)
    assert s.names == ["r_0.png", "r_1.png", "r_2.png", "r_3.png"] and s.image_dir.name == "train"
    _assert_roundtrip(cams[:4], s.model.cameras)
    img = read_image(s.image_path("r_0.png"))
    np.testing.assert_allclose(img[0, 0], [1, 1, 1])  # transparent -> white background
    np.testing.assert_allclose(img[10, 10], [1, 0, 0])
    t = load_scene(root / "transforms_test.json")
    _assert_roundtrip(cams[4:], t.model.cameras)


def _fox(tmp_path, dist=(0.05, -0.01, 0.001, -0.002), missing=2):
    """instant-ngp fox layout: transforms.json with global fl_x/fl_y/cx/cy/w/h and
    k1 k2 p1 p2, 'images/NNNN.jpg' paths, some frames without image files."""
    cams = [Camera(f"{i:04d}.jpg", c.width, c.height, c.K, c.cam_from_world) for i, c in enumerate(_cameras(8))]
    for c in cams:
        c.K = cams[0].K.copy()
    root = tmp_path / "fox"
    frames = []
    for i, c in enumerate(cams):
        if i >= missing:
            _img(root / "images" / c.name, seed=i)
        frames.append({"file_path": f"images/{c.name}", "sharpness": 30.0, "transform_matrix": _c2w_gl(c)})
    K = cams[0].K
    meta = {"camera_angle_x": 1.0, "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": W, "h": H,
            "aabb_scale": 4, "frames": frames}
    meta.update(dict(zip(("k1", "k2", "p1", "p2"), dist)))
    (root / "transforms.json").write_text(json.dumps(meta))
    return root, cams


def test_instant_ngp_missing_frames_and_distortion(tmp_path):
    root, cams = _fox(tmp_path)
    with pytest.raises(SceneError, match="2 of 8 frames.*--skip-missing"):
        load_scene(root)
    with pytest.raises(UnsupportedCameraModelError, match="distortion.*--undistort"):
        load_scene(root, skip_missing=True)
    s = load_scene(root, skip_missing=True, undistort=True, work_dir=tmp_path / "und")
    assert s.undistorted and s.source_models == ("OPENCV",) and len(s.names) == 6
    assert {m for m, _ in s.model.camera_models.values()} == {"PINHOLE"}
    for r, g in zip(cams[2:], s.model.cameras):
        _close_centre(g, r)
        np.testing.assert_allclose(g.R, r.R, atol=1e-9)
    r = _convert(root, tmp_path / "out", "--skip-missing", "--undistort")
    assert r.returncode == 0, r.stderr
    assert "2 of 8 frames" in r.stderr and "6 reference cameras (OPENCV, undistorted to PINHOLE)" in r.stdout


def test_instant_ngp_per_frame_distortion_undistorts_like_colmap(tmp_path):
    """Per-frame k1..p2 give the same undistorted cameras as the equivalent COLMAP OPENCV model."""
    root, cams = _fox(tmp_path, dist=(0, 0, 0, 0), missing=0)
    meta = json.loads((root / "transforms.json").read_text())
    for f in meta["frames"]:
        f.update(k1=0.04, k2=-0.01, p1=0.0005, p2=0.0)
    (root / "transforms.json").write_text(json.dumps(meta))
    a = load_scene(root, undistort=True, work_dir=tmp_path / "a")
    col = tmp_path / "col"
    import shutil

    shutil.copytree(root / "images", col / "images")
    _write_colmap_binary(col / "sparse" / "0", cams, "OPENCV", (0.04, -0.01, 0.0005, 0.0))
    b = load_scene(col, undistort=True, work_dir=tmp_path / "b")
    for ca, cb in zip(a.model.cameras, b.model.cameras):
        np.testing.assert_allclose(ca.K, cb.K, rtol=1e-9)
        np.testing.assert_allclose(ca.cam_from_world, cb.cam_from_world, atol=1e-9)
        assert (ca.width, ca.height) == (cb.width, cb.height)
    np.testing.assert_allclose(read_image(a.image_path(a.names[0])), read_image(b.image_path(b.names[0])), atol=1e-6)


# -------------------------------------------------------------------------- bare folders
def test_bare_folder_takes_photographs_only(tmp_path):
    d = tmp_path / "shots"
    for i in range(4):
        _img(d / f"IMG_{i}.jpg", seed=i)
        _img(d / f"IMG_{i}_mask.png", seed=i, channels=1)
        _img(d / f"conf_{i}.png", seed=i)
    _img(d / "scan.png", channels=1, bits=16)  # single-channel 16-bit: depth-like
    s = load_scene(d)
    assert s.names == [f"IMG_{i}.jpg" for i in range(4)]
    _img(d / "gray.png", channels=1)  # an 8-bit gray photo among RGB ones: mixed roles
    with pytest.raises(SceneError, match="mix pixel types.*--allow-mixed"):
        load_scene(d)
    assert len(load_scene(d, allow_mixed=True).names) == 5


def test_bare_folder_of_mixed_sizes_keeps_each_size(tmp_path):
    """Photos of several sizes (portrait and landscape) convert without --allow-mixed: each
    keeps its size, which scene.json lists, and the run says so; a dataset with cameras still
    needs one size (tests/test_camio_prepare.py)."""
    d = tmp_path / "shots"
    for i in range(3):
        _img(d / f"{i}.jpg", seed=i)
    _img(d / "3.jpg", 32, 32)
    r = _convert(d, tmp_path / "out")
    assert r.returncode == 0, r.stderr
    assert "4 photos of 2 sizes" in r.stdout
    meta = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert meta["image_sizes"]["3.jpg"] == [32, 32] and len({tuple(v) for v in meta["image_sizes"].values()}) == 2


def test_unknown_camera_files_refused(tmp_path):
    d = tmp_path / "scene"
    for i in range(3):
        _img(d / "images" / f"{i}.jpg", seed=i)
    (d / "bundle.out").write_text("# Bundle file v0.3\n")
    (d / "traj.log").write_text("0 0 1\n")
    with pytest.raises(SceneError, match="2 file.*bundle.out.*--format folder"):
        load_scene(d)
    assert len(load_scene(d, format="folder").names) == 3


# ----------------------------------------------------------------------------- Middlebury
def _middlebury_par(path, cams, first_line="count"):
    lines = [str(len(cams))] if first_line == "count" else (
        ["imgname.png " + " ".join(f"k{i}" for i in range(21))] if first_line == "header" else [])
    for c in cams:
        lines.append(" ".join([c.name, *(repr(float(v)) for v in (*c.K.ravel(), *c.R.ravel(), *c.t))]))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("first_line", ["count", "header", "none"])
def test_middlebury_layout(tmp_path, first_line):
    """templeSR0001.png ... beside templeSR_par.txt: 'NAME K(9) R(9) t(3)', P = K [R | t];
    the dataset's count line (or a header of names) is skipped; the cameras round-trip and a
    world point projects where K [R | t] puts it."""
    cams = [Camera(f"templeSR{i + 1:04d}.png", c.width, c.height, c.K, c.cam_from_world)
            for i, c in enumerate(_cameras())]
    root = tmp_path / "templeSparseRing"
    for i, c in enumerate(cams):
        _img(root / c.name, seed=i)
    _middlebury_par(root / "templeSR_par.txt", cams, first_line)
    (root / "templeSR_ang.txt").write_text("0 0\n")  # the dataset's angles file: not a camera file
    assert detect_format(root) == "middlebury"
    s = load_scene(root)
    assert s.source_format == "middlebury" and s.names == [c.name for c in cams]
    _assert_roundtrip(cams, s.model.cameras)
    X = np.array([0.1, -0.2, 0.3])
    for c, g in zip(cams, s.model.cameras):
        x = c.K @ (c.R @ X + c.t)
        uv, _ = project_points(X[None], g.K, g.cam_from_world)
        np.testing.assert_allclose(uv[0], x[:2] / x[2], rtol=1e-9)
    r = _convert(root, tmp_path / "out", "--downsample", "2")
    assert r.returncode == 0, r.stderr
    assert "detected format middlebury: 6 images, 6 reference cameras (PINHOLE)" in r.stdout
    _assert_roundtrip(cams, read_model(tmp_path / "out").cameras, scale=(0.5, 0.5))


def test_middlebury_refuses_what_it_cannot_read(tmp_path):
    cams = [Camera(f"v{i}.png", c.width, c.height, c.K, c.cam_from_world) for i, c in enumerate(_cameras(3))]
    root = tmp_path / "dino"
    for i, c in enumerate(cams):
        _img(root / c.name, seed=i)
    par = root / "dino_par.txt"
    _middlebury_par(par, cams[:2])
    with pytest.raises(SceneError, match=r"1 of 3 image\(s\).*no line in .*dino_par.txt"):
        load_scene(root)
    _middlebury_par(par, cams)
    par.write_text(par.read_text().replace(cams[1].name + " ", cams[1].name + " 7 ", 1))
    with pytest.raises(SceneError, match="camera line 2 holds 23 fields"):
        load_scene(root)
    bad = Camera(cams[1].name, W, H, cams[1].K, np.concatenate([2 * cams[1].R, cams[1].t[:, None]], 1))
    _middlebury_par(par, [cams[0], bad, cams[2]])
    with pytest.raises(SceneError, match="R is not a rotation"):
        load_scene(root)
    _middlebury_par(par, cams)
    _middlebury_par(root / "dinoSR_par.txt", cams)
    with pytest.raises(SceneError, match="2 Middlebury camera files"):
        load_scene(root)
