"""Point selection and 3-NN scales of the Bridge (bridge/selection.py).

References are brute force in float64 (all pairwise distances); tolerance rtol 1e-12.
"""

import numpy as np
import pytest

from bridge.selection import (MIN_DIST2, SINGLE_POINT_SCALE, cap_points, knn_scales, percentile_mask,
                              statistical_outlier_mask, stride_mask, voxel_downsample)


def brute_knn_d2(p: np.ndarray, k: int = 3) -> np.ndarray:
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    kk = min(k, len(p) - 1)
    return np.sort(d2, axis=1)[:, :kk].mean(axis=1)


def test_stride_mask_every_20th_flattened_pixel():
    m = stride_mask(45, 20)
    assert np.flatnonzero(m).tolist() == [0, 20, 40]
    assert stride_mask(5, 1).all()
    with pytest.raises(ValueError):
        stride_mask(5, 0)


def test_percentile_mask_drops_lowest_40_percent():
    c = np.arange(10, dtype=float)  # 40th percentile (linear) = 3.6
    keep, thr = percentile_mask(c, 40)
    assert thr == pytest.approx(3.6)
    assert np.flatnonzero(keep).tolist() == [4, 5, 6, 7, 8, 9]
    keep_eq, _ = percentile_mask(np.full(8, 2.0), 40)  # ties: keep all
    assert keep_eq.all()
    with pytest.raises(ValueError):
        percentile_mask(c, 100)


def test_voxel_downsample_groups_match_open3d_and_keep_most_confident():
    import open3d as o3d

    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, size=(500, 3))
    conf = rng.uniform(1, 10, size=500)
    size = 0.37
    kept = voxel_downsample(p, size, conf)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    _, _, members = pcd.voxel_down_sample_and_trace(size, p.min(axis=0), p.max(axis=0), False)
    groups = [np.asarray(m) for m in members]
    assert len(kept) == len(groups)
    expect = sorted(int(g[np.argmax(conf[g])]) for g in groups)
    assert kept.tolist() == expect


def test_voxel_downsample_without_conf_keeps_first_row():
    p = np.array([[0.0, 0, 0], [0.01, 0, 0], [5.0, 0, 0]])
    assert voxel_downsample(p, 1.0).tolist() == [0, 2]
    assert voxel_downsample(np.zeros((0, 3)), 1.0).tolist() == []
    with pytest.raises(ValueError):
        voxel_downsample(p, 0.0)


def test_statistical_outlier_removal_drops_fly_away_points():
    rng = np.random.default_rng(1)
    p = np.concatenate([rng.normal(size=(300, 3)), [[1e6, 1e6, 1e6], [-1e6, 0, 0]]])
    keep = statistical_outlier_mask(p, 20, 2.0)
    assert not keep[-1] and not keep[-2]
    assert keep[:300].mean() > 0.9
    assert statistical_outlier_mask(p[:5], 20, 2.0).all()  # too few points: keep all


def test_cap_points_keeps_most_confident_or_random_subset():
    conf = np.array([1.0, 9.0, 3.0, 9.0, 5.0])
    assert cap_points(5, 3, conf).tolist() == [1, 3, 4]
    assert cap_points(5, 10, conf).tolist() == [0, 1, 2, 3, 4]
    r = cap_points(100, 10, None, seed=3)
    assert len(r) == 10 and len(set(r.tolist())) == 10
    assert r.tolist() == cap_points(100, 10, None, seed=3).tolist()


class TestKnnScales:
    def test_against_brute_force(self):
        p = np.random.default_rng(2).normal(size=(200, 3))
        s, n_floor = knn_scales(p)
        np.testing.assert_allclose(s, np.sqrt(brute_knn_d2(p)), rtol=1e-12)
        assert n_floor == 0

    def test_hand_computed_line(self):
        # points at 0, 1, 3, 6 on x; every point has the other three as its 3 NN:
        # 0: (1 + 9 + 36) / 3; 1: (1 + 4 + 25) / 3; 3: (9 + 4 + 9) / 3; 6: (36 + 25 + 9) / 3
        p = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [6.0, 0, 0]])
        s, _ = knn_scales(p)
        np.testing.assert_allclose(s ** 2, [46 / 3, 30 / 3, 22 / 3, 70 / 3], rtol=1e-12)

    def test_duplicates_get_the_floor(self):
        p = np.array([[1.0, 2, 3]] * 5 + [[4.0, 5, 6]])
        s, n_floor = knn_scales(p)
        assert np.all(s[:5] == np.sqrt(MIN_DIST2))
        assert n_floor == 5 and np.all(np.isfinite(np.log(s)))

    def test_one_two_three_points(self):
        s1, _ = knn_scales(np.array([[1.0, 2.0, 3.0]]))
        assert s1.tolist() == [SINGLE_POINT_SCALE]
        s2, _ = knn_scales(np.array([[0.0, 0, 0], [0, 0, 2.0]]))  # one neighbour each
        np.testing.assert_allclose(s2, [2.0, 2.0])
        s3, _ = knn_scales(np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]]))  # two each
        np.testing.assert_allclose(s3 ** 2, [5.0, 2.5, 6.5])
        assert knn_scales(np.zeros((0, 3)))[0].shape == (0,)
