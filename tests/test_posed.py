"""The posed initialiser: reference cameras of the training views + points triangulated with
those cameras fixed (pycolmap), optionally with the oracle's seeded noise."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from camio.cameras import project_points
from camio.colmap import read_model
from evaluation.initialisers.oracle import OracleNoise
from evaluation.initialisers.posed import REFERENCE_SOURCE, run_posed

TRAIN = ["0001.png", "0003.png", "0005.png", "0007.png"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from camio.synthetic import write_synthetic_scene

    out = tmp_path_factory.mktemp("posed") / "scene"
    write_synthetic_scene(out, views=10, width=128, seed=0, n_gt_points=5000, n_ref_points=500)
    return out


@pytest.fixture(scope="module")
def exact(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("exact")
    return out, run_posed(scene, TRAIN, out)


def test_exact_cameras_and_points_on_the_surface(scene, exact):
    out, status = exact
    assert status["success_paper"] and status["aligned_ok"] and status["registered"] == 4
    assert status["points"] > 30 and status["reference_source"] == REFERENCE_SOURCE
    assert json.loads((out / "status.json").read_text())["points"] == status["points"]
    model, ref = read_model(out / "sparse" / "0"), read_model(scene)
    assert model.names == TRAIN  # the training views only
    for c in model.cameras:
        np.testing.assert_allclose(c.cam_from_world, ref.camera(c.name).cam_from_world, atol=1e-9)
        np.testing.assert_allclose(c.K, ref.camera(c.name).K, rtol=1e-12)
    # every triangulated point lies on the ground-truth surface seen from its views
    rel = []
    for c in model.cameras:
        xy, idx = model.observations[c.name]
        uv, z = project_points(model.points[idx], c.K, c.cam_from_world)
        err = np.linalg.norm(uv - xy, axis=1)
        assert np.nanmax(err) < 4.0 and np.nanmedian(err) < 0.5  # COLMAP's 4 px filter; typically sub-pixel
        depth = np.load(scene / "gt" / "depth" / f"{c.name[:-4]}.npy")
        col = np.clip(xy[:, 0].astype(int), 0, c.width - 1)
        row = np.clip(xy[:, 1].astype(int), 0, c.height - 1)
        gz = depth[row, col]
        ok = gz > 0
        rel.append(np.abs(z[ok] - gz[ok]) / gz[ok])
    assert np.median(np.concatenate(rel)) < 0.02


def test_noise_is_seeded_and_moves_cameras(scene, exact, tmp_path):
    noise = OracleNoise(rot_deg=2.0, trans_frac=0.05, depth_rel=0.02, outlier_frac=0.1)
    a = run_posed(scene, TRAIN, tmp_path / "a", noise, seed=4)
    b = run_posed(scene, TRAIN, tmp_path / "b", noise, seed=4)
    ma, mb = read_model(tmp_path / "a"), read_model(tmp_path / "b")
    assert a["points"] == b["points"] and a["noise"]["rot_deg"] == 2.0
    np.testing.assert_array_equal(ma.points, mb.points)
    ref = read_model(exact[0] / "sparse" / "0")
    moved = [np.abs(c.cam_from_world - ref.camera(c.name).cam_from_world).max() for c in ma.cameras]
    assert min(moved) > 1e-4


def test_cli_refuses_a_scene_without_reference(scene, tmp_path):
    shutil.copytree(scene / "images", tmp_path / "s" / "images")
    r = subprocess.run([sys.executable, "-m", "evaluation.initialisers.posed", "--scene", str(tmp_path / "s"),
                        "--names", *TRAIN, "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "no reference cameras" in r.stderr and not (tmp_path / "o").exists()


from _machine_data import ABSENT, SCENES as SHARED  # noqa: E402


@pytest.mark.shared_data
@pytest.mark.skipif(not (SHARED / "strecha__fountain-P11").is_dir(), reason=ABSENT)
def test_real_posed_scene(tmp_path):
    """fountain-P11 (LIDAR-calibrated cameras): 3 training views give hundreds of points."""
    from camio.prepare import prepare_scene

    scene = prepare_scene(SHARED / "strecha__fountain-P11", tmp_path / "scene", ns=(3,))
    train = json.loads((scene / "split.json").read_text())["train"]["3"]
    status = run_posed(scene, train, tmp_path / "posed")
    assert status["success_paper"] and status["registered"] == 3 and status["points"] > 100
    assert status["triangulation"]["mean_reproj_error_px"] < 1.0
