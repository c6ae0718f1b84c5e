"""Pose error (ATE, RPE, alignment-free relative rotation error, fy/fx) and the accuracy gate.

The gate test builds COLMAP models that pass the paper's success criterion (all views
registered, points present) but whose poses are wrong (scrambled among the images, or a
mirror image of the scene), and checks that the accuracy gate fails them.
Tolerances: exact cases to 1e-9 (float64 round-off; COLMAP text stores shortest round-trip
decimals, so files are lossless).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from camio.cameras import Camera, camera_center, look_at, qvec_to_rotmat
from camio.colmap import SparseModel, write_text_model
from evaluation.metrics.align import Sim3, transform_cam_from_world
from evaluation.metrics.pose import GateConfig, accuracy_gate, evaluate_pose, relative_pose_errors

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def ring_cameras(n=8, radius=4.0, seed=0) -> list[Camera]:
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 1.5 * np.pi, n)
    eyes = np.stack([radius * np.cos(ang), 0.3 * rng.normal(size=n), radius * np.sin(ang)], axis=1)
    return [Camera(f"v{i:02d}.jpg", 640, 480, K, look_at(e, rng.normal(size=3) * 0.2)) for i, e in enumerate(eyes)]


def model(cams, n_points=20, seed=1) -> SparseModel:
    return SparseModel(cams, np.random.default_rng(seed).normal(size=(n_points, 3)))


def moved(cams, sim: Sim3) -> list[Camera]:
    return [Camera(c.name, c.width, c.height, c.K, transform_cam_from_world(c.cam_from_world, sim)) for c in cams]


SIM = Sim3(0.37, qvec_to_rotmat(np.array([0.3, -0.5, 0.2, 0.7])), np.array([1.0, -2.0, 0.5]))


def test_relative_errors_hand_computed():
    a = look_at(np.array([0.0, 0, -4]), np.zeros(3))
    b = look_at(np.array([2.0, 0, -4]), np.array([2.0, 0, 0]))  # baseline along +x
    ref = np.stack([a, b])
    # turn camera b by 10 degrees about its own y axis, keeping its centre
    rot = qvec_to_rotmat(np.array([np.cos(np.radians(5)), 0, np.sin(np.radians(5)), 0]))
    b2 = b.copy()
    b2[:3, :3] = rot @ b[:3, :3]
    b2[:3, 3] = -b2[:3, :3] @ camera_center(b)
    out = relative_pose_errors(np.stack([a, b2]), ref)
    assert out["rot_deg"][0] == pytest.approx(10.0, abs=1e-9)
    # the centre is unchanged and camera a unchanged: t_ab direction in frame a is unchanged
    assert out["trans_dir_deg"][0] == pytest.approx(0.0, abs=1e-9)
    # move b's centre to the other side of a: the direction flips
    b3 = b.copy()
    b3[:3, 3] = -b[:3, :3] @ np.array([-2.0, 0, -4])
    assert relative_pose_errors(np.stack([a, b3]), ref)["trans_dir_deg"][0] == pytest.approx(180.0, abs=1e-9)


def test_exact_similarity_is_perfect_and_gated_success():
    ref = ring_cameras()
    rec = evaluate_pose(model(moved(ref, SIM)), model(ref))
    assert rec["n_matched"] == 8 and rec["registered"] == 8
    assert rec["ate_rmse"] < 1e-9 and rec["ate_rel_radius"] < 1e-9
    assert rec["rpe_rot_deg"] < 1e-6 and rec["rpe_trans_dir_deg"] < 1e-6
    assert rec["rel_rot_err_max_deg"] < 1e-6
    assert rec["alignment"]["scale"] == pytest.approx(1 / SIM.s, rel=1e-9)
    assert rec["fy_fx_mean"] == pytest.approx(1.0) and rec["fy_fx_max_dev"] == pytest.approx(0.0)
    assert rec["success_paper"] is True and rec["success_gated"] is True


def test_noise_gives_the_expected_ate():
    ref = ring_cameras(n=12)
    rng = np.random.default_rng(5)
    sigma = 0.02  # per-axis centre noise in reference units
    noisy = []
    for c in ref:
        centre = c.center + rng.normal(size=3) * sigma
        noisy.append(Camera(c.name, 640, 480, K, np.c_[c.R, -c.R @ centre]))
    rec = evaluate_pose(model(noisy), model(ref))
    # ATE after a 7-dof fit on 12 cameras: E[ATE^2] = sigma^2 (3 N - 7) / N
    assert rec["ate_rmse"] == pytest.approx(sigma * np.sqrt((36 - 7) / 12), rel=0.5)
    assert rec["ate_rel_radius"] == pytest.approx(rec["ate_rmse"] / rec["trajectory_radius"])
    assert rec["success_gated"] is True


@pytest.mark.parametrize("wrong", ["scrambled", "reflected"])
def test_gate_fails_wrong_poses_that_pass_the_paper_criterion(tmp_path, wrong):
    from evaluation.__main__ import main

    ref = ring_cameras()
    if wrong == "scrambled":  # every image gets another image's pose
        perm = np.roll(np.arange(len(ref)), 3)
        bad = [Camera(c.name, 640, 480, K, ref[j].cam_from_world) for c, j in zip(ref, perm)]
    else:  # mirror image of the rig (world x -> -x, image x -> -x): proper rotations, wrong scene
        m = np.diag([-1.0, 1.0, 1.0])
        bad = [Camera(c.name, 640, 480, K, np.c_[m @ c.R @ m, m @ c.t]) for c in ref]
    write_text_model(tmp_path / "pred", moved(bad, SIM), np.random.default_rng(0).normal(size=(30, 3)))
    write_text_model(tmp_path / "ref", ref)
    out = tmp_path / "pose.json"
    assert main(["pose", "--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref"), "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    for key in ("ate_rmse", "ate_rel_radius", "rpe_rot_deg", "rpe_trans_dir_deg", "n_matched"):
        assert key in rec
    assert rec["registered"] == 8 and rec["n_points"] == 30
    assert rec["success_paper"] is True
    assert rec["success_gated"] is False
    assert rec["ate_rel_radius"] > 0.05 or rec["rel_rot_err_mean_deg"] > 5.0


def test_gate_thresholds_are_options(tmp_path):
    from evaluation.__main__ import main

    ref = ring_cameras()
    rot = qvec_to_rotmat(np.array([np.cos(np.radians(1.5)), np.sin(np.radians(1.5)), 0, 0]))  # 3 degrees
    tilted = [Camera(c.name, 640, 480, K, np.c_[rot @ c.R, -(rot @ c.R) @ c.center]) if i % 2 else c
              for i, c in enumerate(ref)]
    write_text_model(tmp_path / "pred", tilted, np.zeros((1, 3)))
    write_text_model(tmp_path / "ref", ref)
    args = ["pose", "--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref")]
    main(args + ["--out", str(tmp_path / "a.json")])
    main(args + ["--out", str(tmp_path / "b.json"), "--max-rel-rot-deg", "1.0"])
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json"))
    assert 1.0 < a["rel_rot_err_mean_deg"] < 5.0
    assert a["success_gated"] is True and b["success_gated"] is False
    assert b["gate"]["max_rel_rot_deg"] == 1.0


def test_too_few_registered_and_names(tmp_path):
    ref = ring_cameras()
    names = [c.name for c in ref[:4]]
    rec = evaluate_pose(model(moved(ref[:2], SIM)), model(ref), names=names)
    assert rec["n_names"] == 4 and rec["registered"] == 2 and rec["registered_fraction"] == 0.5
    assert rec["ate_rmse"] is None and rec["rpe_rot_deg"] is not None
    # the paper's criterion (>= 1 registered, >= 1 point) holds; the gate needs >= 3 views
    assert rec["success_paper"] is True and rec["success_gated"] is False
    rec3 = evaluate_pose(model(moved(ref[:3], SIM)), model(ref), names=names)
    assert rec3["success_paper"] is True and rec3["success_gated"] is True
    no_points = evaluate_pose(model(moved(ref, SIM), n_points=0), model(ref))
    assert no_points["success_paper"] is False


def test_focal_ratio_flags_drift():
    ref = ring_cameras(n=4)
    k2 = K.copy()
    k2[1, 1] *= 1.3
    pred = [Camera(c.name, 640, 480, k2 if i == 0 else K, c.cam_from_world) for i, c in enumerate(ref)]
    rec = evaluate_pose(model(pred), model(ref))
    assert rec["fy_fx_max"] == pytest.approx(1.3) and rec["fy_fx_max_dev"] == pytest.approx(0.3)


def test_accuracy_gate_without_reference():
    assert accuracy_gate({"success_paper": True, "has_reference": False}) is None
    assert accuracy_gate({"success_paper": False, "has_reference": False}) is None
    assert accuracy_gate({"success_paper": True}) is False  # reference but no figures
    g = GateConfig(max_ate_rel_radius=0.1, max_rel_rot_deg=2.0)
    assert accuracy_gate({"success_paper": True, "ate_rel_radius": 0.08, "rel_rot_err_mean_deg": 1.0}, g) is True
    assert accuracy_gate({"success_paper": True, "ate_rel_radius": 0.08, "rel_rot_err_mean_deg": 3.0}, g) is False


def test_dispatcher_images_missing_and_clear_errors(tmp_path, monkeypatch, capsys):
    import sys

    from evaluation.__main__ import main

    import evaluation.metrics

    monkeypatch.setitem(sys.modules, "evaluation.metrics.images_cli", None)  # import fails
    # an earlier test may have imported it: the package attribute would satisfy the import
    monkeypatch.delattr(evaluation.metrics, "images_cli", raising=False)
    assert main(["images", "--pred", "a", "--gt", "b", "--out", "c"]) == 2
    assert "importing evaluation.metrics.images_cli failed" in capsys.readouterr().err
    # a bad input is an error message and exit status 1, not a traceback
    assert main(["pose", "--pred", str(tmp_path / "none"), "--ref", str(tmp_path / "ref"), "--out", str(tmp_path / "p.json")]) == 2
    assert "pose failed: no COLMAP model" in capsys.readouterr().err
