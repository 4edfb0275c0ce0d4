"""`bmi bench objects`: its scenes hold the surfaces, textures and depth edges the bench reports on."""

import numpy as np
import pytest

from bmi_sdk.bench.objects import (
    CHANNEL_CORRELATION,
    EXPONENT_SPREADS,
    OBJECT_RANGE_M,
    WALL_RANGE_M,
    WALLS,
    lamp_irradiance,
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
    (textured, range_m), (weak, weak_range_m), (lit, lit_range_m) = [object_scene(5, wall) for wall in WALLS.values()]
    assert np.array_equal(range_m, weak_range_m) and np.array_equal(range_m, lit_range_m)
    wall = range_m >= WALL_RANGE_M[0]
    assert 0.2 < wall.mean() < 1.0 and np.unique(range_m[wall]).size == 1
    assert WALL_RANGE_M[0] <= range_m[wall][0] <= WALL_RANGE_M[1]
    objects = range_m[~wall]
    assert OBJECT_RANGE_M[0] <= objects.min() and objects.max() <= OBJECT_RANGE_M[1]
    # the objects' textures do not depend on the wall
    assert np.array_equal(textured[~wall], weak[~wall]) and np.array_equal(lit[~wall], weak[~wall])
    for rgb, name in ((textured, "textured wall"), (weak, "weak wall")):
        paint = rgb[wall] / rgb[wall].mean(axis=0) - 1.0
        assert paint.std(axis=0) == pytest.approx(np.full(3, WALLS[name].contrast), rel=0.25)
    # the lamp-lit wall is the weak wall's paint times one smooth irradiance, the same in every channel (where
    # neither is clipped to the paint's range)
    unclipped = np.all((np.minimum(lit[wall], weak[wall]) > 0.0051) & (np.maximum(lit[wall], weak[wall]) < 0.999),
                       axis=1)
    shading = lit[wall][unclipped] / weak[wall][unclipped]
    assert unclipped.mean() > 0.5 and np.allclose(shading, shading[:, :1], rtol=1e-4)
    assert shading.max() / shading.min() > 1.5
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


def test_a_lamps_irradiance_falls_as_the_inverse_square_times_the_incidence_cosine():
    """``lamp_irradiance`` against the point source's law, h / (h² + r²)^(3/2), at the lamp's foot and one lamp
    distance from it (2^(-3/2) of the foot's), with unit mean over the wall."""
    from bmi_sdk.bench.objects import LAMP_DISTANCE_PX

    size = 900
    irradiance = lamp_irradiance(size, np.random.default_rng(7))
    assert irradiance.mean() == pytest.approx(1.0, rel=1e-9) and irradiance.min() > 0
    foot = np.unravel_index(np.argmax(irradiance), irradiance.shape)
    h = int(LAMP_DISTANCE_PX)
    away = [(foot[0] + dr, foot[1] + dc) for dr, dc in ((h, 0), (-h, 0), (0, h), (0, -h))
            if 0 <= foot[0] + dr < size and 0 <= foot[1] + dc < size]
    assert away
    for point in away:
        assert irradiance[point] / irradiance[foot] == pytest.approx(2 ** -1.5, rel=0.01)
