"""The bundle-adjustment initialiser step (evaluation.initialisers.ba_init): on the synthetic scene it
lowers the pose error of noisy ground-truth-pose and oracle initialisers, writes a model that
COLMAP opens, moves the dense points with their cameras, and falls back (recorded) when the
images cannot be matched."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from camio.colmap import read_model, write_text_model
from camio.images import read_image, write_image
from evaluation.initialisers.ba_init import move_points_with_cameras, run_ba_init
from evaluation.initialisers.oracle import OracleNoise, perturb_cameras, run_oracle
from evaluation.metrics.pose import evaluate_pose
from evaluation.initialisers.posed import run_posed

NOISE = OracleNoise(rot_deg=1.3, trans_frac=0.03)  # about VGGT's pose error


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from camio.synthetic import write_synthetic_scene

    out = tmp_path_factory.mktemp("ba") / "scene"
    write_synthetic_scene(out, views=24, width=128, seed=0, n_gt_points=5000, n_ref_points=500)
    names = sorted(read_model(out).names)
    return out, [names[i] for i in np.round(np.linspace(0, len(names) - 1, 6)).astype(int)]  # the n = 6 rule


def _err(model_dir, ref, names):
    e = evaluate_pose(read_model(model_dir), ref, names)
    return e["ate_pct_radius"], e["rpe_rot_deg"]


def test_posed_ba_lowers_pose_error_and_writes_a_colmap_model(scene, tmp_path):
    import pycolmap

    root, train = scene
    ref = read_model(root)
    run_posed(root, train, tmp_path / "posed", NOISE, seed=1)
    st = run_ba_init(tmp_path / "posed", root / "images", train, tmp_path / "ba", seed_points="triangulated")
    assert st["ba"]["applied"] and not st["ba"]["fallback"] and st["ba"]["fallback_reason"] is None
    ba = st["ba"]["bundle_adjustment"]
    assert ba["reproj_error_px_after"] < ba["reproj_error_px_before"] / 3
    ate0, rot0 = _err(tmp_path / "posed" / "sparse" / "0", ref, train)
    ate1, rot1 = _err(tmp_path / "ba" / "sparse" / "0", ref, train)
    assert ate1 < ate0 / 1.5 and rot1 < rot0 / 2, (ate0, ate1, rot0, rot1)
    rec = pycolmap.Reconstruction(str(tmp_path / "ba" / "sparse" / "0"))  # COLMAP opens it
    assert rec.num_reg_images() == len(train) and rec.num_points3D() == st["points"] > 20
    first = read_model(tmp_path / "posed" / "sparse" / "0").camera(train[0])
    np.testing.assert_allclose(read_model(tmp_path / "ba" / "sparse" / "0").camera(train[0]).cam_from_world,
                               first.cam_from_world, atol=1e-6)
    assert json.loads((tmp_path / "ba" / "status.json").read_text())["ba"]["seed_points"] == "triangulated"


def test_oracle_ba_dense_seed_moves_with_the_cameras(scene, tmp_path):
    root, train = scene
    ref = read_model(root)
    run_oracle(root, train, tmp_path / "oracle", NOISE, seed=1, downsample=4)
    st = run_ba_init(tmp_path / "oracle", root / "images", train, tmp_path / "ba")
    assert st["ba"]["applied"] and st["ba"]["seed_points"] == "dense"
    ate0, rot0 = _err(tmp_path / "oracle" / "sparse" / "0", ref, train)
    ate1, rot1 = _err(tmp_path / "ba" / "sparse" / "0", ref, train)
    assert ate1 < ate0 and rot1 < rot0, (ate0, ate1, rot0, rot1)
    old, new = np.load(tmp_path / "oracle" / "predictions.npz"), np.load(tmp_path / "ba" / "predictions.npz")
    assert set(old.files) == set(new.files)
    model = read_model(tmp_path / "ba" / "sparse" / "0")
    for s, name in enumerate(old["image_names"]):
        np.testing.assert_allclose(new["cam_from_world"][s], model.camera(str(name)).cam_from_world, atol=1e-6)
        # the camera-frame coordinates of each view's points are unchanged
        p_old = old["world_points"][s].reshape(-1, 3) @ old["cam_from_world"][s][:, :3].T.astype(np.float64) \
            + old["cam_from_world"][s][:, 3]
        p_new = new["world_points"][s].reshape(-1, 3) @ new["cam_from_world"][s][:, :3].T.astype(np.float64) \
            + new["cam_from_world"][s][:, 3]
        np.testing.assert_allclose(p_new, p_old, atol=1e-4)


def test_move_points_round_trip():
    rng = np.random.default_rng(0)
    from camio.cameras import Camera, look_at

    a = look_at(np.array([0.0, 0, -3]), np.zeros(3))[:3]
    cam = Camera("a", 10, 10, np.eye(3), a)
    b = perturb_cameras([cam], OracleNoise(rot_deg=5, trans_frac=0.1), rng)[0].cam_from_world
    p = rng.normal(size=(7, 3))
    np.testing.assert_allclose(move_points_with_cameras(move_points_with_cameras(p, a, b), b, a), p, atol=1e-12)


def test_featureless_images_fall_back_and_say_so(scene, tmp_path):
    root, train = scene
    flat = tmp_path / "flat"
    for name in train:
        img = read_image(root / "images" / name)
        write_image(flat / name, np.full_like(img, 0.5))
    run_oracle(root, train, tmp_path / "oracle", NOISE, seed=1, downsample=4)
    st = run_ba_init(tmp_path / "oracle", flat, train, tmp_path / "ba")
    assert st["ba"]["fallback"] and not st["ba"]["applied"]
    assert "too few matches" in st["ba"]["fallback_reason"] or "failed" in st["ba"]["fallback_reason"]
    assert json.loads((tmp_path / "ba" / "status.json").read_text())["ba"]["fallback"] is True
    old, new = np.load(tmp_path / "oracle" / "predictions.npz"), np.load(tmp_path / "ba" / "predictions.npz")
    for k in old.files:  # the unrefined prediction, unchanged
        np.testing.assert_array_equal(old[k], new[k], err_msg=k)
    given, out = read_model(tmp_path / "oracle" / "sparse" / "0"), read_model(tmp_path / "ba" / "sparse" / "0")
    for c in out.cameras:
        np.testing.assert_allclose(c.cam_from_world, given.camera(c.name).cam_from_world, atol=1e-9)


def test_the_fallback_through_the_cli_keeps_the_seed_points(tmp_path):
    """A fallback exits 0 with the base model unchanged, its points included: the Bridge seeds
    from it (a model of cameras alone it refuses)."""
    from camio.synthetic import write_synthetic_scene

    root = write_synthetic_scene(tmp_path / "scene", views=6, width=48, seed=0, n_ref_points=200)
    base = read_model(root)
    train = base.names[:4]
    given = base.subset(train)
    write_text_model(tmp_path / "init" / "sparse" / "0", given.cameras, given.points, given.colors, given.observations)
    for name in train:  # featureless photos: nothing to match, so the adjustment falls back
        write_image(tmp_path / "flat" / name, np.full((36, 48, 3), 0.5, np.float32))
    (tmp_path / "train.txt").write_text("\n".join(train) + "\n")

    def run(*args):
        return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=120)

    proc = run("evaluation.initialisers.ba_init", "--init", str(tmp_path / "init"), "--images", str(tmp_path / "flat"),
               "--image-list", str(tmp_path / "train.txt"), "--out", str(tmp_path / "ba"), "--seed-points", "triangulated")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    st = json.loads((tmp_path / "ba" / "status.json").read_text())
    assert st["ba"]["fallback"] and st["points"] == len(given.points) > 0 and st["success_paper"]
    out = read_model(tmp_path / "ba" / "sparse" / "0")
    assert out.names == train
    np.testing.assert_allclose(out.points, given.points, atol=1e-9)
    np.testing.assert_array_equal(out.colors, given.colors)
    for c in out.cameras:
        np.testing.assert_allclose(c.cam_from_world, given.camera(c.name).cam_from_world, atol=1e-9)
        np.testing.assert_allclose(out.observations[c.name][0], given.observations[c.name][0], atol=1e-9)
    proc = run("bridge", "--colmap", str(tmp_path / "ba" / "sparse" / "0"), "--images", str(tmp_path / "flat"),
               "--out", str(tmp_path / "bridge"))
    assert proc.returncode == 0 and (tmp_path / "bridge" / "seed.ply").is_file(), (proc.stdout + proc.stderr)[-3000:]


def test_dense_seed_needs_predictions(scene, tmp_path):
    root, train = scene
    run_posed(root, train, tmp_path / "posed")
    with pytest.raises(ValueError, match="predictions.npz"):
        run_ba_init(tmp_path / "posed", root / "images", train, tmp_path / "ba")
