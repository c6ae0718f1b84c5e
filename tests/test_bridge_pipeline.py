"""The Bridge stage in memory and on disk: stiff cases, modes, PLY fields, camera frame.

References are recomputed independently in float64 (hand formulas, brute-force 3-NN).
Tolerances: geometry stored as float32 in the PLY -> rtol 1e-6; projections of float32
points -> 1e-3 px; logits of float32 -> atol 1e-5.
"""

from pathlib import Path

import numpy as np
import pytest

from bridge.core import BridgeConfig, build_seed, write_outputs
from bridge.inputs import BridgeInput, load_predictions
from bridge.selection import MIN_DIST2, SINGLE_POINT_SCALE
from bridge.synthetic import synthetic_predictions, write_synthetic_predictions
from camio.cameras import Camera, look_at, project_points

C0 = 0.28209479177387814  # degree-0 SH constant, written out independently of camio


def make_input(points, conf=None, colors=None, n_cams=2) -> BridgeInput:
    points = np.asarray(points, np.float64).reshape(-1, 3)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cams = [Camera(f"c{i}.png", 64, 48, K, look_at([3.0 * i - 1.5, 0.0, -4.0], [0.0, 0.0, 0.0])[:3])
            for i in range(n_cams)]
    if colors is None:
        colors = np.full((len(points), 3), 128, np.uint8)
    return BridgeInput("vggt" if conf is not None else "colmap", Path("memory"), points,
                       None if conf is None else np.asarray(conf, np.float64), colors, cams)


def brute_knn_d2(p: np.ndarray, k: int = 3) -> np.ndarray:
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.sort(d2, axis=1)[:, :min(k, len(p) - 1)].mean(axis=1)


def logit(a):
    a = np.asarray(a, np.float64)
    return np.log(a / (1 - a))


def check_counts(report):
    assert report["points_kept"] + sum(report["dropped"].values()) == report["points_in"]


# ---- stiff and extreme cases -----------------------------------------------------------

def test_all_confidences_equal_gives_alpha_max():
    rng = np.random.default_rng(0)
    res = build_seed(make_input(rng.normal(size=(50, 3)), np.full(50, 4.2)), BridgeConfig(stride=1))
    np.testing.assert_allclose(res.cloud.opacity, 0.5, rtol=1e-6)
    assert res.report["c_min"] == res.report["c_max"] == pytest.approx(4.2)


def test_all_points_at_origin_is_a_clear_error():
    with pytest.raises(ValueError, match="median distance to the origin is 0"):
        build_seed(make_input(np.zeros((20, 3)), np.linspace(1, 2, 20)), BridgeConfig(stride=1))


def test_fly_away_outliers():
    rng = np.random.default_rng(1)
    inl = rng.normal(size=(400, 3))
    pts = np.concatenate([inl, [[1e6, 1e6, 1e6], [-1e6, 2e6, 0.0], [0.0, 0.0, 1e6]]])
    conf = rng.uniform(1, 5, size=len(pts))
    res = build_seed(make_input(pts, conf), BridgeConfig(stride=1))
    s_in = 1.0 / np.median(np.linalg.norm(inl, axis=1))
    assert res.report["s"] == pytest.approx(s_in, rel=0.02)
    for arr in (res.cloud.means, res.cloud.log_scales, res.cloud.opacity_logit, res.cloud.sh_dc):
        assert np.all(np.isfinite(arr))
    assert np.max(np.abs(res.cloud.means)) == pytest.approx(2e6 * res.report["s"], rel=1e-6)
    # with outlier removal they are dropped and counted
    res2 = build_seed(make_input(pts, conf), BridgeConfig(stride=1, outlier_removal=True))
    assert np.max(np.abs(res2.cloud.means)) < 10
    assert res2.report["dropped"]["outliers"] >= 3
    check_counts(res2.report)


