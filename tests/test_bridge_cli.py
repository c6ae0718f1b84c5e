"""End-to-end tests of ``python -m bridge``: outputs read back with pycolmap and plyfile.

Tolerances: cameras written as shortest round-trip decimals of float64 -> rtol 1e-12 against
the float64 values the Bridge computed; float32 inputs -> rtol 1e-6.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bridge.__main__ import main
from bridge.synthetic import write_synthetic_predictions
from camio.cameras import Camera, look_at, qvec_to_rotmat
from _machine_data import ABSENT, SCENES



def read_pycolmap(model_dir: Path):
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.read(str(model_dir))
    out = {}
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        pose = img.cam_from_world()
        xyzw = np.asarray(pose.rotation.quat)
        R = qvec_to_rotmat(np.r_[xyzw[3], xyzw[:3]])
        out[img.name] = (cam.model.name, cam.width, cam.height, np.asarray(cam.params), R,
                         np.asarray(pose.translation))
    return out, rec


def test_cli_predictions_end_to_end(tmp_path):
    npz = write_synthetic_predictions(tmp_path / "predictions.npz", n_views=3, height=10, width=14, scale=2.5)
    out = tmp_path / "out"
    assert main(["--pred", str(npz), "--out", str(out), "--stride", "3", "--max-points", "100", "--points3d",
                 "-q"]) == 0
    report = json.loads((out / "bridge.json").read_text())
    for key in ("s", "c_min", "c_max", "points_in", "points_kept", "dropped", "mode", "alpha_min", "alpha_max",
                "alpha_out", "timings_s"):
        assert key in report
    assert report["mode"] == "gated" and report["points_in"] == 3 * 10 * 14
    assert report["points_kept"] == 100 and report["dropped"]["max_points"] == 140 - 100
    assert report["timings_s"]["total"] > 0 and "load" in report["timings_s"]
    assert report["wall_time_s"] == report["timings_s"]["total"]  # read by evaluation.reports.results

    with np.load(npz) as z:
        raw = {k: z[k] for k in z.files}
    s = report["s"]
    pts = raw["world_points"].reshape(-1, 3).astype(np.float64)
    assert s == pytest.approx(1 / np.median(np.linalg.norm(pts, axis=1)), rel=1e-12)

    cams, rec = read_pycolmap(out / "sparse" / "0")
    assert sorted(cams) == sorted(str(n) for n in raw["image_names"])
    for v, name in enumerate(raw["image_names"]):
        model, w, h, params, R, t = cams[str(name)]
        K = raw["intrinsics_original"][v].astype(np.float64)
        assert model == "PINHOLE"
        assert (w, h) == tuple(int(x) for x in raw["image_sizes_original"][v])
        np.testing.assert_allclose(params, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=1e-12)
        ext = raw["cam_from_world"][v].astype(np.float64)
        np.testing.assert_allclose(R, ext[:, :3], atol=1e-6)
        np.testing.assert_allclose(t, ext[:, 3] * s, rtol=1e-9, atol=1e-9)
    assert rec.num_points3D() == 100

    from plyfile import PlyData

    v = PlyData.read(str(out / "seed.ply"))["vertex"]
    assert len(v) == 100
    alpha = 1 / (1 + np.exp(-v["opacity"].astype(np.float64)))
    assert alpha.min() >= 0.05 - 1e-6 and alpha.max() <= 0.5 + 1e-6


def test_cli_stride_1_keeps_every_valid_pixel_and_modes(tmp_path):
    npz = write_synthetic_predictions(tmp_path / "p.npz", n_views=2, height=6, width=8)
    assert main(["--pred", str(npz), "--out", str(tmp_path / "a"), "--stride", "1", "-q"]) == 0
    assert json.loads((tmp_path / "a" / "bridge.json").read_text())["points_kept"] == 2 * 6 * 8
    cams, rec = read_pycolmap(tmp_path / "a" / "sparse" / "0")
    assert len(cams) == 2 and rec.num_points3D() == 0  # cameras only unless --points3d
    assert main(["--pred", str(npz), "--out", str(tmp_path / "b"), "--mode", "filtered", "--stride", "1",
                 "--alpha-min", "0.1", "--alpha-max", "0.7", "-q"]) == 0
    rb = json.loads((tmp_path / "b" / "bridge.json").read_text())
    assert rb["mode"] == "filtered" and rb["percentile"] == 40.0 and rb["dropped"]["percentile"] > 0
    assert 0.1 <= rb["alpha_out"]["min"] and rb["alpha_out"]["max"] <= 0.7
    assert main(["--pred", str(npz), "--out", str(tmp_path / "c"), "--mode", "uniform",
                 "--uniform-alpha", "0.2", "-q"]) == 0
    rc = json.loads((tmp_path / "c" / "bridge.json").read_text())
    assert rc["alpha_out"]["min"] == pytest.approx(0.2) == pytest.approx(rc["alpha_out"]["max"])
    assert rc["stride"] == 20  # the paper's default for --pred


def _colmap_scene(tmp_path: Path) -> tuple[Path, Path, np.ndarray, np.ndarray, list[Camera]]:
    from camio.colmap import write_text_model
    from camio.images import write_image

    rng = np.random.default_rng(0)
    K = np.array([[40.0, 0, 20.5], [0, 41.0, 15.0], [0, 0, 1]])
    cams = [Camera(f"img{i}.png", 40, 30, K, look_at([np.sin(i) * 4, 0.5, -np.cos(i) * 4], [0, 0, 0])[:3])
            for i in range(3)]
    pts = rng.normal(size=(60, 3)) * 3.0 + [1.0, 0.0, 0.0]
    cols = rng.integers(0, 256, size=(60, 3)).astype(np.uint8)
    model = write_text_model(tmp_path / "colmap" / "sparse" / "0", cams, pts, cols)
    imgs = tmp_path / "images"
    for c in cams:
        write_image(imgs / c.name, np.full((30, 40, 3), 0.5, np.float32))
    return model, imgs, pts, cols, cams


def test_cli_colmap_end_to_end(tmp_path):
    model, imgs, pts, cols, cams = _colmap_scene(tmp_path)
    out = tmp_path / "out"
    assert main(["--colmap", str(model), "--images", str(imgs), "--out", str(out), "-q"]) == 0
    report = json.loads((out / "bridge.json").read_text())
    assert report["source"] == "colmap" and report["mode"] == "uniform" and report["c_min"] is None
    assert report["stride"] == 1 and report["points_kept"] == 60
    s = report["s"]
    assert s == pytest.approx(1 / np.median(np.linalg.norm(pts, axis=1)), rel=1e-12)

    got, rec = read_pycolmap(out / "sparse" / "0")
    for c in cams:
        model_name, w, h, params, R, t = got[c.name]
        assert (w, h) == (40, 30)
        np.testing.assert_allclose(params, [40.0, 41.0, 20.5, 15.0], rtol=1e-15)  # intrinsics kept
        np.testing.assert_allclose(R, c.R, atol=1e-12)
        np.testing.assert_allclose(t, c.t * s, rtol=1e-12, atol=1e-12)

    from plyfile import PlyData

    v = PlyData.read(str(out / "seed.ply"))["vertex"]
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), pts * s, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(v["opacity"], np.log(0.1 / 0.9), atol=1e-6)
    rgb = np.stack([v[f"f_dc_{i}"] for i in range(3)], 1) * 0.28209479177387814 + 0.5
    np.testing.assert_allclose(rgb * 255, cols, atol=1e-3)


def test_cli_errors(tmp_path, capsys):
    model, imgs, *_ = _colmap_scene(tmp_path)
    assert main(["--pred", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "o"), "-q"]) == 2
    bad = tmp_path / "bad.npz"
    np.savez(bad, world_points=np.zeros((1, 2, 2, 3)))
    assert main(["--pred", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "lacks keys" in capsys.readouterr().err
    assert main(["--colmap", str(model), "--out", str(tmp_path / "o"), "--mode", "filtered", "-q"]) == 2
    assert main(["--pred", str(bad), "--images", str(imgs), "--out", str(tmp_path / "o"), "-q"]) == 2
    (imgs / "img1.png").unlink()
    assert main(["--colmap", str(model), "--images", str(imgs), "--out", str(tmp_path / "o"), "-q"]) == 2
    assert not (tmp_path / "o" / "bridge.json").exists()
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "o")])  # neither --pred nor --colmap


def test_python_dash_m_bridge_runs(tmp_path):
    npz = write_synthetic_predictions(tmp_path / "p.npz", n_views=2, height=6, width=8)
    r = subprocess.run([sys.executable, "-m", "bridge", "--pred", str(npz), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "bridge wrote" in r.stderr and "done in" in r.stderr  # logs what it did and how long
    assert (tmp_path / "o" / "bridge.json").is_file()


@pytest.mark.shared_data
@pytest.mark.skipif(not (SCENES / "llff__fern/sparse/0").is_dir(), reason=ABSENT)
def test_cli_real_colmap_model_fern(tmp_path):
    """The real LLFF fern model (its pinhole part) through the COLMAP path of the Bridge."""
    from camio.colmap import read_model, write_text_model

    src = read_model(SCENES / "llff__fern/sparse/0", allow_distorted=True)
    model = write_text_model(tmp_path / "fern" / "sparse" / "0", src.cameras, src.points, src.colors)
    out = tmp_path / "out"
    assert main(["--colmap", str(model), "--images", str(SCENES / "llff__fern/images"),
                 "--out", str(out), "--outlier-removal", "--points3d", "-q"]) == 0
    report = json.loads((out / "bridge.json").read_text())
    assert report["points_in"] == len(src.points)
    assert 0 < report["dropped"]["outliers"] < 0.2 * len(src.points)
    got, rec = read_pycolmap(out / "sparse" / "0")
    assert len(got) == len(src.cameras) and rec.num_points3D() == report["points_kept"]
