"""The random-point initialiser: points in the volume the training cameras share, its depth
range from the cameras alone, the CLI's output contract, and the declared fallback of posed
(and COLMAP) when triangulation leaves too few points."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from camio.cameras import Camera, look_at
from camio.colmap import read_model, write_text_model
from camio.images import read_image, write_image
from evaluation.initialisers import random_init as ri

K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])


def ring(n: int = 3, radius: float = 4.0, arc: float = 1.2) -> list[Camera]:
    """n cameras on an arc of a circle, looking at the origin (converging axes)."""
    angles = np.linspace(0, arc, n)
    return [Camera(f"v{i}.png", 64, 48, K, look_at(np.array([radius * np.sin(a), 0.3, -radius * np.cos(a)]),
                                                   np.zeros(3))) for i, a in enumerate(angles)]


def forward(n: int = 3, baseline: float = 0.1) -> list[Camera]:
    """n cameras side by side looking down +z (parallel axes: a forward-facing capture)."""
    out = []
    for i in range(n):
        cfw = np.eye(4)[:3]
        cfw[:, 3] = [-baseline * i, 0, 0]
        out.append(Camera(f"f{i}.png", 64, 48, K, cfw))
    return out


def test_depth_range_from_converging_axes_is_the_focus_depth():
    near, far, how = ri.depth_range(ring(radius=4.0))
    d = np.linalg.norm([0, 0.3, 4.0])  # every camera's distance to the origin, where the axes meet
    assert near == pytest.approx(ri.NEAR_FRAC * d, rel=1e-9) and far == pytest.approx(ri.FAR_FRAC * d, rel=1e-9)
    assert "focus" in how


def test_depth_range_of_parallel_axes_uses_the_baseline():
    near, far, how = ri.depth_range(forward(3, baseline=0.1))
    d = ri.PARALLEL_DEPTH_BASELINES * 0.2  # the largest distance between centres
    assert (near, far) == pytest.approx((ri.NEAR_FRAC * d, ri.FAR_FRAC * d)) and "baseline" in how
    with pytest.raises(ValueError, match="one centre.*--near and --far"):
        ri.depth_range(forward(1))


@pytest.mark.parametrize("cams", [ring(3), forward(3)], ids=["converging", "parallel"])
def test_points_lie_where_two_views_see_them(cams):
    near, far, _ = ri.depth_range(cams)
    pts, colors = ri.random_points(cams, 3000, np.random.default_rng(1), near, far)
    assert pts.shape == (3000, 3) and pts.dtype == np.float64 and colors.shape == (3000, 3)
    assert colors.dtype == np.uint8 and np.all(colors == 128)  # 3DGS's near-grey SH DC
    seen = ri._views_seeing(pts, cams, near, far)
    assert seen.min() >= 2
    # uniform in the shared volume, not only near the cameras: depths spread over the range
    z = np.array([(cams[0].R @ p + cams[0].t)[2] for p in pts])
    assert z[seen >= 2].max() > near + 0.6 * (far - near)
    same, _ = ri.random_points(cams, 3000, np.random.default_rng(1), near, far)
    other, _ = ri.random_points(cams, 3000, np.random.default_rng(2), near, far)
    assert np.array_equal(pts, same) and not np.array_equal(pts, other)


def test_bad_input_is_refused_clearly():
    cams = ring(3)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="n_points must be > 0"):
        ri.random_points(cams, 0, rng, 1.0, 2.0)
    with pytest.raises(ValueError, match="0 < near < far"):
        ri.random_points(cams, 10, rng, 2.0, 1.0)
    with pytest.raises(ValueError, match="min_views"):
        ri.random_points(cams, 10, rng, 1.0, 2.0, min_views=4)
    with pytest.raises(ValueError, match="no cameras"):
        ri.random_points([], 10, rng, 1.0, 2.0)
    # cameras looking away from each other share no volume
    apart = [Camera("a.png", 64, 48, K, look_at(np.zeros(3), np.array([0, 0, 1.0]))),
             Camera("b.png", 64, 48, K, look_at(np.zeros(3), np.array([0, 0, -1.0])))]
    with pytest.raises(ValueError, match="share almost no volume"):
        ri.random_points(apart, 10, rng, 1.0, 2.0)


def _scene(root, flat: bool = False):
    """A synthetic scene (reference cameras); ``flat``: every image one grey, so SIFT finds no
    feature and triangulation no point."""
    from camio.synthetic import write_synthetic_scene

    scene = root / "scene"
    write_synthetic_scene(scene, views=8, width=64, seed=0, n_gt_points=500, n_ref_points=50)
    if flat:
        for p in sorted((scene / "images").iterdir()):
            write_image(p, np.full(read_image(p).shape, 0.5, np.float32))
    names = sorted(p.name for p in (scene / "images").iterdir())[:3]
    (root / "train.txt").write_text("\n".join(names) + "\n")
    return scene, names


def test_cli_writes_the_initialiser_contract(tmp_path):
    scene, names = _scene(tmp_path)
    rc = ri.main(["--cameras", str(scene / "sparse" / "0"), "--image-list", str(tmp_path / "train.txt"),
                  "--out", str(tmp_path / "out"), "--points", "500", "--seed", "3"])
    assert rc == 0
    status = json.loads((tmp_path / "out" / "status.json").read_text())
    assert status["success_paper"] and status["aligned_ok"] and status["reason"] is None
    assert (status["registered"], status["n_images"], status["points"], status["seed"]) == (3, 3, 500, 3)
    assert status["random"]["min_views"] == 2 and 0 < status["random"]["near"] < status["random"]["far"]
    model = read_model(tmp_path / "out" / "sparse" / "0")
    ref = read_model(scene / "sparse" / "0")
    assert model.names == names and len(model.points) == 500
    assert all(len(idx) == 0 for _, idx in model.observations.values())  # no observations: no depth prior
    for cam in model.cameras:  # the given cameras, unchanged
        np.testing.assert_allclose(cam.cam_from_world, ref.camera(cam.name).cam_from_world, atol=1e-9)
    # a training view without a camera: one clear error, nothing left behind
    (tmp_path / "bad.txt").write_text("nope.png\n")
    assert ri.main(["--cameras", str(scene / "sparse" / "0"), "--image-list", str(tmp_path / "bad.txt"),
                    "--out", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad" / "status.json").exists()


def test_default_count_is_3dgs_100k_but_never_more_than_the_pixels_support(tmp_path):
    # 3 views of 64x48: 9,216 pixels -> 0.25 per pixel = 2,304 points, not 100k
    scene, names = _scene(tmp_path)
    assert ri.main(["--cameras", str(scene / "sparse" / "0"), "--image-list", str(tmp_path / "train.txt"),
                    "--out", str(tmp_path / "out")]) == 0
    status = json.loads((tmp_path / "out" / "status.json").read_text())
    assert status["points"] == status["random"]["n_points"] == int(ri.POINTS_PER_PIXEL * 3 * 64 * 48) == 2304
    # LLFF at 1/8, three views: the pixels allow more than 100k, so 3DGS's count stands
    llff = [Camera(f"l{i}.png", 504, 378, K, np.eye(4)[:3]) for i in range(3)]
    assert ri.default_points(llff) == ri.N_POINTS == 100_000
    assert ri.default_points([Camera("t.png", 1, 1, K, np.eye(4)[:3])]) == 1  # never 0


def test_posed_falls_back_to_random_points_when_triangulation_finds_none(tmp_path):
    from evaluation.initialisers.posed import main as posed_main
    from evaluation.reports.results import collect_runs
    from evaluation.reports.run_status import run_status_table

    scene, names = _scene(tmp_path, flat=True)
    run = tmp_path / "results" / "ds" / "flat" / "n3" / "posed"
    assert posed_main(["--scene", str(scene), "--image-list", str(tmp_path / "train.txt"), "--out", str(run),
                       "--fallback-points", "400"]) == 0
    status = json.loads((run / "status.json").read_text())
    # the reconstruction's own result and success are unchanged ...
    assert status["points"] == 0 and status["success_paper"] is False and status["registered"] == 3
    assert len(read_model(run / "sparse" / "0").points) == 0
    # ... and the fallback is declared, with the model the Bridge seeds from
    fb = status["fallback"]
    assert fb["applied"] and fb["points_found"] == 0 and fb["min_points"] == ri.FALLBACK_MIN_POINTS
    assert fb["n_points"] == 400 and "random points" in fb["reason"]
    assert ri.seed_model_dir(run) == run / ri.FALLBACK_DIR / "sparse" / "0"
    seed = read_model(run / ri.FALLBACK_DIR / "sparse" / "0")
    assert seed.names == names and len(seed.points) == 400
    # named in the run-status table, never silent
    table = run_status_table(collect_runs(tmp_path / "results"), tmp_path / "results")
    row = table[table["init"] == "posed"].iloc[0]
    assert row["status"] == "ran, random-point fallback" and "random points" in row["why"]
    assert "gave 0 points" in row["why"]


def test_fallback_off_or_not_needed_leaves_the_model(tmp_path):
    run = tmp_path / "run"
    write_text_model(run / "sparse" / "0", ring(3), np.zeros((150, 3)), np.zeros((150, 3), np.uint8))
    (run / "status.json").write_text(json.dumps({"points": 150, "registered": 3}))
    assert ri.apply_fallback(run)["fallback"] == {"applied": False, "min_points": ri.FALLBACK_MIN_POINTS}
    assert ri.seed_model_dir(run) == run / "sparse" / "0"
    (run / "status.json").write_text(json.dumps({"points": 5, "registered": 3}))
    assert ri.apply_fallback(run, min_points=0)["fallback"]["applied"] is False  # 0 = off
    # one registered camera: no volume follows from it; recorded, the run's result stands
    write_text_model(run / "sparse" / "0", ring(1))
    (run / "status.json").write_text(json.dumps({"points": 0, "registered": 1}))
    fb = ri.apply_fallback(run)["fallback"]
    assert fb["applied"] is False and "one centre" in fb["error"]
    # no registered camera (a COLMAP run without a model): nothing to place points for
    shutil.rmtree(run / "sparse")
    (run / "status.json").write_text(json.dumps({"points": 0, "registered": 0}))
    assert ri.apply_fallback(run)["fallback"]["applied"] is False
    assert not (run / ri.FALLBACK_DIR).exists()


def test_colmap_cli_records_the_fallback_and_keeps_its_success(tmp_path, monkeypatch):
    """A COLMAP run that registered cameras but kept too few points: the CLI adds the fallback;
    success_paper and points stay the reconstruction's."""
    from evaluation.initialisers import colmap_baseline

    def fake_run(images, names, out, seed=0, settings=None, keep_work=False):
        write_text_model(tmp_path / "out" / "sparse" / "0", ring(3))
        status = {"success_paper": False, "aligned_ok": False, "registered": 3, "n_images": 3, "points": 0,
                  "reason": "no points", "seed": seed}
        (tmp_path / "out" / "status.json").write_text(json.dumps(status))
        return status

    monkeypatch.setattr(colmap_baseline, "run_colmap", fake_run)
    images = tmp_path / "images"
    for i in range(3):
        write_image(images / f"v{i}.png", np.full((48, 64, 3), 0.5, np.float32))
    assert colmap_baseline.main(["--images", str(images), "--names", "v0.png", "v1.png", "v2.png",
                                 "--out", str(tmp_path / "out"), "--fallback-points", "300"]) == 0
    status = json.loads((tmp_path / "out" / "status.json").read_text())
    assert status["success_paper"] is False and status["points"] == 0 and status["reason"] == "no points"
    assert status["fallback"]["applied"] and status["fallback"]["n_points"] == 300
    assert len(read_model(ri.seed_model_dir(tmp_path / "out")).points) == 300
