"""evaluation.initialisers.bundle: bundle adjustment on a scene with exact correspondences must reduce the
reprojection error and the pose error, and keep the gauge (first camera, scale) fixed."""

import numpy as np
import pytest

from camio.cameras import Camera, look_at, project_points
from camio.colmap import SparseModel
from evaluation.initialisers.bundle import bundle_adjust, reprojection_errors
from evaluation.initialisers.oracle import OracleNoise, perturb_cameras
from evaluation.metrics.pose import evaluate_pose


def _scene(n_cams=5, n_points=300, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n_points, 3))
    cams = []
    for i, a in enumerate(np.linspace(-0.6, 0.6, n_cams)):
        eye = np.array([4 * np.sin(a), 0.5 * np.cos(2 * a), -4 * np.cos(a)])
        K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
        cams.append(Camera(f"im_{i:02d}.png", 320, 240, K, look_at(eye, np.zeros(3))[:3]))
    obs = {}
    for c in cams:
        uv, z = project_points(pts, c.K, c.cam_from_world)
        ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 320) & (uv[:, 1] > 0) & (uv[:, 1] < 240)
        obs[c.name] = (uv[ok], np.flatnonzero(ok))
    return SparseModel(cams, pts, np.full((n_points, 3), 128, np.uint8), obs)


def _pose_err(cams, truth):
    e = evaluate_pose(SparseModel(list(cams)), SparseModel(list(truth)))
    return e["ate_pct_radius"], e["rpe_rot_deg"]


def test_exact_correspondences_reduce_reprojection_and_pose_error():
    truth = _scene()
    rng = np.random.default_rng(3)
    noisy = perturb_cameras(truth.cameras, OracleNoise(rot_deg=1.5, trans_frac=0.03), rng)
    noisy[0] = truth.cameras[0]
    start = SparseModel(noisy, truth.points + rng.normal(0, 0.01, truth.points.shape), truth.colors,
                        truth.observations)
    ate0, rot0 = _pose_err(noisy, truth.cameras)
    e0 = reprojection_errors(start).mean()
    refined, stats = bundle_adjust(start, loss_scale_px=None)
    ate1, rot1 = _pose_err(refined.cameras, truth.cameras)
    assert e0 > 1.0 and stats["reproj_error_px_before"] == pytest.approx(e0)
    assert stats["reproj_error_px_after"] < 1e-3 < e0 / 100
    assert ate1 < ate0 / 20 and rot1 < rot0 / 20, (ate0, ate1, rot0, rot1)
    # the gauge: first camera constant, names and order kept
    assert [c.name for c in refined.cameras] == [c.name for c in noisy]
    np.testing.assert_allclose(refined.cameras[0].cam_from_world, noisy[0].cam_from_world, atol=1e-9)
    np.testing.assert_allclose(refined.cameras[1].K, noisy[1].K)  # focal not refined by default
    spread = lambda cams: sum(np.sum((c.center - cams[0].center) ** 2) for c in cams)  # noqa: E731
    assert spread(refined.cameras) == pytest.approx(spread(noisy), rel=1e-9)  # the scale is the input's


def test_refine_focal_recovers_a_wrong_focal():
    truth = _scene()
    K = truth.cameras[0].K.copy()
    K[0, 0] = K[1, 1] = 309.0  # 3 % off; the principal point is right
    wrong = [Camera(c.name, c.width, c.height, K, c.cam_from_world) for c in truth.cameras]
    start = SparseModel(wrong, truth.points, truth.colors, truth.observations)
    refined, stats = bundle_adjust(start, refine_focal=True, loss_scale_px=None)
    assert stats["reproj_error_px_after"] < 1e-3
    assert refined.cameras[2].K[0, 0] == pytest.approx(300.0, rel=1e-4)


def test_too_little_input_is_an_error():
    with pytest.raises(ValueError, match=">= 2 cameras"):
        bundle_adjust(SparseModel(_scene().cameras[:1]))