def test_nan_and_inf_are_dropped_and_counted():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(100, 3))
    conf = rng.uniform(1, 5, size=100)
    pts[3] = [np.nan, 0, 0]
    pts[7, 2] = np.inf
    pts[9] = -np.inf
    conf[11] = np.nan
    conf[12] = np.inf
    conf[9] = np.nan  # both bad: counted once, as a bad point
    res = build_seed(make_input(pts, conf), BridgeConfig(stride=1))
    d = res.report["dropped"]
    assert d["nonfinite_point"] == 3 and d["nonfinite_conf"] == 2
    assert res.report["points_valid"] == 95 == res.report["points_kept"]
    check_counts(res.report)
    good = np.setdiff1d(np.arange(100), [3, 7, 9, 11, 12])
    assert res.report["s"] == pytest.approx(1 / np.median(np.linalg.norm(pts[good], axis=1)), rel=1e-12)
    assert res.report["c_max"] == pytest.approx(conf[good].max())
    assert np.all(np.isfinite(res.cloud.means)) and np.all(np.isfinite(res.cloud.opacity_logit))


def test_all_non_finite_is_a_clear_error():
    with pytest.raises(ValueError, match="all 4 points are NaN/Inf"):
        build_seed(make_input(np.full((4, 3), np.nan), np.ones(4)), BridgeConfig(stride=1))


def test_single_point():
    res = build_seed(make_input([[0.0, 3.0, 4.0]], [7.0]), BridgeConfig(stride=1))
    assert len(res.cloud) == 1
    np.testing.assert_allclose(res.points, [[0.0, 0.6, 0.8]], rtol=1e-12)  # s = 1/5
    np.testing.assert_allclose(np.exp(res.cloud.log_scales), SINGLE_POINT_SCALE, rtol=1e-6)
    np.testing.assert_allclose(res.cloud.opacity, 0.5, rtol=1e-6)  # c_max = c_min


def test_zero_points_is_a_clear_error():
    with pytest.raises(ValueError, match="zero points"):
        build_seed(make_input(np.zeros((0, 3)), np.zeros(0)), BridgeConfig())


def test_stride_that_leaves_nothing_is_a_clear_error():
    pts = np.full((30, 3), np.nan)
    pts[5] = [1.0, 2.0, 3.0]  # the only valid row is off the stride
    with pytest.raises(ValueError, match="no point left after selection"):
        build_seed(make_input(pts, np.ones(30)), BridgeConfig(stride=20))


def test_duplicate_points_get_the_scale_floor():
    pts = np.array([[1.0, 1.0, 1.0]] * 6 + [[2.0, 0.0, 1.0], [0.0, 2.0, 1.0]])
    res = build_seed(make_input(pts, np.arange(8.0) + 1), BridgeConfig(stride=1))
    scales = np.exp(res.cloud.log_scales.astype(np.float64))
    np.testing.assert_allclose(scales[:6], np.sqrt(MIN_DIST2), rtol=1e-6)
    assert np.all(np.isfinite(res.cloud.log_scales))
    assert res.report["scale"]["n_floored"] == 6


def test_confidence_span_1e_minus6_to_1e6():
    rng = np.random.default_rng(3)
    conf = np.logspace(-6, 6, 200)
    rng.shuffle(conf)
    res = build_seed(make_input(rng.normal(size=(200, 3)), conf), BridgeConfig(stride=1))
    a = res.cloud.opacity
    assert np.all(np.isfinite(a))
    assert a.min() >= 0.05 - 1e-6 and a.max() <= 0.5 + 1e-6
    np.testing.assert_allclose(a, 0.05 + 0.45 * (conf - 1e-6) / (1e6 - 1e-6), atol=1e-6)
    assert res.report["c_min"] == pytest.approx(1e-6) and res.report["c_max"] == pytest.approx(1e6)


# ---- modes and selection -----------------------------------------------------------------

