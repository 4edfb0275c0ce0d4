"""bmi_sdk.scenes.statistics.spectral_slope against noise whose amplitude spectrum is known by construction."""

import numpy as np
import pytest

from bmi_sdk.scenes.statistics import power_law_levels, spectral_slope


def power_law_noise(size: int, alpha: float, seed: int) -> np.ndarray:
    """Periodic noise with amplitude spectrum exactly ∝ 1/f^alpha: unit-modulus random phases scaled per frequency
    (an independent construction: no code shared with the estimator or the scene generator)."""
    rng = np.random.default_rng(seed)
    f = np.hypot(np.fft.fftfreq(size)[:, None], np.fft.fftfreq(size)[None, :])
    f[0, 0] = 1.0
    phase = np.exp(2j * np.pi * rng.uniform(size=(size, size)))
    spectrum = phase * f ** -alpha
    spectrum[0, 0] = 0.0
    return np.fft.ifft2(spectrum).real


@pytest.mark.parametrize("alpha", [0.5, 1.0, 1.5, 2.0])
def test_the_slope_of_power_law_noise_is_its_exponent(alpha):
    assert spectral_slope(power_law_noise(512, alpha, 0)) == pytest.approx(alpha, abs=0.08)


def test_a_crop_of_power_law_noise_reads_the_same_slope_through_the_window():
    """A crop is not periodic: without the Hann window its borders would pull α of white noise up towards 1."""
    big = power_law_noise(1024, 1.0, 1)
    assert spectral_slope(big[100:356, 300:556]) == pytest.approx(1.0, abs=0.12)
    white = np.random.default_rng(2).standard_normal((256, 256)) + np.linspace(0, 5, 256)[None, :]
    assert spectral_slope(white) == pytest.approx(0.0, abs=0.12)


def test_a_colour_image_reads_its_channel_mean_and_bad_input_is_named():
    grey = power_law_noise(256, 1.0, 3)
    assert spectral_slope(np.repeat(grey[..., None], 3, axis=2)) == pytest.approx(spectral_slope(grey))
    with pytest.raises(ValueError, match="band_cpp"):
        spectral_slope(grey, band_cpp=(0.3, 0.2))
    with pytest.raises(ValueError, match="fewer than 2 cycles"):
        spectral_slope(grey[:40, :40])
    with pytest.raises(ValueError, match="H × W"):
        spectral_slope(np.zeros(16))


def test_power_law_levels_are_flat_for_power_law_noise_and_find_a_notch():
    """1/f noise reads level 1 in every bin (4 draws averaged: the lowest bins hold few frequencies); the same noise
    with its power halved over 1/128–1/64 cycles/px (a notch built in Fourier, independently of the estimator)
    reads a dip there and not elsewhere."""
    size = 1024
    f = np.hypot(np.fft.fftfreq(size)[:, None], np.fft.fftfreq(size)[None, :])
    notch = np.where((f > 1 / 128) & (f < 1 / 64), np.sqrt(0.5), 1.0)
    flat, notched = [], []
    for seed in range(4):
        noise = power_law_noise(size, 1.0, seed)
        f_cpp, level = power_law_levels(noise, bins=8)
        flat.append(level)
        notched.append(power_law_levels(np.fft.ifft2(np.fft.fft2(noise) * notch).real, bins=8)[1])
    flat, ratio = np.mean(flat, axis=0), np.mean(notched, axis=0) / np.mean(flat, axis=0)
    assert np.all(np.abs(np.log(flat)) < np.log(1.15))
    inside = (f_cpp > 1 / 128) & (f_cpp < 1 / 64)
    assert inside.any() and np.all(ratio[inside] / np.median(ratio) < 0.75)
    far = (f_cpp > 1 / 24) | (f_cpp < 1 / 160)
    assert np.all(np.abs(np.log(ratio[far] / np.median(ratio))) < np.log(1.12))
    with pytest.raises(ValueError, match="power_law_levels reads"):
        power_law_levels(np.zeros(16))


@pytest.mark.parametrize("argv, message", [
    (["--seeds", "0"], "--seeds must be at least 1"),
    (["--surface-px", "-3"], "--surface-px must be at least 64"),
    (["--crop-px", "100000"], "must not exceed 8192"),
    (["--levels-scene-px", "512", "--levels-crop-px", "1024"], "--levels-scene-px must lie in"),
])
def test_the_statistics_command_refuses_options_that_draw_nothing_or_exhaust_memory(argv, message, monkeypatch, capsys):
    from bmi_sdk.scenes import statistics

    monkeypatch.setattr("sys.argv", ["statistics"] + argv)
    with pytest.raises(SystemExit):
        statistics._main()
    assert message in capsys.readouterr().err
