"""Sim(3) alignment: Umeyama with the reflection guard, collinear and coincident camera layouts,
camera transforms, and the ``align`` CLI.

Tolerances: noise-free fits are exact to float64 round-off (1e-9 relative).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from camio.cameras import Camera, camera_center, look_at, qvec_to_rotmat
from camio.colmap import read_model, write_text_model
from evaluation.metrics.align import (AlignmentError, Sim3, collinearity_ratio, fit_sim3_cameras,
                              rotation_angle_deg, transform_cam_from_world, umeyama)


def random_sim(rng: np.random.Generator) -> Sim3:
    q = rng.normal(size=4)
    return Sim3(float(np.exp(rng.uniform(-2, 2))), qvec_to_rotmat(q), rng.uniform(-5, 5, 3))


def random_cameras(rng, n, eyes=None) -> dict[str, np.ndarray]:
    """n cameras looking roughly at the origin; ``eyes`` [n, 3] overrides the centres."""
    if eyes is None:
        eyes = rng.normal(size=(n, 3)) * 2 + np.array([0, 0, -4.0])
    out = {}
    for i, e in enumerate(eyes):
        target = rng.normal(size=3) * 0.3
        up = np.array([0.0, -1.0, 0.0]) + rng.normal(size=3) * 0.2
        out[f"img{i:03d}.png"] = look_at(e, target, up)
    return out


def move_cameras(cams: dict[str, np.ndarray], sim: Sim3) -> dict[str, np.ndarray]:
    return {k: transform_cam_from_world(v, sim) for k, v in cams.items()}


quats = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(lambda q: np.linalg.norm(q) > 0.2)


class TestUmeyama:
    @settings(max_examples=40, deadline=None)
    @given(q=quats, log_s=st.floats(-3, 3), t=st.tuples(*[st.floats(-10, 10)] * 3),
           seed=st.integers(0, 2**16), n=st.integers(3, 12))
    def test_recovers_random_similarity(self, q, log_s, t, seed, n):
        rng = np.random.default_rng(seed)
        src = rng.normal(size=(n, 3))
        if collinearity_ratio(src) < 0.05:
            return  # degenerate draw; covered by the collinear tests
        sim = Sim3(np.exp(log_s), qvec_to_rotmat(np.array(q)), np.array(t))
        fit = umeyama(src, sim.apply(src))
        assert fit.s == pytest.approx(sim.s, rel=1e-9)
        np.testing.assert_allclose(fit.R, sim.R, atol=1e-8)
        np.testing.assert_allclose(fit.t, sim.t, atol=1e-8 * (1 + np.abs(sim.t).max()))

    def test_reflection_guard(self):
        rng = np.random.default_rng(1)
        src = rng.normal(size=(10, 3))
        dst = src * np.array([-1.0, 1.0, 1.0])  # a mirror image: no rotation fits exactly
        fit = umeyama(src, dst)
        assert np.linalg.det(fit.R) == pytest.approx(1.0)
        assert fit.s > 0

    def test_noise(self):
        rng = np.random.default_rng(2)
        src = rng.normal(size=(200, 3))
        sim = random_sim(rng)
        dst = sim.apply(src) + rng.normal(size=src.shape) * 1e-3 * sim.s
        fit = umeyama(src, dst)
        assert fit.s == pytest.approx(sim.s, rel=1e-3)
        assert rotation_angle_deg(fit.R.T @ sim.R) < 0.05

    def test_errors(self):
        with pytest.raises(AlignmentError, match="coincide"):
            umeyama(np.ones((4, 3)), np.zeros((4, 3)))
        with pytest.raises(AlignmentError, match="\\[N, 3\\]"):
            umeyama(np.zeros((4, 3)), np.zeros((3, 3)))


class TestFitCameras:
    def test_exact_from_random_cameras(self):
        rng = np.random.default_rng(3)
        for _ in range(10):
            ref = random_cameras(rng, int(rng.integers(3, 13)))
            sim = random_sim(rng)  # ref -> pred; the fit must find its inverse
            pred = move_cameras(ref, sim)
            al = fit_sim3_cameras(pred, ref)
            inv = sim.inverse()
            assert al.sim.s == pytest.approx(inv.s, rel=1e-9)
            np.testing.assert_allclose(al.sim.R, inv.R, atol=1e-8)
            np.testing.assert_allclose(al.sim.t, inv.t, atol=1e-8 * (1 + np.abs(inv.t).max()))
            assert al.rmse < 1e-9 * al.ref_radius
            assert np.max(al.rotation_residuals_deg) < 1e-6

    @pytest.mark.parametrize("n", [2, 3, 5])
    def test_collinear_centres_exact_with_orientations(self, n):
        rng = np.random.default_rng(4 + n)
        eyes = np.linspace(-1, 1, n)[:, None] * np.array([1.0, 0.2, 0.1]) + np.array([0, 0, -4.0])
        ref = random_cameras(rng, n, eyes)
        sim = random_sim(rng)
        pred = move_cameras(ref, sim)
        al = fit_sim3_cameras(pred, ref, min_cameras=2)
        assert al.collinear and al.used_orientations and al.collinearity < 1e-9
        inv = sim.inverse()
        assert al.sim.s == pytest.approx(inv.s, rel=1e-9)
        np.testing.assert_allclose(al.sim.R, inv.R, atol=1e-8)
        np.testing.assert_allclose(al.sim.t, inv.t, atol=1e-8 * (1 + np.abs(inv.t).max()))

    def test_arc_of_three_flagged(self):
        """Three views on a shallow 20-degree arc: flagged collinear, orientations used, and
        robust to a little noise; centres only ('never') reports the flag too."""
        rng = np.random.default_rng(5)
        ang = np.radians([-10, 0, 10])
        eyes = np.stack([4 * np.sin(ang), np.zeros(3), -4 * np.cos(ang)], axis=1)
        ref = random_cameras(rng, 3, eyes)
        sim = random_sim(rng)
        pred = move_cameras(ref, sim)
        noisy = {}
        for k, v in pred.items():  # 1e-3 radius noise on the centres
            c = camera_center(v) + rng.normal(size=3) * 1e-3 * sim.s
            noisy[k] = np.concatenate([v[:3, :3], (-v[:3, :3] @ c)[:, None]], axis=1)
        al = fit_sim3_cameras(noisy, ref)
        assert al.collinear and al.used_orientations
        assert rotation_angle_deg(al.sim.R.T @ sim.inverse().R) < 0.5
        al_never = fit_sim3_cameras(noisy, ref, use_orientations="never")
        assert al_never.collinear and not al_never.used_orientations

    def test_too_few_and_coincident(self):
        rng = np.random.default_rng(6)
        ref = random_cameras(rng, 3)
        with pytest.raises(AlignmentError, match="at least 3"):
            fit_sim3_cameras(ref, {k: ref[k] for k in list(ref)[:2]})
        same = random_cameras(rng, 4, np.zeros((4, 3)) + 1.0)
        with pytest.raises(AlignmentError, match="coincide"):
            fit_sim3_cameras(same, random_cameras(rng, 4))

    def test_unmatched_names_skipped(self):
        rng = np.random.default_rng(7)
        ref = random_cameras(rng, 5)
        pred = {k: v for k, v in list(ref.items())[:4]}
        al = fit_sim3_cameras(pred, ref, names=list(ref))
        assert len(al.names) == 4 and al.sim.s == pytest.approx(1.0)


def test_transform_cam_from_world_preserves_projection():
    rng = np.random.default_rng(8)
    sim = random_sim(rng)
    cam = look_at(np.array([0.3, -0.2, -3.0]), np.zeros(3))
    pts = rng.normal(size=(50, 3)) * 0.5
    a = pts @ cam[:3, :3].T + cam[:3, 3]
    moved = transform_cam_from_world(cam, sim)
    b = sim.apply(pts) @ moved[:, :3].T + moved[:, 3]
    np.testing.assert_allclose(b, sim.s * a, rtol=1e-10, atol=1e-10)
    back = transform_cam_from_world(moved, sim.inverse())
    np.testing.assert_allclose(back, cam[:3], atol=1e-10)


# --- the align CLI ---

def test_align_cli(tmp_path):
    from evaluation.__main__ import main

    rng = np.random.default_rng(11)
    names = [f"im{i:02d}.png" for i in range(12)]
    eyes = np.stack([3 * np.cos(np.linspace(0, 2, 12)), 0.1 * rng.normal(size=12),
                     3 * np.sin(np.linspace(0, 2, 12))], axis=1)
    ref_cfw = {n: look_at(e, np.zeros(3)) for n, e in zip(names, eyes)}
    K = np.array([[800.0, 0, 400], [0, 800, 300], [0, 0, 1]])
    write_text_model(tmp_path / "ref", [Camera(n, 800, 600, K, c) for n, c in ref_cfw.items()])
    test, train = names[::8], [n for i, n in enumerate(names) if i % 8][:3]
    sim = random_sim(rng)  # ref -> pred frame
    pred_K = np.array([[410.0, 0, 200], [0, 410, 150], [0, 0, 1]])
    write_text_model(tmp_path / "pred", [Camera(n, 400, 300, pred_K, transform_cam_from_world(ref_cfw[n], sim))
                                         for n in train])
    (tmp_path / "split.json").write_text(json.dumps(
        {"rule": "every8", "test": test, "train_pool": [n for n in names if n not in test], "train": {"3": train}}))
    rc = main(["align", "--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref"),
               "--train-names", str(tmp_path / "split.json"), "--n", "3", "--image-scale", "0.125",
               "--out", str(tmp_path / "out")])
    assert rc == 0
    rec = json.loads((tmp_path / "out" / "align.json").read_text())
    assert rec["scale"] == pytest.approx(1 / sim.s, rel=1e-9)
    assert rec["names"] == sorted(train) and rec["test_names"] == test
    assert rec["intrinsics"] == "reference" and rec["rmse"] < 1e-9
    assert rec["train_cameras"] == "initialiser"
    # the same fit labelled as refined training cameras; the label is recorded, the
    # results reader prefers align_refined/ and the report names it
    rc = main(["align", "--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref"),
               "--train-names", str(tmp_path / "split.json"), "--n", "3", "--image-scale", "0.125",
               "--train-cameras", "refined", "--out", str(tmp_path / "run" / "align_refined")])
    assert rc == 0
    (tmp_path / "run" / "align").mkdir()
    (tmp_path / "run" / "align" / "align.json").write_text((tmp_path / "out" / "align.json").read_text())
    from evaluation.reports.report import _heldout_cameras_note
    from evaluation.reports.results import read_run

    runs_dir = tmp_path / "res" / "ds" / "sc" / "n3"
    runs_dir.mkdir(parents=True)
    (tmp_path / "run").rename(runs_dir / "vggt")
    rec_run = read_run(runs_dir / "vggt")
    assert rec_run["heldout_cameras"] == "refined"
    import pandas as pd

    note = _heldout_cameras_note(pd.DataFrame([rec_run]))
    assert "refined during training" in note[0]
    model = read_model(tmp_path / "out")
    assert model.names == test
    for cam in model.cameras:
        assert (cam.width, cam.height) == (100, 75)
        np.testing.assert_allclose(cam.K, [[100, 0, 50], [0, 100, 37.5], [0, 0, 1]], atol=1e-9)
        expected = transform_cam_from_world(ref_cfw[cam.name], sim)  # the same camera in the pred frame
        np.testing.assert_allclose(cam.cam_from_world, expected, atol=1e-8)
