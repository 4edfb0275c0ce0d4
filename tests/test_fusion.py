"""The learned decoder's fusion of its network's depth with its classical stage's (``decode.fusion``): the
inverse-variance weights of two analytic cases, the fused σ against the spread of correlated draws (the
bound it claims for every correlation), the invalid pixels of either read, the logistic weight's terms
computed by hand, the weights' validation, and the fit (``nn.fusion_fit``) on reads with heavy-tailed
errors, judged on draws it never saw. The runtime's wiring through ``bmi infer`` and ``bmi fit-fusion`` is
tested in test_learned.py, with refinements whose reads are known."""

from __future__ import annotations

import numpy as np
import pytest

from bmi_sdk.decode.fusion import INVERSE_VARIANCE, FusionWeights, fuse_log_depth


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


def test_the_variation_term_enters_the_logit_and_weights_that_read_it_need_it():
    """c_v log(v_a + v₀) is added to the four terms, by hand; a flat neighbourhood (v = 0) hands the pixel to read
    a, a varying one to read b; weights with c_v need the variation, weights without ignore it."""
    weights = FusionWeights(-7.0, -1.5, 1.0, -2.0, -1.2)
    assert weights.reads_variation and not INVERSE_VARIANCE.reads_variation
    depth_a, depth_b = np.full(3, 3.0), np.full(3, 3.6)
    rel_a, rel_b, variation = 0.2, 0.1, np.array([0.0, 0.05, np.nan])
    _, _, weight = fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, weights, None, variation)
    logit = (-7.0 - 1.5 * np.log(rel_a) + np.log(rel_b) - 2.0 * np.log(np.log(1.2) + 0.01)
             - 1.2 * np.log(np.nan_to_num(variation) + 0.01))
    np.testing.assert_allclose(weight, 1.0 / (1.0 + np.exp(-logit)))
    assert weight[0] > 0.5 > weight[1] and weight[2] == weight[0]  # no variation read (NaN): as flat
    with pytest.raises(ValueError, match="variation; none was given"):
        fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, weights)
    plain = FusionWeights(-7.0, -1.5, 1.0, -2.0)
    np.testing.assert_array_equal(fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, plain)[2],
                                  fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, plain, None,
                                                 variation)[2])


def test_the_local_log_depth_variation_is_the_std_of_log_depth_over_3x3_windows():
    """On a window grid of 1/d: 0 on a plane; across a step from 2 m to 5 m, the windows whose 3 × 3 holds k of
    9 on the far side read |log 2.5| √(p(1 − p)), p = k/9; windows without a read are left out, not zeros."""
    from bmi_sdk.decode.classical import local_log_depth_variation

    plane = np.full((5, 6), 1 / 3.0)
    np.testing.assert_allclose(local_log_depth_variation(plane), 0.0, atol=1e-12)
    step = np.full((5, 6), 1 / 2.0)
    step[:, 3:] = 1 / 5.0
    v = local_log_depth_variation(step)
    p = 3 / 9  # an interior window next to the step sees one column of three on the far side
    np.testing.assert_allclose(v[2, 2], np.log(2.5) * np.sqrt(p * (1 - p)))
    np.testing.assert_allclose(v[2, 0], 0.0, atol=1e-12)
    holes = step.copy()
    holes[1, 1] = np.nan
    assert np.isnan(local_log_depth_variation(holes)[1, 1])
    np.testing.assert_allclose(local_log_depth_variation(holes)[2, 1], 0.0, atol=1e-12)


def test_a_fit_reads_the_variation_where_the_sigmas_cannot_tell_the_reads_apart():
    """Read a is 1 % off where its neighbourhood is flat and 40 % off where it varies, with one σ throughout;
    read b is 10 % off everywhere. Fitted with the variation, the weight trusts a on the flat part only and beats
    the four-term fit on fresh draws."""
    from dataclasses import replace

    from bmi_sdk.nn.fusion_fit import ReadSet, fit_fusion_weights, mean_abs_log_error

    def reads(seed, n=40_000):
        rng = np.random.default_rng(seed)
        truth = np.exp(rng.uniform(0.0, 2.0, n))
        flat = rng.random(n) < 0.5
        variation = np.where(flat, rng.uniform(0.0, 0.01, n), rng.uniform(0.1, 0.5, n))
        depth_a = truth * np.exp(np.where(flat, 0.01, 0.40) * rng.standard_normal(n))
        depth_b = truth * np.exp(0.10 * rng.standard_normal(n))
        return ReadSet(f"seed {seed}", depth_a, 0.1 * depth_a, depth_b, 0.1 * depth_b, truth, 0.005, variation)

    train, fresh = reads(1), reads(2)
    with_v = fit_fusion_weights([train], pixels_per_set=20_000)
    without_v = fit_fusion_weights([replace(train, classical_variation=None)], pixels_per_set=20_000)
    assert with_v.variation_a < -0.5 and without_v.variation_a == 0.0
    assert mean_abs_log_error(fresh, with_v) < 0.9 * mean_abs_log_error(replace(fresh, classical_variation=None),
                                                                         without_v)


