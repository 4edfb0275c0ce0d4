"""The learned decoder's fusion of its network's depth with its classical stage's (``decode.fusion``): the
inverse-variance weights of two analytic cases, the fused σ against the spread of correlated draws (the
bound it claims for every correlation) and the invalid pixels of either read. The runtime's wiring through
``bmi infer`` is tested in test_learned.py, with a refinement whose reads are known."""

from __future__ import annotations

import numpy as np
import pytest

from bmi_sdk.decode.fusion import fuse_log_depth


def test_two_reads_of_equal_relative_sigma_fuse_to_their_geometric_mean():
    depth, sigma, weight = fuse_log_depth(np.array([2.0]), np.array([0.2]), np.array([8.0]), np.array([0.8]))
    np.testing.assert_allclose(depth, [4.0])
    np.testing.assert_allclose(sigma, [0.4])  # the same 10 % of the fused depth
    np.testing.assert_allclose(weight, [0.5])


def test_the_weights_are_the_inverse_relative_variances():
    """r_a = 1 %, r_b = 3 %: read a carries 9 / 10 of the log depth."""
    depth, sigma, weight = fuse_log_depth(np.array([3.0]), np.array([0.03]), np.array([3.3]), np.array([0.099]))
    np.testing.assert_allclose(weight, [0.9])
    np.testing.assert_allclose(depth, [np.exp(0.9 * np.log(3.0) + 0.1 * np.log(3.3))])
    np.testing.assert_allclose(sigma / depth, [0.9 * 0.01 + 0.1 * 0.03])


@pytest.mark.parametrize("rho", [0.0, 0.6, 1.0])
def test_the_fused_sigma_bounds_the_fused_error_for_every_correlation(rho):
    """Log-depth errors of 5 % and 15 % drawn with correlation ρ: the fused depth's error spread never
    exceeds its reported σ, meets it at ρ = 1, and for independent reads is below the better read's."""
    rng = np.random.default_rng(11)
    n, rel_a, rel_b, true_m = 200_000, 0.05, 0.15, 4.0
    e_a = rng.standard_normal(n)
    e_b = rho * e_a + np.sqrt(1.0 - rho ** 2) * rng.standard_normal(n)
    depth_a, depth_b = true_m * np.exp(rel_a * e_a), true_m * np.exp(rel_b * e_b)
    depth, sigma, _ = fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b)
    spread, reported = np.std(np.log(depth / true_m)), np.median(sigma / depth)
    assert spread <= reported * 1.01
    if rho == 1.0:
        assert spread == pytest.approx(reported, rel=0.01)
    if rho == 0.0:
        assert spread < rel_a * 0.96  # √(1/(1/0.05² + 1/0.15²)) = 0.0474
    assert np.median(np.abs(np.log(depth / true_m))) < np.median(np.abs(np.log(depth_b / true_m)))


def test_a_pixel_only_one_read_holds_takes_that_read_and_one_neither_holds_is_nan():
    depth_a = np.array([2.0, np.nan, 2.0, 2.0, np.nan], np.float32)
    sigma_a = np.array([0.2, 0.2, 0.0, np.inf, np.nan], np.float32)
    depth_b = np.array([3.0, 3.0, 3.0, 3.0, np.nan], np.float32)
    sigma_b = np.array([np.nan, 0.3, 0.3, 0.3, 0.3], np.float32)
    depth, sigma, weight = fuse_log_depth(depth_a, sigma_a, depth_b, sigma_b)
    assert depth.dtype == sigma.dtype == np.float32
    np.testing.assert_allclose(depth[:4], [2.0, 3.0, 3.0, 3.0])
    np.testing.assert_allclose(sigma[:4], [0.2, 0.3, 0.3, 0.3])
    np.testing.assert_allclose(weight[:4], [1.0, 0.0, 0.0, 0.0])
    assert np.isnan(depth[4]) and np.isnan(sigma[4]) and np.isnan(weight[4])


def test_reads_of_different_shapes_are_refused():
    with pytest.raises(ValueError, match="one shape"):
        fuse_log_depth(np.ones(3), np.ones(3), np.ones(4), np.ones(4))
