"""Sensor model: noise statistics against their analytic moments, CFA phase, ADC limits, cos θ falloff."""

import numpy as np
import pytest

from bmi_sdk.geometry import BMI_SENSOR, IDEAL_BMI_SENSOR
from bmi_sdk.sensor import (
    BLACK_LEVEL_DN,
    PAPER_NOISE_SIGMAS,
    WHITE_LEVEL_DN,
    NoiseProfile,
    SensorModel,
    adc_dn,
    add_gaussian_noise,
    bayer_mosaic,
    cfa_channel_map,
    relative_illumination,
)


@pytest.mark.parametrize("sigma", PAPER_NOISE_SIGMAS)
def test_paper_gaussian_noise_moments(sigma):
    rng = np.random.default_rng(1)
    x = np.full((400, 500), 0.5, np.float32)
    y = add_gaussian_noise(x, sigma, rng)
    assert y.dtype == np.float32
    n = y.size
    assert abs(y.mean() - 0.5) < 5 * sigma / np.sqrt(n) + 1e-7
    # sample std within 5 standard errors of sigma (se ≈ σ / sqrt(2n))
    assert abs(y.std() - sigma) <= 5 * sigma / np.sqrt(2 * n) + 1e-7


def test_paper_noise_clips_and_refuses_bad_sigma():
    rng = np.random.default_rng(0)
    y = add_gaussian_noise(np.zeros((100, 100), np.float32), 0.05, rng)
    assert y.min() == 0.0 and y.max() <= 1.0
    with pytest.raises(ValueError, match="sigma"):
        add_gaussian_noise(np.zeros(3), -0.1, rng)


@pytest.mark.parametrize("mean_e", [3.0, 40.0, 2500.0])  # exact Poisson and Gaussian-limit regimes
def test_poisson_gaussian_dn_moments(mean_e):
    model = SensorModel()
    gain, black = 2.0, 200
    exposure_us = 1000.0
    irr = np.full((500, 400), mean_e / (model.electrons_per_us * exposure_us), np.float32)
    dn = model.expose_mosaic(irr, exposure_us, gain, black, np.random.default_rng(7)).astype(np.float64)
    g = model.conversion_gain_dn_per_e * gain
    mu = black + g * mean_e
    var = g * g * (mean_e + model.read_noise_e**2) + 1 / 12
    n = dn.size
    assert abs(dn.mean() - mu) < 5 * np.sqrt(var / n)
    assert abs(dn.var() / var - 1) < 5 * np.sqrt(2 / n) + 0.01


@pytest.mark.parametrize("additive_sigma, irradiance, exposure_us, gain, black", [
    (None, 0.0, 1000, 1.0, 256),     # read noise and ADC rounding only: the offset alone
    (None, 0.005, 5000, 4.0, 64),    # 15 e⁻: exact Poisson regime
    (None, 0.1, 2000, 1.0, 256),     # 120 e⁻: Gaussian limit
    (None, 0.2, 1000, 16.0, 256),    # highest gain
    (None, 0.5, 10_000, 1.5, 0),     # 3000 e⁻, half the well
    (0.01, 0.3, 10_000, 1.0, 256),   # the paper's additive model
    (0.01, 0.05, 2000, 8.0, 64),
    (0.01, 0.5, 500, 2.0, 256),      # σ of 3.8 DN: rounding still a small part
])
def test_noise_profile_is_the_measured_variance_of_flat_fields(additive_sigma, irradiance, exposure_us, gain, black):
    """Var[x] of a 400×400 flat field through the whole chain (shot/additive noise, read noise, ADC) equals
    the profile at the field's expected signal x = g μ / (white − black), within 4 σ of the sample variance."""
    model = SensorModel() if additive_sigma is None else SensorModel(additive_sigma=additive_sigma)
    dn = model.expose_mosaic(np.full((400, 400), irradiance, np.float32), exposure_us, gain, black,
                             np.random.default_rng(11))
    span = model.white_level_dn - black
    x = (dn.astype(np.float64) - black) / span
    assert 0 < dn.min() and dn.max() < model.white_level_dn  # nothing clipped: the profile's domain
    expected_x = model.conversion_gain_dn_per_e * gain * irradiance * model.electrons_per_us * exposure_us / span
    profile = model.noise_profile(gain, exposure_us, black)
    expected_var = float(profile.variance(expected_x))
    n = x.size
    assert abs(x.mean() - expected_x) < 5 * np.sqrt(expected_var / n)
    assert abs(x.var(ddof=1) / expected_var - 1) < 4 * np.sqrt(2 / (n - 1))  # ≈ 0.014
    assert (profile.scale == 0) == (additive_sigma is not None)  # the additive model has no shot noise


@pytest.mark.parametrize("scale, offset", [(-1e-4, 1e-6), (1e-4, -1e-9), (np.nan, 1e-6), (1e-4, np.inf), (0.0, 0.0)])
def test_noise_profile_refuses_negative_non_finite_and_all_zero_values(scale, offset):
    with pytest.raises(ValueError, match="NoiseProfile"):
        NoiseProfile(scale, offset)


def test_saturation_and_black_frame():
    model = SensorModel(read_noise_e=0.0)
    hot = model.expose_mosaic(np.full((8, 8), 50.0, np.float32), 10_000, 16.0, 256, np.random.default_rng(0))
    assert (hot == model.white_level_dn).all()
    dark = model.expose_mosaic(np.zeros((8, 8), np.float32), 10_000, 1.0, 256, np.random.default_rng(0))
    assert (dark == 256).all()
    # the full well clips before the ADC: gain 1 on a full well stays below white
    well = model.expose_mosaic(np.full((8, 8), 50.0, np.float32), 10_000, 1.0, 0, np.random.default_rng(0))
    assert (well == round(model.full_well_e * model.conversion_gain_dn_per_e)).all()