def test_reads_of_different_shapes_are_refused():
    with pytest.raises(ValueError, match="one shape"):
        fuse_log_depth(np.ones(3), np.ones(3), np.ones(4), np.ones(4))


def test_the_logistic_weight_is_its_four_terms():
    """logit p = w₀ + w_a log r_a + w_b log r_b + w_g log(|log d_a − log d_b| + g₀), computed by hand."""
    weights = FusionWeights(-1.0, -1.5, 1.0, -2.0, gap_floor=0.01)
    depth_a, depth_b = np.array([3.0, 3.0]), np.array([3.0 * np.exp(0.005), 6.0])
    rel_a, rel_b = 0.2, 0.1
    depth, sigma, weight = fuse_log_depth(depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, weights)
    gap = np.abs(np.log(depth_a / depth_b))
    logit = -1.0 - 1.5 * np.log(rel_a) + 1.0 * np.log(rel_b) - 2.0 * np.log(gap + 0.01)
    want = 1.0 / (1.0 + np.exp(-logit))
    np.testing.assert_allclose(weight, want)
    assert weight[0] > 0.99 and weight[1] < 0.5  # reads that agree take a, reads far apart lean to b
    np.testing.assert_allclose(depth, np.exp(want * np.log(depth_a) + (1 - want) * np.log(depth_b)))
    np.testing.assert_allclose(sigma / depth, want * rel_a + (1 - want) * rel_b)


def test_inverse_variance_is_the_logistic_with_slopes_minus_two_and_two():
    rng = np.random.default_rng(3)
    rel_a, rel_b = np.exp(rng.uniform(-5, 1, 1000)), np.exp(rng.uniform(-5, 1, 1000))
    depth = np.exp(rng.uniform(-1, 2.5, 1000))
    _, _, weight = fuse_log_depth(depth, rel_a * depth, depth * 1.3, rel_b * depth * 1.3, INVERSE_VARIANCE)
    np.testing.assert_allclose(weight, rel_b ** 2 / (rel_a ** 2 + rel_b ** 2), rtol=1e-12)


@pytest.mark.parametrize("bad, match", [
    ({"intercept": 0.0, "rel_sigma_a": -2.0, "rel_sigma_b": float("nan")}, "rel_sigma_b must be a finite"),
    ({"intercept": 0.0, "rel_sigma_a": -2.0, "rel_sigma_b": 2.0, "gap_floor": 0.0}, "need gap_floor"),
    ({"intercept": 0.0, "rel_sigma_a": -2.0, "rel_sigma_b": 2.0, "slope": 1.0}, "unknown fusion weight"),
    ({"intercept": 0.0, "rel_sigma_a": -2.0}, "lack some of"),
    ({"intercept": "0", "rel_sigma_a": -2.0, "rel_sigma_b": 2.0}, "intercept must be a finite"),
])
def test_unreadable_fusion_weights_are_refused_by_name(bad, match):
    with pytest.raises(ValueError, match=match):
        FusionWeights.from_dict(bad)


def _heavy_tailed_reads(seed: int, n: int = 60_000):
    """Read a: 1 % log errors, but a quarter of its pixels 40 % off (a window on the wrong side of focus); read b:
    10 % everywhere. Each pixel's errors scale with a factor of its own (0.5–2 per read), and each read reports
    the σ of its whole error distribution there, so inverse variance favours b."""
    from bmi_sdk.nn.fusion_fit import ReadSet

    rng = np.random.default_rng(seed)
    truth = np.exp(rng.uniform(np.log(0.8), np.log(10.0), n))
    scale_a, scale_b = np.exp(rng.uniform(np.log(0.5), np.log(2.0), (2, n)))
    outlier = rng.random(n) < 0.25
    err_a = scale_a * np.where(outlier, rng.choice([-0.4, 0.4], n), 0.01 * rng.standard_normal(n))
    err_b = scale_b * 0.10 * rng.standard_normal(n)
    rel_a, rel_b = scale_a * np.sqrt(0.25 * 0.16 + 0.75 * 1e-4), scale_b * 0.10
    depth_a, depth_b = truth * np.exp(err_a), truth * np.exp(err_b)
    return ReadSet("synthetic", depth_a, rel_a * depth_a, depth_b, rel_b * depth_b, truth)


def test_the_fit_learns_to_trust_the_precise_read_where_the_two_agree():
    """On reads whose errors are heavy-tailed, the fitted weights beat the inverse-variance ones and each read
    alone on fresh draws; the gap term is what carries it (read a is right wherever b agrees with it)."""
    from bmi_sdk.nn.fusion_fit import fit_fusion_weights, mean_abs_log_error

    weights = fit_fusion_weights([_heavy_tailed_reads(1)], pixels_per_set=20_000)
    held_out = _heavy_tailed_reads(2)
    fitted, inverse = mean_abs_log_error(held_out, weights), mean_abs_log_error(held_out, INVERSE_VARIANCE)
    alone_a = np.mean(np.abs(np.log(held_out.classical_m / held_out.truth_m)))
    alone_b = np.mean(np.abs(np.log(held_out.network_m / held_out.truth_m)))
    assert fitted < 0.75 * min(inverse, alone_a, alone_b)
    assert weights.gap < 0
    assert fit_fusion_weights([_heavy_tailed_reads(1)], pixels_per_set=20_000) == weights


