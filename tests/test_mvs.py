"""The dense multi-view-stereo initialiser (``python -m evaluation.initialisers.mvs``).

Accuracy against the synthetic scene's exact depth through the CLI (the targets: at 3 views
delta1 >= 0.9 over the kept pixels and completeness >= 0.6; 6 and 12 views on a smaller scene),
the confidence ranking the error, the files it writes (predictions.npz in vggt_init's schema,
a COLMAP model pycolmap opens, status.json) and the Bridge reading them with every mode, and
the stiff cases: textureless and repeated texture, two views, views that do not overlap, a
baseline of nothing and a forward move (points behind a camera), 4,000-pixel photos.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from camio.cameras import Camera, look_at
from camio.colmap import read_model, write_text_model
from camio.images import write_image
from evaluation.initialisers.mvs.__main__ import main
from evaluation.initialisers.mvs.run import MvsConfig
from evaluation.initialisers.mvs.accuracy import depth_accuracy
from evaluation.initialisers.mvs.sweep import inverse_depth_planes, plane_sweep

#: the contract's keys of predictions.npz (docs/contracts.md, vggt_init output)
KEYS = {"image_names", "cam_from_world", "intrinsics", "intrinsics_original", "image_sizes_original",
        "world_points", "world_points_conf", "colors", "depth", "depth_conf"}


def _synthetic(root: Path, width: int, ns=(3, 6, 12)) -> Path:
    from camio.synthetic import write_synthetic_scene

    return write_synthetic_scene(root, views=24, width=width, ns=ns)


def _names(scene: Path, n: int) -> list[str]:
    return json.loads((scene / "split.json").read_text())["train"][str(n)]


def _run(scene: Path, names: list[str], out: Path, *extra: str) -> int:
    lst = out.parent / f"{out.name}.txt"
    lst.write_text("\n".join(names) + "\n")
    return main(["--scene", str(scene), "--image-list", str(lst), "--out", str(out), "-q", *extra])


def _accuracy(scene: Path, out: Path) -> dict:
    pred = np.load(out / "predictions.npz")
    names = [str(n) for n in pred["image_names"]]
    gt = [np.load(scene / "gt" / "depth" / f"{Path(n).stem}.npy") for n in names]
    depth = np.where(pred["depth"] > 0, pred["depth"], np.nan)
    return depth_accuracy(list(depth), list(pred["depth_conf"]), gt)


@pytest.fixture(scope="module")
def scene256(tmp_path_factory) -> Path:
    return _synthetic(tmp_path_factory.mktemp("mvs") / "scene", 256, ns=(3,))


@pytest.fixture(scope="module")
def scene128(tmp_path_factory) -> Path:
    return _synthetic(tmp_path_factory.mktemp("mvs") / "scene", 128)


@pytest.fixture(scope="module")
def run3(scene256, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("mvs3") / "out"
    assert _run(scene256, _names(scene256, 3), out) == 0
    return out


def test_three_views_meet_the_target(scene256, run3):
    acc = _accuracy(scene256, run3)
    assert acc["delta1"] >= 0.9, acc
    assert acc["completeness"] >= 0.6, acc
    assert acc["abs_rel"] <= 0.05, acc


def test_the_confidence_ranks_the_error(scene256, run3):
    """Error falls as the confidence rises: the top three deciles err far less than the bottom
    three, and the most confident decile least of all."""
    dec = [d["mean_error"] for d in _accuracy(scene256, run3)["deciles"]]
    assert len(dec) == 10
    assert np.mean(dec[-3:]) < 0.25 * np.mean(dec[:3]), dec
    assert dec[-1] <= min(dec[:5]), dec


@pytest.mark.parametrize("n, completeness", [(6, 0.7), (12, 0.8)])
def test_more_views_are_more_complete(scene128, tmp_path, n, completeness):
    out = tmp_path / "out"
    assert _run(scene128, _names(scene128, n), out) == 0
    acc = _accuracy(scene128, out)
    assert acc["delta1"] >= 0.93 and acc["completeness"] >= completeness, acc


def test_the_outputs_follow_the_contract(scene256, run3):
    pred = np.load(run3 / "predictions.npz")
    assert set(pred.files) == KEYS
    S, H, W = pred["world_points_conf"].shape
    assert S == 3 and (W, H) == (256, 192)
    assert pred["world_points"].shape == (S, H, W, 3) and pred["colors"].dtype == np.uint8
    assert pred["intrinsics_original"].dtype == np.float64 and pred["image_sizes_original"].dtype == np.int64
    has_point = np.all(np.isfinite(pred["world_points"]), axis=-1)
    conf = pred["world_points_conf"]
    kept = pred["depth"] > 0
    # a kept pixel has a point, a confidence in (0, 1] and a depth
    assert kept.any() and np.all(has_point[kept]) and np.all((conf[kept] > 0) & (conf[kept] <= 1))
    # an unexplained ray on the fill grid (by default every pixel) has a point with confidence 0
    # and no depth; every other pixel nothing
    filled = has_point & ~kept
    k = MvsConfig().fill_stride
    grid = np.zeros((H, W), bool)
    grid[k // 2::k, k // 2::k] = True
    assert filled.any() and np.all(conf[~kept] == 0) and not np.any(filled & ~grid)
    assert np.all(filled[:, grid] | kept[:, grid])  # the synthetic views see the scene everywhere
    status = json.loads((run3 / "status.json").read_text())
    assert status["filled_points"] == int(filled.sum())
    # each point lies on its own pixel's ray: a kept one at its depth, a filled one within the
    # view's stereo depths (5th-95th percentile)
    cfw, K = pred["cam_from_world"][0].astype(np.float64), pred["intrinsics"][0].astype(np.float64)
    z = {}
    for name, sel in (("kept", kept[0]), ("filled", filled[0])):
        i, j = np.nonzero(sel)
        pc = pred["world_points"][0][i, j].astype(np.float64) @ cfw[:, :3].T + cfw[:, 3]
        uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
        assert np.allclose(uv, np.stack([j + 0.5, i + 0.5], 1), atol=1e-2), name
        z[name] = pc[:, 2]
    assert np.allclose(z["kept"], pred["depth"][0][kept[0]], rtol=1e-4)
    lo, hi = np.percentile(pred["depth"][0][kept[0]], [5, 95])
    assert np.all((z["filled"] >= lo * (1 - 1e-4)) & (z["filled"] <= hi * (1 + 1e-4)))
    # the COLMAP model: the reference cameras unchanged, points with tracks; pycolmap opens it
    model = read_model(run3 / "sparse" / "0")
    ref = read_model(scene256 / "sparse" / "0")
    for cam in model.cameras:
        assert np.allclose(cam.cam_from_world, ref.camera(cam.name).cam_from_world, atol=1e-9)
    assert 1000 < len(model.points) <= 100_000
    import pycolmap

    rec = pycolmap.Reconstruction(str(run3 / "sparse" / "0"))
    assert rec.num_points3D() == len(model.points)
    assert min(len(p.track.elements) for p in rec.points3D.values()) >= 2  # seen by >= 2 views
    status = json.loads((run3 / "status.json").read_text())
    assert status["success_paper"] and status["working_size"] == [256, 192] and status["points"] == len(model.points)


@pytest.mark.parametrize("mode", ["gated", "uniform", "filtered"])
def test_the_bridge_reads_it_with_every_mode(run3, tmp_path, mode):
    from bridge.__main__ import main as bridge_main

    out = tmp_path / "bridge"
    assert bridge_main(["--pred", str(run3 / "predictions.npz"), "--out", str(out), "--mode", mode, "-q"]) == 0
    info = json.loads((out / "bridge.json").read_text())
    assert info["points_kept"] > 1000 and info["depth_prior"]["source"] == "dense"
    if mode != "uniform":
        assert info["alpha_out"]["max"] > info["alpha_out"]["min"]  # Eq. 2 spreads the opacity


# ----------------------------------------------------------------------------- stiff cases


def _posed_scene(root: Path, cams: list[Camera], images: list[np.ndarray] | None = None) -> Path:
    """A prepared scene of the synthetic world seen by ``cams`` (or of ``images`` instead)."""
    from camio.synthetic import build_scene, render_view

    world = build_scene(0) if images is None else None
    (root / "images").mkdir(parents=True)
    for k, cam in enumerate(cams):
        img = render_view(world, cam)[0] if images is None else images[k]
        write_image(root / "images" / cam.name, img)
    write_text_model(root / "sparse" / "0", cams)
    return root


def _cam(name: str, eye, target, width: int = 96) -> Camera:
    h = width * 3 // 4
    f = width / (2 * np.tan(np.deg2rad(30)))
    K = np.array([[f, 0, width / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(name, width, h, K, look_at(np.asarray(eye, float), np.asarray(target, float), up=(0, 0, 1)))


def test_two_views_give_points(tmp_path):
    cams = [_cam("a.png", (-0.6, -5, 2), (0, 0, 1)), _cam("b.png", (0.6, -5, 2), (0, 0, 1))]
    scene = _posed_scene(tmp_path / "s", cams)
    out = tmp_path / "out"
    assert _run(scene, ["a.png", "b.png"], out) == 0
    status = json.loads((out / "status.json").read_text())
    assert status["points"] > 500 and status["aligned_ok"] is False  # two views: no Sim(3) alignment


def test_views_that_do_not_overlap_are_one_line(tmp_path, capsys):
    cams = [_cam("a.png", (0, -5, 2), (0, 0, 1)), _cam("b.png", (0, -5.5, 2), (0, -12, 1))]  # back to back
    scene = _posed_scene(tmp_path / "s", cams)
    assert _run(scene, ["a.png", "b.png"], tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no pixel of any view is confirmed" in err[0]
    assert not (tmp_path / "out").exists()


def test_one_camera_centre_is_one_line(tmp_path, capsys):
    scene = _posed_scene(tmp_path / "s", [_cam("a.png", (0, -5, 2), (0, 0, 1)), _cam("b.png", (0, -5, 2), (0.5, 0, 1))])
    assert _run(scene, ["a.png", "b.png"], tmp_path / "out") == 2
    assert "share one centre" in capsys.readouterr().err


def test_textureless_views_are_one_line(tmp_path, capsys):
    cams = [_cam("a.png", (-0.6, -5, 2), (0, 0, 1)), _cam("b.png", (0.6, -5, 2), (0, 0, 1))]
    flat = [np.full((72, 96, 3), 0.5, np.float32)] * 2
    scene = _posed_scene(tmp_path / "s", cams, flat)
    assert _run(scene, ["a.png", "b.png"], tmp_path / "out") == 2
    assert "no pixel of any view is confirmed" in capsys.readouterr().err


def test_a_narrow_baseline_and_a_forward_move_stay_finite(tmp_path):
    """A baseline of 1/1000 of the depth, and a camera straight ahead of another (points
    between them lie behind it; no parallax at the epipole): finite results or one line."""
    for k, (eye_b, target_b) in enumerate([((0.005, -5, 2), (0.005, 0, 1)), ((0, -3.5, 1.7), (0, 0, 1))]):
        scene = _posed_scene(tmp_path / f"s{k}", [_cam("a.png", (0, -5, 2), (0, 0, 1)), _cam("b.png", eye_b, target_b)])
        out = tmp_path / f"out{k}"
        rc = _run(scene, ["a.png", "b.png"], out)
        assert rc in (0, 2)
        if rc == 0:
            pred = np.load(out / "predictions.npz")
            kept = pred["world_points_conf"] > 0  # stereo's points; the filled rays have confidence 0
            assert np.all(np.isfinite(pred["world_points_conf"])) and np.all(pred["depth"][kept] > 0)
            assert np.all(np.isfinite(pred["world_points"]).all(-1) | np.isnan(pred["world_points"]).all(-1))


def test_repeated_texture_is_not_trusted():
    """Stripes repeat every 6 pixels along the baseline: many depths match equally well, so the
    matching confidence stays low where a random texture's is high."""
    rng = np.random.default_rng(0)
    H, W, d = 48, 96, 10.0  # a fronto-parallel wall at depth d, a 1-unit baseline along x
    K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])
    ref_cfw = np.eye(4)[:3]
    src_cfw = np.concatenate([np.eye(3), [[-1.0], [0], [0]]], 1)  # the source 1 unit to the right
    shift = int(round(60.0 * 1.0 / d))  # disparity in pixels
    rhos = inverse_depth_planes(1 / 40, 1 / 4, 64)
    conf = {}
    for kind in ("stripes", "random"):
        if kind == "stripes":
            row = (np.arange(W + shift) % 6 < 3).astype(np.float32) * 0.6 + 0.2
            wide = np.tile(row, (H, 1))
        else:
            wide = rng.random((H, W + shift)).astype(np.float32)
        ref, src = wide[:, :W], wide[:, shift:]  # the wall seen from the left and from the right
        cfg = MvsConfig()
        res = plane_sweep(ref, K, ref_cfw, [(src, K, src_cfw)], rhos, window=5, min_std=cfg.min_std,
                          margin_scale=cfg.margin_scale, chunk=cfg.chunk)
        conf[kind] = float(np.median(res.conf[8:-8, 16:-16]))
        if kind == "random":
            good = np.abs(res.depth[8:-8, 16:-16] - d) / d < 0.05
            assert good.mean() > 0.9
    assert conf["stripes"] < 0.1 < 0.5 < conf["random"], conf


