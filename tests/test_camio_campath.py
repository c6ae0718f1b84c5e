"""Fly-through camera paths (camio.campath), float64."""

from __future__ import annotations

import numpy as np
import pytest

from _view_scene import make_cameras
from camio import Camera
from camio.cameras import camera_center, look_at, project_points, rotmat_to_qvec
from camio.campath import interpolate_path, look_centre, orbit_path, slerp


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The rotation angle between two rotations (stable near 0, unlike arccos of the trace)."""
    q = rotmat_to_qvec(Ra.T @ Rb)
    return float(2.0 * np.arctan2(np.linalg.norm(q[1:]), abs(q[0])))


def test_interpolate_passes_through_every_camera_in_order():
    cams = make_cameras(n=4)
    n = 6
    poses = interpolate_path(cams, n)
    assert poses.shape == ((len(cams) - 1) * n + 1, 4, 4)
    for i, c in enumerate(cams):
        np.testing.assert_allclose(poses[i * n, :3], c.cam_from_world, atol=1e-12)
    centres = camera_center(poses)
    for i in range(len(cams) - 1):
        a, b = cams[i], cams[i + 1]
        seg = centres[i * n:(i + 1) * n + 1]
        t = np.arange(n + 1) / n
        np.testing.assert_allclose(seg, (1 - t)[:, None] * a.center + t[:, None] * b.center, atol=1e-12)
        # slerp: the rotation turns at a constant rate from a to b
        total = _angle(a.R, b.R)
        assert total > 0.1
        for k in range(n + 1):
            assert _angle(a.R, poses[i * n + k, :3, :3]) == pytest.approx(t[k] * total, abs=1e-9)
            assert _angle(poses[i * n + k, :3, :3], b.R) == pytest.approx((1 - t[k]) * total, abs=1e-9)
    for R in poses[:, :3, :3]:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_interpolate_one_frame_per_segment_is_the_cameras():
    cams = make_cameras(n=3)
    poses = interpolate_path(cams, 1)
    np.testing.assert_allclose(poses[:, :3], np.stack([c.cam_from_world for c in cams]), atol=1e-12)


def test_slerp_takes_the_short_arc():
    qa = np.array([1.0, 0.0, 0.0, 0.0])
    qb = -rotmat_to_qvec(look_at(np.zeros(3), np.array([0.3, 0.0, 1.0]))[:3, :3])  # the long-way sign
    mid = slerp(qa, qb, np.array([0.5]))[0]
    assert np.linalg.norm(mid) == pytest.approx(1.0, abs=1e-12)
    assert mid[0] > 0.99  # a few degrees, not a turn of nearly 360


def test_orbit_keeps_the_centre_in_view_at_the_cameras_distance_and_height():
    cams = make_cameras(n=4, radius=3.0)
    centre = look_centre(cams)
    np.testing.assert_allclose(centre, 0.0, atol=1e-9)  # make_cameras all look at the origin
    frames = 24
    poses = orbit_path(cams, frames)
    assert poses.shape == (frames, 4, 4)
    up = -np.mean([c.R[1] for c in cams], axis=0)
    up /= np.linalg.norm(up)
    rel = np.stack([c.center for c in cams]) - centre
    want_h = np.mean(rel @ up)
    want_r = np.mean(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1))
    eyes = camera_center(poses)
    K = cams[0].K
    for m, eye in zip(poses, eyes):
        uv, z = project_points(centre[None], K, m)
        np.testing.assert_allclose(uv[0], K[:2, 2], atol=1e-9)  # on the optical axis
        assert z[0] > 0
        h = (eye - centre) @ up
        assert h == pytest.approx(want_h, abs=1e-9)
        assert np.linalg.norm(eye - centre - h * up) == pytest.approx(want_r, abs=1e-9)
        assert -m[1, :3] @ up > 0  # the image's up is the cameras' up side
    # a full circle in even steps, starting at the first camera's azimuth
    flat = eyes - centre - np.outer((eyes - centre) @ up, up)
    first = rel[0] - (rel[0] @ up) * up
    cos0 = flat[0] @ first / (np.linalg.norm(flat[0]) * np.linalg.norm(first))
    assert cos0 == pytest.approx(1.0, abs=1e-9)
    steps = [np.arccos(np.clip(flat[k] @ flat[(k + 1) % frames] / want_r ** 2, -1, 1)) for k in range(frames)]
    np.testing.assert_allclose(steps, 2 * np.pi / frames, atol=1e-9)


def test_orbit_refuses_parallel_axes():
    K = np.array([[50.0, 0, 20], [0, 50, 15], [0, 0, 1]])
    cams = [Camera(f"f{i}.png", 40, 30, K, look_at(np.array([0.3 * i, 0, -3]), np.array([0.3 * i, 0, 0])))
            for i in range(3)]
    with pytest.raises(ValueError, match="interpolate"):
        orbit_path(cams, 10)


def test_paths_refuse_bad_counts():
    cams = make_cameras(n=3)
    with pytest.raises(ValueError):
        interpolate_path(cams, 0)
    with pytest.raises(ValueError):
        orbit_path(cams, 0)
    with pytest.raises(ValueError):
        interpolate_path([], 3)