def test_a_fit_without_pixels_is_refused():
    from bmi_sdk.nn.fusion_fit import ReadSet, fit_fusion_weights

    empty = ReadSet("empty", *(np.zeros(0) for _ in range(5)))
    with pytest.raises(ValueError, match="valid pixels"):
        fit_fusion_weights([empty])
    with pytest.raises(ValueError, match="at least one set"):
        fit_fusion_weights([])


def test_the_weights_move_with_log_noise_between_the_levels_fitted_and_hold_beyond():
    # the second level's row has four numbers, as weights fitted before the variation term: its c_v is 0
    weights = FusionWeights(1.0, -2.0, 2.0, 0.0, 0.5, noise_ref_sigma=0.005, noise_levels=(0.02, 0.08),
                            noise_coefficients=((3.0, -1.0, 2.0, 0.0, -1.5), (-1.0, -1.0, 4.0, 2.0)))
    base, at_02, at_08 = (np.array([1.0, -2.0, 2.0, 0.0, 0.5]), np.array([3.0, -1.0, 2.0, 0.0, -1.5]),
                          np.array([-1.0, -1, 4, 2, 0]))
    np.testing.assert_allclose(weights.coefficients(None), base)
    np.testing.assert_allclose(weights.coefficients(0.0), base)  # a noise-free frame
    np.testing.assert_allclose(weights.coefficients(0.001), base)  # below the least noise fitted: held
    np.testing.assert_allclose(weights.coefficients(0.01), (base + at_02) / 2)  # halfway in log σ
    np.testing.assert_allclose(weights.coefficients(0.02), at_02)
    np.testing.assert_allclose(weights.coefficients(0.04), (at_02 + at_08) / 2)
    np.testing.assert_allclose(weights.coefficients(0.5), at_08)  # beyond the most: held
    assert FusionWeights.from_dict(weights.to_dict()) == weights
    with pytest.raises(ValueError, match="noise σ must be a number ≥ 0"):
        weights.coefficients(-0.01)
    with pytest.raises(ValueError, match="5 numbers .4 before variation_a. for each of the 1 noise_levels"):
        FusionWeights(0.0, -2.0, 2.0, noise_levels=(0.02,), noise_coefficients=((1.0, 2.0),))
    with pytest.raises(ValueError, match="must rise above noise_ref_sigma"):
        FusionWeights(0.0, -2.0, 2.0, noise_levels=(0.004,), noise_coefficients=((0.0, -2.0, 2.0, 0.0),))


def _reads_at_noise(seed: int, noise_sigma: float, n: int = 40_000):
    """Read a is 2 % off at σ 0.005 and 30 % off at σ 0.02 but reports 5 % at both; read b is honest (10 %)."""
    from bmi_sdk.nn.fusion_fit import ReadSet

    rng = np.random.default_rng(seed)
    truth = np.exp(rng.uniform(0.0, 2.0, n))
    rel_a_true = 0.02 if noise_sigma < 0.01 else 0.30
    depth_a = truth * np.exp(rel_a_true * rng.standard_normal(n))
    depth_b = truth * np.exp(0.10 * rng.standard_normal(n))
    return ReadSet(f"σ {noise_sigma}", depth_a, 0.05 * depth_a, depth_b, 0.10 * depth_b, truth, noise_sigma)


def test_a_fit_over_two_noise_levels_learns_what_each_reads_sigma_is_worth_at_each():
    """Read a's σ says 5 % at both noise levels but it is 2 % at the one and 30 % at the other: fitted over both
    levels, the weights trust a at low noise and b at high noise, which one set of weights for both cannot."""
    from dataclasses import replace

    from bmi_sdk.nn.fusion_fit import fit_fusion_weights, mean_abs_log_error

    train = [_reads_at_noise(1, 0.005), _reads_at_noise(2, 0.02)]
    weights = fit_fusion_weights(train, pixels_per_set=20_000)
    blind = fit_fusion_weights([replace(s, noise_sigma=0.005) for s in train], pixels_per_set=20_000)
    assert (weights.noise_ref_sigma, weights.noise_levels) == (0.005, (0.02,)) and blind.noise_levels == ()
    low, high = _reads_at_noise(3, 0.005), _reads_at_noise(4, 0.02)
    share_low = fuse_log_depth(low.classical_m, low.classical_sigma_m, low.network_m, low.network_sigma_m, weights,
                               0.005)[2]
    share_high = fuse_log_depth(high.classical_m, high.classical_sigma_m, high.network_m, high.network_sigma_m,
                                weights, 0.02)[2]
    assert share_low.mean() > 0.8 and share_high.mean() < 0.2
    for held_out in (low, high):
        blind_error = mean_abs_log_error(replace(held_out, noise_sigma=0.005), blind)
        assert mean_abs_log_error(held_out, weights) < 0.9 * blind_error