def test_modes_uniform_gated_filtered():
    rng = np.random.default_rng(4)
    pts, conf = rng.normal(size=(100, 3)), np.arange(100.0) + 1.0
    uni = build_seed(make_input(pts, conf), BridgeConfig(mode="uniform", stride=1))
    np.testing.assert_allclose(uni.cloud.opacity, 0.1, rtol=1e-6)
    gated = build_seed(make_input(pts, conf), BridgeConfig(stride=1))
    np.testing.assert_allclose(gated.cloud.opacity, 0.05 + 0.45 * (conf - 1) / 99, rtol=1e-6)
    filt = build_seed(make_input(pts, conf), BridgeConfig(mode="filtered", stride=1))
    assert filt.report["percentile"] == 40.0
    assert filt.report["dropped"]["percentile"] == 40 and filt.report["points_kept"] == 60
    # Eq. 2 keeps the scene's c_min/c_max (all valid points), so the kept range starts above a_min
    kept_conf = conf[conf >= filt.report["percentile_threshold"]]
    np.testing.assert_allclose(np.sort(filt.cloud.opacity), 0.05 + 0.45 * (kept_conf - 1) / 99, rtol=1e-6)
    check_counts(filt.report)


def test_stride_and_max_points_keep_most_confident():
    rng = np.random.default_rng(5)
    pts, conf = rng.normal(size=(1000, 3)), rng.uniform(1, 10, 1000)
    res = build_seed(make_input(pts, conf), BridgeConfig(stride=20, max_points=10))
    assert res.report["dropped"]["stride"] == 950 and res.report["dropped"]["max_points"] == 40
    on_stride = conf[::20]
    np.testing.assert_allclose(np.sort(res.cloud.opacity),
                               0.05 + 0.45 * (np.sort(on_stride)[-10:] - conf.min()) / (conf.max() - conf.min()),
                               rtol=1e-6)
    # Eq. 1 over all valid points, not only the seeded ones
    assert res.report["s"] == pytest.approx(1 / np.median(np.linalg.norm(pts, axis=1)), rel=1e-12)


def test_voxel_downsampling_counts():
    rng = np.random.default_rng(6)
    res = build_seed(make_input(rng.normal(size=(2000, 3)), rng.uniform(1, 2, 2000)),
                     BridgeConfig(stride=1, voxel_size=0.5))
    assert 0 < res.report["dropped"]["voxel"] < 2000
    keys = np.floor((res.points - res.points.min(0)) / 0.5)
    assert len(np.unique(keys, axis=0)) == len(res.points)  # one point per voxel
    check_counts(res.report)


def test_colmap_input_falls_back_to_uniform_and_refuses_filtering():
    rng = np.random.default_rng(7)
    inp = make_input(rng.normal(size=(30, 3)))
    res = build_seed(inp, BridgeConfig(stride=1))
    assert res.report["mode"] == "uniform" and res.report["mode_requested"] == "gated"
    np.testing.assert_allclose(res.cloud.opacity, 0.1, rtol=1e-6)
    with pytest.raises(ValueError, match="no confidence"):
        build_seed(inp, BridgeConfig(mode="filtered", stride=1))


@pytest.mark.parametrize("k", [1e-3, 7.5, 1e4])
def test_seed_invariant_to_global_scaling(k):
    """Scaling the input world by k changes s by 1/k and nothing else."""
    d = synthetic_predictions(n_views=2, height=8, width=10)
    d_k = synthetic_predictions(n_views=2, height=8, width=10, scale=k)
    cfg = BridgeConfig(stride=3)

    def run(dd):
        inp = BridgeInput("vggt", Path("m"), dd["world_points"].reshape(-1, 3).astype(np.float64),
                          dd["world_points_conf"].reshape(-1), dd["colors"].reshape(-1, 3),
                          [Camera(str(n), 40, 32, K, e) for n, K, e in
                           zip(dd["image_names"], dd["intrinsics_original"], dd["cam_from_world"].astype(np.float64))])
        return build_seed(inp, cfg)

    a, b = run(d), run(d_k)
    assert b.report["s"] == pytest.approx(a.report["s"] / k, rel=1e-5)
    np.testing.assert_allclose(b.points, a.points, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.cloud.log_scales, a.cloud.log_scales, atol=1e-4)
    np.testing.assert_allclose(b.cloud.opacity_logit, a.cloud.opacity_logit, atol=1e-6)
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_allclose(cb.cam_from_world, ca.cam_from_world, rtol=1e-5, atol=1e-6)


# ---- on disk: PLY fields with an independent reader, frame of sparse/0 --------------------

