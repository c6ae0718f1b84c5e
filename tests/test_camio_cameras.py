"""Camera maths: quaternions (w x y z vs pycolmap's x y z w), transforms, projection."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from camio.cameras import (
    Camera, camera_center, invert_cam_from_world, look_at, opengl_to_opencv_c2w, project_points,
    qvec_to_rotmat, rotmat_to_qvec, scale_intrinsics, to_homogeneous,
)

quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3)


@settings(max_examples=100, deadline=None)
@given(quats)
def test_quaternion_roundtrip(q):
    q = np.asarray(q) / np.linalg.norm(q)
    R = qvec_to_rotmat(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    q2 = rotmat_to_qvec(R)
    assert q2[0] >= 0
    assert abs(q2 @ q) == pytest.approx(1.0, abs=1e-9)  # same rotation (q and -q)
    if abs(q[0]) > 1e-6:  # w >= 0 picks the sign unless w ~ 0
        np.testing.assert_allclose(q2, q * np.sign(q[0]), atol=1e-9)
    np.testing.assert_allclose(qvec_to_rotmat(q2), R, atol=1e-12)


def test_quaternion_known_values_and_pycolmap_order():
    import pycolmap

    # 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(qvec_to_rotmat(q), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        rot = pycolmap.Rotation3d(np.r_[q[1:], q[0]])  # pycolmap takes x y z w
        np.testing.assert_allclose(rot.matrix(), qvec_to_rotmat(q), atol=1e-12)
        xyzw = np.asarray(pycolmap.Rotation3d(qvec_to_rotmat(q)).quat)
        np.testing.assert_allclose(np.abs(np.r_[xyzw[3], xyzw[:3]] @ q), 1.0, atol=1e-12)
    # 180-degree rotations (trace -1) are where naive formulas fail
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        np.testing.assert_allclose(qvec_to_rotmat(rotmat_to_qvec(R)), R, atol=1e-12)
    with pytest.raises(ValueError):
        qvec_to_rotmat(np.zeros(4))
    with pytest.raises(ValueError):
        rotmat_to_qvec(np.eye(4))


def test_rigid_helpers():
    rng = np.random.default_rng(1)
    R = qvec_to_rotmat(rng.normal(size=4))
    t = rng.normal(size=3)
    m = np.c_[R, t]
    inv = invert_cam_from_world(m)
    np.testing.assert_allclose(inv @ to_homogeneous(m), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(camera_center(m), -R.T @ t, atol=1e-12)
    np.testing.assert_allclose(R @ camera_center(m) + t, 0, atol=1e-12)
    batch = np.stack([m, m])
    assert invert_cam_from_world(batch).shape == (2, 4, 4)
    with pytest.raises(ValueError):
        to_homogeneous(np.eye(3))


def test_look_at_and_projection():
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    m = look_at([0, -5, 0], [0, 0, 0], up=(0, 0, 1))
    uv, z = project_points(np.array([[0, 0, 0], [0, 0, 1.0], [1, 0, 0], [0, -10, 0]]), K, m)
    np.testing.assert_allclose(uv[0], [50, 40])  # target at the principal point
    assert uv[1, 1] < 40  # world up appears up (smaller row)
    assert uv[2, 0] > 50  # +x appears right when looking along +y with z up
    assert np.isnan(uv[3]).all() and z[3] < 0
    np.testing.assert_allclose(look_at([0, 0, 0], [0, 0, 1]), np.eye(4), atol=1e-12)
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 1], up=(0, 0, 1))


def test_opengl_conversion():
    # An OpenGL camera at (0,0,5) looking down -z (identity rotation) sees the origin
    # at the image centre; OpenCV camera_from_world must have the origin at +z depth 5.
    c2w_gl = np.eye(4)
    c2w_gl[2, 3] = 5
    cfw = opengl_to_opencv_c2w(c2w_gl)
    K = np.array([[10.0, 0, 8], [0, 10, 6], [0, 0, 1]])
    uv, z = project_points(np.array([[0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]]), K, cfw)
    np.testing.assert_allclose(z, 5)
    np.testing.assert_allclose(uv[0], [8, 6])
    assert uv[1, 1] < 6 and uv[2, 0] > 8  # world +y (GL up) is image up, +x right


def test_scale_intrinsics_pixel_centres():
    K = np.array([[100.0, 0, 32], [0, 90, 24], [0, 0, 1]])
    K2 = scale_intrinsics(K, 0.5)
    # the centre of the top-left pixel of a 2x2 block, (1.0, 1.0) in the big image, is the
    # centre (0.5, 0.5) of the small one
    np.testing.assert_allclose(K2 @ np.linalg.solve(K, [1.0, 1.0, 1.0]), [0.5, 0.5, 1.0])
    cam = Camera("a.png", 64, 48, K)
    s = cam.scaled(32, 24)
    np.testing.assert_allclose(s.K, K2)
    assert (s.width, s.height) == (32, 24)
    with pytest.raises(ValueError):
        Camera("a", 0, 10, K)