def test_large_photos_work_at_the_stated_resolution(scene128, tmp_path):
    """Photos of 4,000 pixels are swept at the working resolution (long side <= max_size),
    which status.json states; the points come back at the photos' own cameras."""
    src = read_model(scene128 / "sparse" / "0")
    names = _names(scene128, 3)
    big = []
    from camio.images import read_image
    from evaluation.initialisers.mvs.run import _resize

    for n in names:
        img = read_image(scene128 / "images" / n)[..., :3]
        big.append(_resize(img.astype(np.float32), (4000, 3000)))
    cams = [src.camera(n).scaled(4000, 3000) for n in names]
    scene = _posed_scene(tmp_path / "big", cams, big)
    out = tmp_path / "out"
    assert _run(scene, names, out, "--max-size", "160") == 0
    status = json.loads((out / "status.json").read_text())
    assert status["working_size"] == [160, 120] and status["original_size"] == [4000, 3000]
    model = read_model(out / "sparse" / "0")
    assert model.cameras[0].width == 4000 and len(model.points) > 100


def test_cameras_of_another_model_may_lack_a_photo(scene128, tmp_path, capsys):
    """``--images --cameras``: an estimated model (COLMAP's) need not register every photo; the
    photos without a camera are left out with a warning, the rest are swept."""
    src = read_model(scene128 / "sparse" / "0")
    names = _names(scene128, 6)
    model = tmp_path / "model"
    write_text_model(model, [src.camera(n) for n in names[:4]])  # two photos unregistered
    lst = tmp_path / "train.txt"
    lst.write_text("\n".join(names) + "\n")
    out = tmp_path / "out"
    assert main(["--images", str(scene128 / "images"), "--cameras", str(model), "--image-list", str(lst),
                 "--out", str(out)]) == 0
    pred = np.load(out / "predictions.npz")
    assert [str(n) for n in pred["image_names"]] == names[:4]
    assert "2 of 6 training images have no camera" in capsys.readouterr().err