@pytest.fixture(scope="module")
def seeded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bridge")
    npz = write_synthetic_predictions(tmp / "predictions.npz", n_views=3, height=12, width=16, scale=3.7)
    res = build_seed(load_predictions(npz), BridgeConfig(stride=2))
    write_outputs(res, tmp / "out", write_points3d=True)
    with np.load(npz) as z:
        raw = {k: z[k] for k in z.files}
    return tmp / "out", res, raw


def test_ply_fields_with_plyfile(seeded):
    from plyfile import PlyData

    out, res, raw = seeded
    v = PlyData.read(str(out / "seed.ply"))["vertex"]
    names = [p.name for p in v.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(45)] + ["opacity"]
                     + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    assert all(p.val_dtype in ("f4", "<f4", "float32") or np.dtype(p.val_dtype) == np.float32 for p in v.properties)

    # independent reference from the raw npz
    rows = np.arange(raw["world_points"][..., 0].size)[::2]
    pts = raw["world_points"].reshape(-1, 3).astype(np.float64)
    conf = raw["world_points_conf"].reshape(-1).astype(np.float64)
    s = 1.0 / np.median(np.linalg.norm(pts, axis=1))
    p_ref = pts[rows] * s
    rgb = raw["colors"].reshape(-1, 3)[rows] / 255.0
    alpha = 0.05 + 0.45 * (conf[rows] - conf.min()) / (conf.max() - conf.min())
    scale = np.sqrt(np.maximum(brute_knn_d2(p_ref), 1e-7))

    assert len(v) == len(rows)
    xyz = np.stack([v["x"], v["y"], v["z"]], 1)
    np.testing.assert_allclose(xyz, p_ref, rtol=1e-5, atol=1e-6)
    for k in ("nx", "ny", "nz"):
        assert np.all(v[k] == 0)
    np.testing.assert_allclose(np.stack([v[f"f_dc_{i}"] for i in range(3)], 1), (rgb - 0.5) / C0, atol=1e-5)
    for i in range(45):
        assert np.all(v[f"f_rest_{i}"] == 0)
    np.testing.assert_allclose(v["opacity"], logit(alpha), atol=1e-5)
    for i in range(3):
        np.testing.assert_allclose(v[f"scale_{i}"], np.log(scale), atol=1e-4)
    np.testing.assert_array_equal(np.stack([v[f"rot_{i}"] for i in range(4)], 1),
                                  np.tile([1.0, 0, 0, 0], (len(rows), 1)))


def test_ply_round_trip_with_camio(seeded):
    from camio.ply import read_gaussian_ply

    out, res, _ = seeded
    back = read_gaussian_ply(out / "seed.ply")
    for f in ("means", "sh_dc", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(back, f), getattr(res.cloud, f))
    np.testing.assert_array_equal(back.sh_rest, 0)
    assert back.sh_degree == 3


def test_sparse_model_is_in_the_seed_frame_at_original_resolution(seeded):
    """Every seed point projects, with the normalised original-resolution camera of its view,
    to the original-resolution centre of the pixel that predicted it."""
    from camio.colmap import read_model

    out, res, raw = seeded
    model = read_model(out / "sparse" / "0")
    S, H, W, _ = raw["world_points"].shape
    factor = raw["image_sizes_original"][0, 0] / W
    s = res.report["s"]
    pts = raw["world_points"].astype(np.float64) * s
    for v, name in enumerate(raw["image_names"]):
        cam = model.camera(str(name))
        assert (cam.width, cam.height) == tuple(raw["image_sizes_original"][v])
        np.testing.assert_allclose(cam.K, raw["intrinsics_original"][v], rtol=1e-7)
        np.testing.assert_allclose(cam.t, raw["cam_from_world"][v, :, 3] * s, rtol=1e-6, atol=1e-7)
        uv, z = project_points(pts[v].reshape(-1, 3), cam.K, cam.cam_from_world)
        jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        np.testing.assert_allclose(uv, np.stack([jj, ii], -1).reshape(-1, 2) * factor, atol=2e-3)
    assert len(model.points) == len(res.cloud)
    np.testing.assert_allclose(model.points, res.points, rtol=1e-12)
