"""The oracle initialiser: exact ground truth at zero noise, seeded noise of the stated size,
confidence that ranks the injected depth errors, and the predictions.npz contract."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camio.cameras import Camera, camera_center, look_at, project_points
from camio.colmap import write_text_model
from camio.images import write_image
from evaluation.initialisers.oracle import (
    OracleNoise,
    make_oracle_predictions,
    main,
    perturb_cameras,
    rotation_from_axis_angle,
    run_oracle,
    unproject_depth,
)

W, H = 40, 30
NAMES = ["a.png", "b.png", "c.png", "d.png"]


def _cameras() -> list[Camera]:
    K = np.array([[35.0, 0.0, W / 2 + 0.3], [0.0, 36.0, H / 2 - 0.2], [0.0, 0.0, 1.0]])
    cams = []
    for i, name in enumerate(NAMES):
        ang = np.deg2rad(-30 + 20 * i)
        eye = np.array([3 * np.sin(ang), 0.2 * i, -3 * np.cos(ang)])
        cams.append(Camera(name, W, H, K, look_at(eye, np.zeros(3))[:3]))
    return cams


@pytest.fixture()
def scene(tmp_path) -> Path:
    """Reference cameras, images and z-depth maps (random, with a background patch)."""
    rng = np.random.default_rng(1)
    cams = _cameras()
    write_text_model(tmp_path / "sparse" / "0", cams)
    (tmp_path / "gt" / "depth").mkdir(parents=True)
    for cam in cams:
        write_image(tmp_path / "images" / cam.name, rng.random((H, W, 3)).astype(np.float32))
        depth = rng.uniform(2.0, 4.0, (H, W)).astype(np.float32)
        depth[:4, :6] = 0.0  # background
        np.save(tmp_path / "gt" / "depth" / f"{Path(cam.name).stem}.npy", depth)
    return tmp_path


def test_zero_noise_reproduces_ground_truth(scene):
    arrays, noisy = make_oracle_predictions(scene, NAMES[:3], OracleNoise())
    cams = {c.name: c for c in _cameras()}
    for s, name in enumerate(arrays["image_names"]):
        ref = cams[str(name)]
        np.testing.assert_allclose(arrays["cam_from_world"][s], ref.cam_from_world, atol=1e-6)
        gt = np.load(scene / "gt" / "depth" / f"{Path(str(name)).stem}.npy").astype(np.float64)
        valid = gt > 0
        pts = arrays["world_points"][s].astype(np.float64)
        uv, z = project_points(pts[valid], ref.K, ref.cam_from_world)
        rows, cols = np.nonzero(valid)
        np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], 1), atol=2e-4)
        np.testing.assert_allclose(z, gt[valid], rtol=1e-6)
        np.testing.assert_array_equal(arrays["depth"][s], gt.astype(np.float32))
        conf = arrays["world_points_conf"][s]
        assert np.all(conf[valid] == pytest.approx(11.0)) and np.all(conf[~valid] == 1.0)


def test_contract_keys_shapes_dtypes(scene, tmp_path):
    out = tmp_path / "out"
    status = run_oracle(scene, NAMES, out, OracleNoise(depth_rel=0.05), seed=0, downsample=2)
    d = np.load(out / "predictions.npz")
    S, h, w = len(NAMES), H // 2, W // 2
    assert d["image_names"].tolist() == NAMES
    assert d["cam_from_world"].shape == (S, 3, 4) and d["cam_from_world"].dtype == np.float32
    assert d["intrinsics"].shape == (S, 3, 3) and d["intrinsics_original"].shape == (S, 3, 3)
    np.testing.assert_allclose(d["intrinsics"][0, :2], d["intrinsics_original"][0, :2] / 2, rtol=1e-6)
    assert d["image_sizes_original"].tolist() == [[W, H]] * S
    assert d["world_points"].shape == (S, h, w, 3) and d["world_points"].dtype == np.float32
    assert d["world_points_conf"].shape == (S, h, w) and np.all(d["world_points_conf"] >= 1.0)
    assert d["colors"].shape == (S, h, w, 3) and d["colors"].dtype == np.uint8
    assert d["depth"].shape == (S, h, w) and d["depth_conf"].shape == (S, h, w)
    assert status["success_paper"] is True and status["registered"] == S and status["grid_size"] == [h, w]
    assert json.loads((out / "status.json").read_text())["noise"]["depth_rel"] == 0.05
    assert (out / "sparse" / "0" / "cameras.txt").is_file()


def test_seeded_and_repeatable(scene):
    noise = OracleNoise(rot_deg=2, trans_frac=0.05, depth_rel=0.05, outlier_frac=0.1, conf_noise=0.5)
    a, _ = make_oracle_predictions(scene, NAMES, noise, seed=4)
    b, _ = make_oracle_predictions(scene, NAMES, noise, seed=4)
    c, _ = make_oracle_predictions(scene, NAMES, noise, seed=5)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["world_points"], c["world_points"])


def test_pose_noise_has_the_stated_rms():
    """Over many cameras the RMS rotation angle and centre displacement match the config."""
    rng = np.random.default_rng(0)
    K = np.eye(3)
    cams = [Camera(f"{i}", 4, 4, K, look_at(rng.normal(size=3) * 2, np.zeros(3))[:3]) for i in range(4000)]
    centers = np.stack([c.center for c in cams])
    radius = np.sqrt(np.mean(np.sum((centers - centers.mean(0)) ** 2, 1)))
    noisy = perturb_cameras(cams, OracleNoise(rot_deg=3.0, trans_frac=0.1), np.random.default_rng(1))
    ang = [np.rad2deg(Rotation.from_matrix(n.R @ c.R.T).magnitude()) for n, c in zip(noisy, cams)]
    shift = np.linalg.norm(np.stack([n.center for n in noisy]) - centers, axis=1)
    assert np.sqrt(np.mean(np.square(ang))) == pytest.approx(3.0, rel=0.05)
    assert np.sqrt(np.mean(shift**2)) == pytest.approx(0.1 * radius, rel=0.05)
    for n in noisy[:10]:  # still proper rotations
        np.testing.assert_allclose(n.R @ n.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(n.R) == pytest.approx(1.0)


def test_confidence_ranks_the_injected_depth_error(scene):
    noise = OracleNoise(depth_rel=0.05, outlier_frac=0.1, conf_noise=0.3)
    arrays, _ = make_oracle_predictions(scene, NAMES, noise, seed=2)
    gt = np.stack([np.load(scene / "gt" / "depth" / f"{Path(n).stem}.npy") for n in NAMES]).astype(np.float64)
    valid = gt > 0
    err = np.abs(arrays["depth"][valid] / gt[valid] - 1)
    conf = arrays["world_points_conf"][valid]
    from scipy.stats import spearmanr

    rho = spearmanr(err, conf).statistic
    assert rho < -0.7
    # exact ranking without confidence noise
    exact, _ = make_oracle_predictions(scene, NAMES, OracleNoise(depth_rel=0.05), seed=2)
    err2 = np.abs(exact["depth"][valid] / gt[valid] - 1)
    assert spearmanr(err2, exact["world_points_conf"][valid]).statistic < -0.999


def test_rodrigues_matches_scipy():
    v = np.random.default_rng(3).normal(size=(50, 3)) * 1.5
    np.testing.assert_allclose(rotation_from_axis_angle(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rotation_from_axis_angle(np.zeros(3)), np.eye(3), atol=0)


def test_unproject_handles_skew_exactly():
    K = np.array([[50.0, 2.0, 20.0], [0.0, 45.0, 15.0], [0, 0, 1]])
    pose = look_at(np.array([0.5, -0.2, -3.0]), np.zeros(3))[:3]
    z = np.random.default_rng(0).uniform(1, 3, (5, 7))
    rows, cols = np.arange(5) * 3, np.arange(7) * 2
    pts = unproject_depth(z, K, pose, rows, cols)
    uv, zz = project_points(pts.reshape(-1, 3), K, pose)
    cc, rr = np.meshgrid(cols + 0.5, rows + 0.5)
    np.testing.assert_allclose(uv, np.stack([cc.ravel(), rr.ravel()], 1), atol=1e-9)
    np.testing.assert_allclose(zz, z.ravel(), rtol=1e-12)
    assert camera_center(pose).shape == (3,)


def test_errors_are_clear(scene, tmp_path):
    with pytest.raises(ValueError, match="no reference camera"):
        make_oracle_predictions(scene, ["zzz.png"], OracleNoise())
    (scene / "gt" / "depth" / "b.npy").unlink()
    with pytest.raises(FileNotFoundError, match="gt/depth"):
        make_oracle_predictions(scene, ["a.png", "b.png"], OracleNoise())
    with pytest.raises(ValueError, match="rot_deg"):
        OracleNoise(rot_deg=-1)


def test_cli_reads_the_split(scene, tmp_path, tmp_path_factory):
    split = {"rule": "every8", "test": ["a.png"], "train_pool": NAMES[1:], "train": {"3": NAMES[1:]}}
    (tmp_path / "split.json").write_text(json.dumps(split))
    out = tmp_path_factory.mktemp("oracle_cli") / "cli"  # outside the scene: the output rule
    assert main(["--scene", str(scene), "--split", str(tmp_path / "split.json"), "--n", "3",
                 "--out", str(out), "--rot-deg", "1", "--seed", "7"]) == 0
    d = np.load(out / "predictions.npz")
    assert d["image_names"].tolist() == NAMES[1:]  # the test image is never used
