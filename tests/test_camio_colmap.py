"""COLMAP text writer read back exactly by pycolmap; reader for text and binary models."""

from __future__ import annotations

import numpy as np
import pytest

from camio.cameras import Camera, look_at, qvec_to_rotmat
from camio.colmap import SparseModel, UnsupportedCameraModelError, find_model_dir, read_model, write_text_model


def _cams(n=4, seed=0):
    rng = np.random.default_rng(seed)
    K = np.array([[300.25, 0, 160.5], [0, 301.125, 120.0], [0, 0, 1]])
    cams = []
    for i in range(n):
        eye = rng.normal(size=3) * 0.5 + [0, 0, -4]
        Ki = K if i < n - 1 else K * [[1.1], [1.1], [1]]  # last camera has its own intrinsics
        cams.append(Camera(f"im_{i}.png", 320, 240, Ki, look_at(eye, rng.normal(size=3) * 0.1)[:3]))
    return cams


def test_write_then_pycolmap_reads_back_exactly(tmp_path):
    import pycolmap

    cams = _cams()
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(30, 3))
    cols = rng.integers(0, 256, (30, 3), dtype=np.uint8)
    obs = {}
    for c in cams:
        uv = (pts @ c.R.T + c.t) @ c.K.T
        obs[c.name] = (uv[:, :2] / uv[:, 2:], np.arange(30))
    write_text_model(tmp_path / "m", cams, pts, cols, obs, errors=np.full(30, 0.5))
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "m"))
    assert len(rec.cameras) == 2 and len(rec.images) == 4 and len(rec.points3D) == 30
    by_name = {img.name: img for img in rec.images.values()}
    for c in cams:
        img = by_name[c.name]
        cam = rec.cameras[img.camera_id]
        assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (320, 240)
        np.testing.assert_array_equal(cam.params, [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]])
        pose = img.cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), c.R, atol=1e-15)
        np.testing.assert_allclose(pose.translation, c.t, atol=1e-15)
        xyzw = np.asarray(pose.rotation.quat)
        np.testing.assert_allclose(qvec_to_rotmat(np.r_[xyzw[3], xyzw[:3]]), c.R, atol=1e-15)
        xy = np.array([p.xy for p in img.points2D])
        np.testing.assert_array_equal(xy, obs[c.name][0])
    for pid, p in rec.points3D.items():
        np.testing.assert_array_equal(p.xyz, pts[pid - 1])
        np.testing.assert_array_equal(p.color, cols[pid - 1])
        assert p.track.length() == 4 and p.error == 0.5
    # and camio's own reader gives back the same arrays
    m = read_model(tmp_path / "m")
    for a, b in zip(cams, m.cameras):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_allclose(a.cam_from_world, b.cam_from_world, atol=1e-15)
    np.testing.assert_array_equal(m.points, pts)
    np.testing.assert_array_equal(m.colors, cols)
    np.testing.assert_array_equal(m.observations["im_2.png"][0], obs["im_2.png"][0])


def test_binary_model_and_find_model_dir(tmp_path):
    import pycolmap

    cams = _cams(3)
    write_text_model(tmp_path / "txt", cams, np.zeros((2, 3)) + [0, 0, 1])
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "txt"))
    (tmp_path / "scene" / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "scene" / "sparse" / "0"))
    assert find_model_dir(tmp_path / "scene") == tmp_path / "scene" / "sparse" / "0"
    m = read_model(tmp_path / "scene")
    assert m.names == ["im_0.png", "im_1.png", "im_2.png"] and len(m.points) == 2
    with pytest.raises(FileNotFoundError, match="no COLMAP model"):
        find_model_dir(tmp_path / "txt" / "nothing")


def test_distorted_refused_by_default(tmp_path):
    write_text_model(tmp_path / "m", _cams(2))
    txt = (tmp_path / "m" / "cameras.txt").read_text().replace("PINHOLE 320 240 300.25 301.125",
                                                              "SIMPLE_RADIAL 320 240 300.25")
    txt = "\n".join(ln + " 0.01" if ln.startswith("1 SIMPLE_RADIAL") else ln for ln in txt.splitlines())
    (tmp_path / "m" / "cameras.txt").write_text(txt + "\n")
    with pytest.raises(UnsupportedCameraModelError, match="SIMPLE_RADIAL"):
        read_model(tmp_path / "m")
    m = read_model(tmp_path / "m", allow_distorted=True)
    assert m.camera_models["im_0.png"][0] == "SIMPLE_RADIAL"


def test_writer_rejects_bad_input(tmp_path):
    cams = _cams(2)
    with pytest.raises(ValueError, match="no cameras"):
        write_text_model(tmp_path / "a", [])
    with pytest.raises(ValueError, match="whitespace"):
        write_text_model(tmp_path / "a", [Camera("a b.png", 4, 4, np.eye(3))])
    with pytest.raises(ValueError, match="duplicate"):
        write_text_model(tmp_path / "a", [cams[0], cams[0]])
    with pytest.raises(ValueError, match="out of range"):
        write_text_model(tmp_path / "a", cams, np.zeros((1, 3)), observations={"im_0.png": (np.zeros((1, 2)), [5])})
    assert not (tmp_path / "a").exists()
    assert list(tmp_path.iterdir()) == []


def test_sparse_model_subset():
    m = SparseModel(_cams(3), np.zeros((2, 3)))
    s = m.subset(["im_2.png", "im_0.png"])
    assert s.names == ["im_0.png", "im_2.png"] and len(s.points) == 2
    with pytest.raises(KeyError):
        m.subset(["zzz"])
