"""Optical sources: the simulated camera sees scenes through the lens, consistently in any window."""

import numpy as np

from bmi_sdk.render import render_coded
from bmi_sdk.scenes import generate_scene
from firmware_sim import RenderedScene, make_source, source_names
from firmware_sim.optical import _tensor


def test_blocks_and_strips_equal_one_render():
    s = generate_scene(200, 200, 1)
    src = RenderedScene(s.rgb, s.range_m, 1000, 1100, block_px=128, zone_px=64, psf_mode="tensor")
    whole = src.irradiance(1000, 1100, 200, 200)
    strips = RenderedScene(s.rgb, s.range_m, 1000, 1100, block_px=128, zone_px=64, psf_mode="tensor")
    by_strips = np.concatenate([strips.irradiance(1000 + r, 1100, 50, 200) for r in range(0, 200, 50)])
    assert np.array_equal(whole, by_strips)
    one = render_coded(s.rgb, s.range_m, _tensor("bmi_monocentric"), row0=1000, col0=1100, zone_px=64,
                       psf_mode="tensor")
    assert np.abs(whole - one).max() < 1e-6


def test_outside_the_scene_there_is_no_light():
    s = generate_scene(64, 64, 2)
    src = RenderedScene(s.rgb, s.range_m, 2000, 3000, block_px=64, zone_px=32, psf_mode="tensor")
    window = src.irradiance(1990, 2990, 84, 84)
    assert np.all(window[:10] == 0) and np.all(window[:, :10] == 0) and window[10:, 10:].mean() > 0.01


def test_procedural_source_is_registered():
    assert "procedural" in source_names()
    src = make_source("procedural:3")
    assert src.metadata()["seed"] == 3
