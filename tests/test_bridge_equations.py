"""Eq. 1 and Eq. 2 of the Bridge against hand-computed values, limits and properties.

Tolerances: float64 throughout; hand-computed values are exact binary fractions or agree
to 1e-15 relative (rtol 1e-12 leaves room for the float64 median/norm rounding).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from bridge.equations import global_coordinate_normalisation, uncertainty_gated_opacity


class TestGlobalCoordinateNormalisation:
    def test_hand_computed_odd(self):
        # norms 5, 2, 1 -> median 2 -> s = 0.5
        pts = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
        R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        ext = np.concatenate([R, np.array([[2.0], [-4.0], [6.0]])], axis=1)[None]
        p_n, ext_n, s = global_coordinate_normalisation(pts, ext)
        assert s == 0.5
        np.testing.assert_array_equal(p_n, [[1.5, 2.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.0, 0.0]])
        np.testing.assert_array_equal(ext_n[0, :, :3], R)  # rotations unchanged
        np.testing.assert_array_equal(ext_n[0, :, 3], [1.0, -2.0, 3.0])

    def test_hand_computed_even_and_4x4(self):
        # norms 1, 2, 3, 4 -> median 2.5 -> s = 0.4; 4x4 input gives [S,3,4] output
        pts = np.array([[1.0, 0, 0], [0, -2.0, 0], [0, 0, 3.0], [0, 4.0, 0]])
        ext = np.tile(np.eye(4), (2, 1, 1))
        ext[1, :3, 3] = [10.0, 0.0, -5.0]
        p_n, ext_n, s = global_coordinate_normalisation(pts, ext)
        assert s == pytest.approx(0.4, rel=1e-15)
        assert ext_n.shape == (2, 3, 4)
        np.testing.assert_allclose(ext_n[1, :, 3], [4.0, 0.0, -2.0], rtol=1e-15)
        np.testing.assert_allclose(np.median(np.linalg.norm(p_n, axis=1)), 1.0, rtol=1e-15)

    def test_grid_shape_and_single_camera(self):
        pts = np.random.default_rng(0).normal(size=(2, 3, 4, 3))
        p_n, ext_n, s = global_coordinate_normalisation(pts, np.eye(4)[:3])
        assert p_n.shape == pts.shape and ext_n.shape == (3, 4)
        np.testing.assert_allclose(p_n, pts * s, rtol=1e-15)

    def test_projections_preserved(self):
        """x_cam scales by s, so pixel coordinates x/z are unchanged."""
        rng = np.random.default_rng(1)
        pts = rng.normal(size=(50, 3)) * 7 + [0, 0, 30]
        ext = np.concatenate([np.eye(3), [[0.3], [-1.0], [2.0]]], axis=1)[None]
        p_n, ext_n, s = global_coordinate_normalisation(pts, ext)
        x0 = pts @ ext[0, :, :3].T + ext[0, :, 3]
        x1 = p_n @ ext_n[0, :, :3].T + ext_n[0, :, 3]
        np.testing.assert_allclose(x1, s * x0, rtol=1e-12)
        np.testing.assert_allclose(x1[:, :2] / x1[:, 2:], x0[:, :2] / x0[:, 2:], rtol=1e-12)

    def test_all_points_at_origin_is_a_clear_error(self):
        with pytest.raises(ValueError, match="median distance to the origin is 0"):
            global_coordinate_normalisation(np.zeros((10, 3)), np.eye(4)[None, :3])

    def test_majority_at_origin_is_a_clear_error(self):
        pts = np.zeros((5, 3))
        pts[:2] = 1.0  # 3 of 5 at the origin -> median 0
        with pytest.raises(ValueError, match="3 of 5 points"):
            global_coordinate_normalisation(pts, np.eye(4)[None, :3])

    def test_minority_at_origin_is_fine(self):
        pts = np.zeros((5, 3))
        pts[:3, 0] = [1.0, 2.0, 3.0]  # norms 0 0 1 2 3 -> median 1
        _, _, s = global_coordinate_normalisation(pts, np.eye(4)[None, :3])
        assert s == 1.0

    def test_zero_points_and_non_finite_are_errors(self):
        with pytest.raises(ValueError, match="at least one point"):
            global_coordinate_normalisation(np.zeros((0, 3)), np.eye(4)[None, :3])
        with pytest.raises(ValueError, match="finite points"):
            global_coordinate_normalisation(np.array([[np.nan, 0, 1.0]]), np.eye(4)[None, :3])
        bad = np.eye(4)[None, :3].copy()
        bad[0, 0, 3] = np.inf
        with pytest.raises(ValueError, match="pose is not finite"):
            global_coordinate_normalisation(np.ones((3, 3)), bad)

    def test_fly_away_outliers_do_not_move_the_median(self):
        rng = np.random.default_rng(2)
        inliers = rng.normal(size=(1000, 3))
        _, _, s0 = global_coordinate_normalisation(inliers, np.eye(4)[None, :3])
        pts = np.concatenate([inliers, np.full((10, 3), 1e6), [[-1e6, 1e6, 0.0]]])
        p_n, _, s1 = global_coordinate_normalisation(pts, np.eye(4)[None, :3])
        assert np.all(np.isfinite(p_n))
        # 11 outliers shift the median by at most 11 ranks of 1011: a few percent
        assert s1 == pytest.approx(s0, rel=0.05)

    def test_extreme_magnitudes(self):
        # coordinates near the float64 limit: hypot avoids overflow of x^2
        pts = np.array([[1e300, 1e300, 0.0]] * 3)
        p_n, _, s = global_coordinate_normalisation(pts, np.eye(4)[None, :3])
        np.testing.assert_allclose(np.linalg.norm(p_n, axis=1), 1.0, rtol=1e-12)
        with pytest.raises(ValueError, match="too small|overflows"):
            global_coordinate_normalisation(np.full((3, 3), 1e-310), np.eye(4)[None, :3])

    @settings(max_examples=60, deadline=None)
    @given(
        pts=arrays(np.float64, (20, 3), elements=st.floats(-1e3, 1e3, allow_nan=False)),
        t=arrays(np.float64, (3,), elements=st.floats(-1e3, 1e3, allow_nan=False)),
        k=st.floats(1e-3, 1e3),
    )
    def test_invariant_to_global_scaling(self, pts, t, k):
        """Normalising k*P (and k*t) gives the same scene; s scales by 1/k."""
        norms = np.linalg.norm(pts, axis=1)
        if not np.median(norms) > 1e-6:
            return  # degenerate input (Eq. 1 raises; tested above)
        ext = np.concatenate([np.eye(3), t[:, None]], axis=1)[None]
        ext_k = ext.copy()
        ext_k[0, :, 3] *= k
        p1, e1, s1 = global_coordinate_normalisation(pts, ext)
        p2, e2, s2 = global_coordinate_normalisation(k * pts, ext_k)
        assert s2 == pytest.approx(s1 / k, rel=1e-12)
        np.testing.assert_allclose(p2, p1, rtol=1e-12, atol=1e-12 * np.abs(p1).max())
        np.testing.assert_allclose(e2, e1, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(e1).max()))


class TestUncertaintyGatedOpacity:
    def test_hand_computed(self):
        # c_min 2, c_max 10: ratios 0, 1/4, 1/2, 1 -> 0.05 + 0.45 * ratio
        alpha = uncertainty_gated_opacity(np.array([2.0, 4.0, 6.0, 10.0]))
        np.testing.assert_allclose(alpha, [0.05, 0.1625, 0.275, 0.5], rtol=1e-15)

    def test_hand_computed_custom_range_and_scene_extremes(self):
        # range from the whole scene (c_min 0, c_max 8), evaluated on a subset
        alpha = uncertainty_gated_opacity(np.array([2.0, 6.0]), alpha_min=0.1, alpha_max=0.9, c_min=0.0, c_max=8.0)
        np.testing.assert_allclose(alpha, [0.3, 0.7], rtol=1e-15)

    def test_equal_confidences_limit_is_alpha_max(self):
        alpha = uncertainty_gated_opacity(np.full(7, 3.25))
        np.testing.assert_array_equal(alpha, np.full(7, 0.5))
        one = uncertainty_gated_opacity(np.array([42.0]), 0.05, 0.4)
        np.testing.assert_array_equal(one, [0.4])

    def test_confidence_span_1e_minus6_to_1e6(self):
        c = np.array([1e-6, 1e-3, 1.0, 1e3, 1e6])
        alpha = uncertainty_gated_opacity(c)
        ref = 0.05 + 0.45 * (c - 1e-6) / (1e6 - 1e-6)
        np.testing.assert_allclose(alpha, ref, rtol=1e-12)
        assert alpha[0] == 0.05 and alpha[-1] == 0.5

    def test_no_overflow_at_float64_limits(self):
        c = np.array([-1.7e308, 0.0, 1.7e308])  # c_max - c_min overflows naively
        alpha = uncertainty_gated_opacity(c)
        np.testing.assert_allclose(alpha, [0.05, 0.275, 0.5], rtol=1e-12)

    def test_values_outside_the_range_are_clipped(self):
        alpha = uncertainty_gated_opacity(np.array([-5.0, 50.0]), c_min=0.0, c_max=10.0)
        np.testing.assert_array_equal(alpha, [0.05, 0.5])

    def test_empty_and_errors(self):
        assert uncertainty_gated_opacity(np.zeros(0)).shape == (0,)
        with pytest.raises(ValueError, match="finite confidences"):
            uncertainty_gated_opacity(np.array([1.0, np.nan]))
        with pytest.raises(ValueError, match="alpha_min <= alpha_max"):
            uncertainty_gated_opacity(np.ones(3), alpha_min=0.6, alpha_max=0.5)
        with pytest.raises(ValueError, match="alpha_min <= alpha_max < 1"):
            uncertainty_gated_opacity(np.ones(3), alpha_min=0.0, alpha_max=0.5)
        with pytest.raises(ValueError, match="c_min <= c_max"):
            uncertainty_gated_opacity(np.ones(3), c_min=2.0, c_max=1.0)

    @settings(max_examples=200, deadline=None)
    @given(
        c=arrays(np.float64, st.integers(1, 40), elements=st.floats(-1e12, 1e12, allow_nan=False)),
        a=st.floats(1e-4, 0.99),
        b=st.floats(1e-4, 0.99),
    )
    def test_opacity_stays_in_range(self, c, a, b):
        lo, hi = min(a, b), max(a, b)
        alpha = uncertainty_gated_opacity(c, lo, hi)
        assert np.all(np.isfinite(alpha))
        assert np.all(alpha >= lo) and np.all(alpha <= hi)
        # monotone in confidence
        order = np.argsort(c, kind="stable")
        assert np.all(np.diff(alpha[order]) >= -1e-15)

    @settings(max_examples=60, deadline=None)
    @given(c=arrays(np.float64, st.integers(2, 30), elements=st.floats(1.0, 1e3)), k=st.floats(1e-3, 1e3))
    def test_invariant_to_confidence_scaling(self, c, k):
        np.testing.assert_allclose(uncertainty_gated_opacity(k * c), uncertainty_gated_opacity(c),
                                   rtol=1e-9, atol=1e-12)
