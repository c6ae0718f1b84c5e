"""Real scenes of this project's machine data (tests/_machine_data.py; skipped when absent)."""

from __future__ import annotations

import numpy as np
import pytest

from camio.cameras import project_points
from camio.scene import check_same_size, load_scene
from _machine_data import ABSENT, SCENES

pytestmark = [pytest.mark.shared_data,
              pytest.mark.skipif(not SCENES.is_dir(), reason=ABSENT)]
FERN = SCENES / "llff__fern"


@pytest.fixture(scope="module")
def fern_undistorted(tmp_path_factory):
    work = tmp_path_factory.mktemp("fern") / "und"
    return load_scene(FERN, images_subdir="images_8", undistort=True, work_dir=work, verify_images=False)


@pytest.mark.parametrize("name,fmt,n,cams", [
    ("strecha__fountain-P11", "colmap", 11, 11),
    ("tnt__Family", "folder", 24, 0),
    ("instantsplat__NUS_3views", "folder", 3, 0),
])
def test_scene_loads(name, fmt, n, cams):
    s = load_scene(SCENES / name)
    assert s.source_format == fmt and len(s.names) == n
    assert (0 if s.model is None else len(s.model.cameras)) == cams
    check_same_size(s.image_dir, s.names)


def test_fern_distorted_model_undistorted(fern_undistorted):
    from camio.colmap import UnsupportedCameraModelError

    with pytest.raises(UnsupportedCameraModelError, match="SIMPLE_RADIAL"):
        load_scene(FERN, verify_images=False)
    s = fern_undistorted
    assert s.undistorted and len(s.names) == 20 and len(s.model.points) > 5000
    assert {m for m, _ in s.model.camera_models.values()} == {"PINHOLE"}
    w, h = check_same_size(s.image_dir, s.names)
    assert 480 < w <= 504 and 360 < h <= 378
    # reference points3D: most lie in front of every camera and inside its image
    for cam in s.model.cameras:
        uv, z = project_points(s.model.points, cam.K, cam.cam_from_world)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        assert inside.mean() > 0.6, cam.name


def test_fern_reprojection_subpixel(fern_undistorted, tmp_path):
    """SIFT matches (pycolmap, geometrically verified) between 6 undistorted fern images,
    triangulated by DLT with the reference cameras, re-project with sub-pixel error: the
    reference poses, intrinsics, undistortion and pixel convention all agree."""
    import pycolmap

    from camio.colmap import cpu_matching_options

    s = fern_undistorted
    names = s.names[:6]
    db = tmp_path / "db.db"
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = 2
    pycolmap.extract_features(db, s.image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, matching_options=cpu_matching_options(), device=pycolmap.Device.cpu)
    d = pycolmap.Database.open(str(db))
    ids = {im.image_id: im.name for im in d.read_all_images()}
    cams = {c.name: c for c in s.model.cameras}
    errs = []
    for a in ids:
        for b in ids:
            if a >= b:
                continue
            m = np.asarray(d.read_two_view_geometry(a, b).inlier_matches).reshape(-1, 2)
            if len(m) == 0:
                continue
            xa = np.asarray(d.read_keypoints(a))[m[:, 0], :2].astype(np.float64)
            xb = np.asarray(d.read_keypoints(b))[m[:, 1], :2].astype(np.float64)
            Pa = cams[ids[a]].K @ cams[ids[a]].cam_from_world
            Pb = cams[ids[b]].K @ cams[ids[b]].cam_from_world
            A = np.stack([xa[:, :1] * Pa[2] - Pa[0], xa[:, 1:] * Pa[2] - Pa[1],
                          xb[:, :1] * Pb[2] - Pb[0], xb[:, 1:] * Pb[2] - Pb[1]], axis=1)
            X = np.linalg.svd(A)[2][:, -1]
            X = X[:, :3] / X[:, 3:]
            for P, x in ((Pa, xa), (Pb, xb)):
                p = X @ P[:, :3].T + P[:, 3]
                errs.append(np.linalg.norm(p[:, :2] / p[:, 2:] - x, axis=1))
    d.close()
    e = np.concatenate(errs)
    assert len(e) > 2000
    assert e.mean() < 0.5 and np.median(e) < 0.3, (e.mean(), np.median(e))  # measured 0.24 / 0.14


def test_fern_llff_poses_agree_with_colmap():
    llff = load_scene(FERN / "original" / "poses_bounds.npy", format="llff", images_subdir=FERN / "images_8",
                      verify_images=False)
    col = load_scene(FERN, images_subdir="images_8", verify_images=False, undistort=False, format="folder")
    assert col.model is None  # a bare folder view of the same images
    from camio.colmap import read_model

    ref = read_model(FERN, allow_distorted=True)
    assert llff.names == ref.names
    a, b = llff.model.cameras, ref.cameras
    # relative rotations are invariant to a similarity between the two frames
    for i in range(len(a)):
        for j in (0, len(a) // 2):
            ra = a[i].R @ a[j].R.T
            rb = b[i].R @ b[j].R.T
            ang = np.degrees(np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1)))
            assert ang < 1e-3, (i, j, ang)
    # centres agree up to scale: ratios of centre distances match
    ca = np.array([c.center for c in a])
    cb = np.array([c.center for c in b])
    da = np.linalg.norm(ca[1:] - ca[0], axis=1)
    db = np.linalg.norm(cb[1:] - cb[0], axis=1)
    np.testing.assert_allclose(da / da[0], db / db[0], rtol=1e-6)
    # LLFF focal (3260.5 px at 4032 wide) rescaled to images_8 matches the COLMAP camera
    np.testing.assert_allclose(a[0].K[0, 0], b[0].K[0, 0] / 2, rtol=1e-6)