def test_held_out_checks_score_exact_points_as_exact_and_shuffled_colours_as_wrong(scene128):
    """The real-scene measures of experiments/mvs_accuracy.py on the synthetic scene's own points
    seen from a held-out view: depth error 0 where a point is on the pixel, and the photo's own
    colours far closer than the same colours shuffled."""
    from camio.images import read_image_uint8
    from evaluation.initialisers.mvs.accuracy import heldout_depth_error, heldout_reprojection, visible_points

    ref = read_model(scene128 / "sparse" / "0")
    test = json.loads((scene128 / "split.json").read_text())["test"][0]
    cam = ref.camera(test)
    xy, idx = visible_points(ref.points, cam.K, cam.cam_from_world, cam.width, cam.height)
    assert 0 < len(idx) < len(ref.points)  # some are hidden or outside
    err = heldout_depth_error(ref.points, ref.points, xy, idx, cam.K, cam.cam_from_world, cam.width, cam.height)
    assert err["matched"] == 1.0 and err["median_rel_error"] < 1e-6 and err["share_within_5pct"] == 1.0
    seen = heldout_reprojection(ref.points[idx], ref.colors[idx], read_image_uint8(scene128 / "images" / test),
                                cam.K, cam.cam_from_world)
    assert seen["colour_error"] < 0.5 * seen["colour_error_shuffled"] and 0 < seen["coverage"] < 1