def test_adc_refuses_bad_black_level():
    with pytest.raises(ValueError, match="black_level_dn"):
        SensorModel().adc(np.zeros(2), 1.0, 5000)
    with pytest.raises(ValueError, match="black_level_dn"):
        adc_dn(np.zeros(2), 1.0, 4095, 4095)


def test_adc_adds_the_black_level_rounds_to_even_and_clips_at_zero_and_white():
    assert (BLACK_LEVEL_DN, WHITE_LEVEL_DN) == (256, 4095)  # 12 bits
    dn = adc_dn(np.array([0.0, 0.4, 0.6, 1.5, 2.5, -10.0, -300.0, 5000.0]), 1.0, 256, 4095)
    assert dn.dtype == np.uint16
    assert dn.tolist() == [256, 256, 257, 258, 258, 246, 0, 4095]  # 257.5 → 258, 258.5 → 258 (ties to even)
    # a [0, 1] signal spanning black to white, as training digitises it
    assert adc_dn(np.array([0.0, 0.5, 1.0, 1.2]), 4095 - 256, 256, 4095).tolist() == [256, 2176, 4095, 4095]


@pytest.mark.parametrize("sigma, row0, col0", [(0.0, 0, 0), (0.02, 0, 0), (0.02, 1, 3)])
def test_training_raw_frames_are_the_noisy_mosaic_through_the_12_bit_adc(sigma, row0, col0):
    """nn.data.simulate_raw, bit for bit: noise, RGGB mosaic at the window's phase, then DN = black +
    signal × (white − black) in float32, rounded and clipped to [0, 4095] (written out here, not through
    the SDK's ADC)."""
    from bmi_sdk.nn.data import simulate_raw

    optical = np.random.default_rng(2).uniform(-0.05, 1.05, (24, 36, 3)).astype(np.float32)
    raw = simulate_raw(optical, sigma, np.random.default_rng(5), row0, col0)
    mosaic = bayer_mosaic(add_gaussian_noise(optical, sigma, np.random.default_rng(5)), row0, col0)
    expected = np.clip(np.rint(np.float32(256) + mosaic * np.float32(4095 - 256)), 0, 4095).astype(np.uint16)
    assert raw.dtype == np.uint16
    np.testing.assert_array_equal(raw, expected)


def test_bayer_mosaic_rggb_phase_follows_window_offset():
    h, w = 6, 8
    rgb = np.stack([np.full((h, w), c, np.float32) for c in (1, 2, 3)], axis=-1)
    m = bayer_mosaic(rgb)
    assert m[0, 0] == 1 and m[0, 1] == 2 and m[1, 0] == 2 and m[1, 1] == 3
    # a window starting at an odd row/col on the full sensor starts on B
    m11 = bayer_mosaic(rgb, row0=1, col0=1)
    assert m11[0, 0] == 3 and m11[1, 1] == 1
    full = bayer_mosaic(np.random.default_rng(0).random((10, 12, 3)))
    win = bayer_mosaic(np.random.default_rng(0).random((10, 12, 3))[3:9, 5:11], row0=3, col0=5)
    np.testing.assert_array_equal(full[3:9, 5:11], win)
    np.testing.assert_array_equal(cfa_channel_map(2, 2), [[0, 1], [1, 2]])


def test_relative_illumination_cos_theta():
    g = BMI_SENSOR
    cy, cx = g.centre_px
    row0, col0 = 2000, 3500
    ri = relative_illumination(g, row0, col0, 10, 20)
    assert ri.shape == (10, 20) and ri.dtype == np.float32
    r, c = 5, 7
    theta_rad = np.radians(g.field_angles(row0 + r, col0 + c)[0])  # the lens's traced field of that pixel
    assert ri[r, c] == pytest.approx(np.cos(theta_rad), rel=1e-6)
    # with the ideal mapping the corner is just inside the 60° field (59.7°); the design lens sees 60.06° there,
    # outside its image circle, so the corner is dark, as on a sensor with a 50° circle
    assert relative_illumination(IDEAL_BMI_SENSOR, 0, 0, 1, 1)[0, 0] == pytest.approx(np.cos(np.radians(59.68)),
                                                                                     abs=1e-3)
    assert relative_illumination(g, 0, 0, 1, 1)[0, 0] == 0.0
    narrow = type(g)(max_field_deg=50.0)
    assert relative_illumination(narrow, 0, 0, 1, 1)[0, 0] == 0.0
    # the table is made once per geometry, to the farthest corner: blocks at the field edge and past the sensor (a
    # reflected margin) still read each pixel's own cos θ, or 0 beyond the circle
    for row0, col0 in ((4244, 5744), (-40, -60), (1200, 5900)):
        ri = relative_illumination(IDEAL_BMI_SENSOR, row0, col0, 256, 256)
        rows, cols = np.mgrid[row0:row0 + 256, col0:col0 + 256]
        theta = IDEAL_BMI_SENSOR.field_angles(rows, cols)[0]
        expected = np.where(theta <= IDEAL_BMI_SENSOR.max_field_deg, np.cos(np.radians(theta)), 0.0)
        np.testing.assert_allclose(ri, expected, atol=2e-6)
