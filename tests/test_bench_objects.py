"""`bmi bench objects`: its scenes hold the surfaces, textures and depth edges the bench reports on."""

import numpy as np
import pytest

from bmi_sdk.bench.objects import (
    CHANNEL_CORRELATION,
    EXPONENT_SPREADS,
    OBJECT_RANGE_M,
    WALL_RANGE_M,
    WALLS,
    object_scene,
    surface_texture,
)
from bmi_sdk.nn.eval_strata import EDGE_NEAR_PX, edge_distance_px


@pytest.mark.parametrize("contrast", [0.3, 0.03])
def test_a_surfaces_texture_has_a_1_over_f2_spectrum_its_contrast_and_correlated_channels(contrast):
    rgb = surface_texture(256, np.random.default_rng(2), contrast)
    relative = rgb / rgb.mean(axis=(0, 1)) - 1.0
    assert relative.std(axis=(0, 1)) == pytest.approx(np.full(3, contrast), rel=0.1)
    channels = relative.reshape(-1, 3).T
    assert np.corrcoef(channels)[np.triu_indices(3, 1)] == pytest.approx(np.full(3, CHANNEL_CORRELATION), abs=0.05)
    power = np.abs(np.fft.fft2(relative[..., 1])) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(256), np.fft.fftfreq(256), indexing="ij"))
    edges = np.geomspace(4 / 256, 0.4, 9)
    levels = [power[(f >= a) & (f < b)].mean() for a, b in zip(edges[:-1], edges[1:])]
    slope = -np.polyfit(np.log(np.sqrt(edges[1:] * edges[:-1])), np.log(levels), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.15)


def test_every_wall_has_the_same_objects_nearer_than_it_with_depth_edges_to_score():
    scenes = [object_scene(5, contrast) for contrast in WALLS.values()]
    (textured, range_m), (weak, weak_range_m) = scenes
    assert np.array_equal(range_m, weak_range_m)
    wall = range_m >= WALL_RANGE_M[0]
    assert 0.2 < wall.mean() < 1.0 and np.unique(range_m[wall]).size == 1
    assert WALL_RANGE_M[0] <= range_m[wall][0] <= WALL_RANGE_M[1]
    objects = range_m[~wall]
    assert OBJECT_RANGE_M[0] <= objects.min() and objects.max() <= OBJECT_RANGE_M[1]
    assert np.array_equal(textured[~wall], weak[~wall])  # the objects' textures do not depend on the wall
    for rgb, contrast in ((textured, WALLS["textured wall"]), (weak, WALLS["weak wall"])):
        paint = rgb[wall] / rgb[wall].mean(axis=0) - 1.0
        assert paint.std(axis=0) == pytest.approx(np.full(3, contrast), rel=0.25)
    near = edge_distance_px(range_m) <= EDGE_NEAR_PX
    assert 0.02 < near.mean() < 0.5


def test_a_texture_takes_its_exponent_and_a_scattered_scene_keeps_its_objects():
    def slope(rgb):
        g = rgb[..., 1] / rgb[..., 1].mean() - 1.0
        power = np.abs(np.fft.fft2(g)) ** 2
        f = np.hypot(*np.meshgrid(np.fft.fftfreq(256), np.fft.fftfreq(256), indexing="ij"))
        edges = np.geomspace(4 / 256, 0.4, 9)
        levels = [power[(f >= a) & (f < b)].mean() for a, b in zip(edges[:-1], edges[1:])]
        return -np.polyfit(np.log(np.sqrt(edges[1:] * edges[:-1])), np.log(levels), 1)[0]

    assert [slope(surface_texture(256, np.random.default_rng(4), 0.2, p)) for p in (1.6, 2.4)] == pytest.approx(
        [1.6, 2.4], abs=0.15)
    rgb, range_m = object_scene(3, WALLS["textured wall"])
    assert np.array_equal(object_scene(3, WALLS["textured wall"], EXPONENT_SPREADS["1/f²"])[0], rgb)
    scattered, scattered_range_m = object_scene(3, WALLS["textured wall"], EXPONENT_SPREADS["1/f^(2 ± 0.4)"])
    assert np.array_equal(scattered_range_m, range_m) and not np.array_equal(scattered, rgb)  # the same objects