def test_the_fill_draws_from_the_stereo_depths_and_is_finite_on_nothing():
    """fill_unexplained in float64: a view with no kept pixel fills from the other views' points
    seen from it; nothing to draw from leaves every pixel NaN (no exception, no inf); the same
    seed gives the same points."""
    from evaluation.initialisers.mvs.fill import fill_unexplained

    cams = [_cam("a.png", [-0.3, 0, -4], [0, 0, 0], 32), _cam("b.png", [0.3, 0, -4], [0, 0, 0], 32)]
    H, W = cams[0].height, cams[0].width
    pts = np.full((2, H, W, 3), np.nan)
    Ks, cfws = [c.K for c in cams], [c.cam_from_world for c in cams]
    empty = fill_unexplained(pts, Ks, cfws, 2)
    assert np.isnan(empty).all()
    rng = np.random.default_rng(0)
    pts[0, :8] = np.c_[rng.uniform(-1, 1, (8 * W, 2)), rng.uniform(-0.5, 0.5, 8 * W)].reshape(8, W, 3)
    out = fill_unexplained(pts, Ks, cfws, 2)
    assert np.array_equal(out[0, :8], pts[0, :8])  # kept points untouched
    assert np.isfinite(out[1, 1::2, 1::2]).all() and np.isnan(out[1, 0::2]).all()
    z = out[1, 1::2, 1::2].reshape(-1, 3) @ cfws[1][:, :3].T + cfws[1][:, 3]
    ref = pts[0, :8].reshape(-1, 3) @ cfws[1][:, :3].T + cfws[1][:, 3]
    lo, hi = np.percentile(ref[:, 2], [5, 95])
    assert np.all((z[:, 2] >= lo - 1e-9) & (z[:, 2] <= hi + 1e-9))
    assert np.array_equal(out, fill_unexplained(pts, Ks, cfws, 2), equal_nan=True)
    with pytest.raises(ValueError, match="fill stride"):
        fill_unexplained(pts, Ks, cfws, 0)
