"""`bmi bench texture`: its planes hold the power spectrum they are named for."""

import numpy as np
import pytest

from bmi_sdk.bench.decoder import power_law_texture
from bmi_sdk.bench.texture import POWER_SLOPES


@pytest.mark.parametrize("slope", POWER_SLOPES)
def test_a_planes_power_spectrum_falls_as_its_named_slope(slope):
    rgb = power_law_texture(256, slope, np.random.default_rng(1))
    assert abs(rgb.mean() - 0.4) < 0.01 and abs(rgb.std() - 0.15) < 0.01
    g = rgb[..., 1] - rgb[..., 1].mean()
    power = np.abs(np.fft.fft2(g)) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(256), np.fft.fftfreq(256), indexing="ij"))
    edges = np.geomspace(4 / 256, 0.4, 9)
    centres = np.sqrt(edges[1:] * edges[:-1])
    levels = [power[(f >= a) & (f < b)].mean() for a, b in zip(edges[:-1], edges[1:])]
    fitted = -np.polyfit(np.log(centres), np.log(levels), 1)[0]
    assert fitted == pytest.approx(slope, abs=0.15)
