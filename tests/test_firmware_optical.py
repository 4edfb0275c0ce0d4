"""Optical sources: the simulated camera sees scenes through the lens, consistently in any window."""

import numpy as np
import pytest

from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens
from bmi_sdk.render import render_coded
from bmi_sdk.scenes import generate_scene
from firmware_sim import RenderedScene, make_source, source_names


@pytest.fixture(scope="module")
def tensor():
    """Four depth layers keep the test small; the source's logic does not depend on the grid."""
    return PsfTensor(get_lens(), TensorSpec(depth_m=(0.7, 1.5, 3.0, 10.0)))


def test_blocks_and_strips_equal_one_render(tensor):
    s = generate_scene(160, 160, 1)
    kw = dict(block_px=96, zone_px=64, psf_mode="tensor", tensor=tensor)
    whole = RenderedScene(s.rgb, s.range_m, 1000, 1100, **kw).irradiance(1000, 1100, 160, 160)
    strips = RenderedScene(s.rgb, s.range_m, 1000, 1100, **kw)
    by_strips = np.concatenate([strips.irradiance(1000 + r, 1100, 40, 160) for r in range(0, 160, 40)])
    assert np.array_equal(whole, by_strips)
    one = render_coded(s.rgb, s.range_m, tensor, row0=1000, col0=1100, zone_px=64, psf_mode="tensor")
    assert np.abs(whole - one).max() < 1e-6


def test_outside_the_scene_there_is_no_light(tensor):
    s = generate_scene(64, 64, 2)
    src = RenderedScene(s.rgb, s.range_m, 2000, 3000, block_px=64, zone_px=32, psf_mode="tensor", tensor=tensor)
    window = src.irradiance(1990, 2990, 84, 84)
    assert np.all(window[:10] == 0) and np.all(window[:, :10] == 0) and window[10:, 10:].mean() > 0.01


def test_procedural_source_is_registered():
    assert "procedural" in source_names()
    src = make_source("procedural:3")
    assert src.metadata()["seed"] == 3
