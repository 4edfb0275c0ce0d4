"""Procedural scenes: determinism, value ranges, layered piecewise-planar depth, 1/f statistics."""

import numpy as np
import pytest

from bmi_sdk.scenes import Scene, generate_scene
from bmi_sdk.scenes.procedural import _Painter, pink_noise


def spectrum_slope(image, fmin, fmax):
    """Log-log slope of the radially averaged amplitude spectrum (Hann window) between fmin and fmax."""
    image = image - image.mean()
    h, w = image.shape
    window = np.hanning(h)[:, None] * np.hanning(w)[None, :]
    amplitude = np.abs(np.fft.fft2(image * window)).ravel()
    f = np.hypot(np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]).ravel()
    edges = np.geomspace(fmin, fmax, 12)
    which = np.digitize(f, edges)
    fa = [f[which == i].mean() for i in range(1, len(edges))]
    aa = [amplitude[which == i].mean() for i in range(1, len(edges))]
    return np.polyfit(np.log(fa), np.log(aa), 1)[0]


def test_same_seed_same_scene_and_generator_accepted():
    a = generate_scene(96, 128, 7)
    b = generate_scene(96, 128, np.random.default_rng(7))
    c = generate_scene(96, 128, 8)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.range_m, b.range_m)
    assert not np.array_equal(a.range_m, c.range_m)


@pytest.mark.parametrize("shape", [(64, 64), (37, 101), (480, 640)])
def test_output_contract(shape):
    scene = generate_scene(*shape, 3)
    assert isinstance(scene, Scene) and scene.intrinsics is None
    assert scene.rgb.shape == (*shape, 3) and scene.rgb.dtype == np.float32
    assert scene.range_m.shape == shape and scene.range_m.dtype == np.float32
    assert np.all(np.isfinite(scene.range_m))
    assert scene.range_m.min() >= 0.7 and scene.range_m.max() <= 10.0
    assert scene.rgb.min() >= 0.0 and scene.rgb.max() <= 1.0


def test_depth_is_piecewise_planar_with_sharp_edges_and_spans_the_range():
    ranges = [generate_scene(256, 256, seed).range_m.astype(np.float64) for seed in range(4)]
    inv = np.stack([1.0 / r for r in ranges])
    # sharp occlusion edges: neighbouring pixels on different surfaces, >10 % apart in range
    jump = np.abs(np.diff(np.log(np.stack(ranges)), axis=2))
    edge_fraction = np.mean(jump > 0.1)
    assert 0.001 < edge_fraction < 0.05
    # inside surfaces inverse range is affine along rows (slanted planes): second difference ~0
    d1, d2 = np.diff(inv, axis=2)[:, :, :-1], np.diff(inv, axis=2)[:, :, 1:]
    same_surface = (np.abs(d1) < 0.01 * inv[:, :, 1:-1]) & (np.abs(d2) < 0.01 * inv[:, :, 1:-1])
    second = np.abs(d2 - d1)[same_surface] / inv[:, :, 1:-1][same_surface]
    assert np.mean(second < 1e-4) > 0.98
    # surfaces are slanted, not fronto-parallel layers: depth varies smoothly inside them
    assert np.mean(np.abs(d1[same_surface]) > 0) > 0.5
    # near and far both occur across seeds
    all_r = np.concatenate([r.ravel() for r in ranges])
    assert all_r.min() < 1.5 and all_r.max() > 4.5


def test_near_objects_occlude_far_ones_consistently():
    """Z-buffer: a surface painted later but farther must not overwrite a nearer one."""
    p = _Painter(64, 64, np.random.default_rng(0), 0.7, 10.0)
    p.background(8.0, slant=0.0)
    near = np.ones((20, 20), dtype=np.uint8)
    p.surface(10, 10, near, 1.0, slant=0.0)
    p.surface(20, 20, np.ones((20, 20), dtype=np.uint8), 5.0, slant=0.0)  # farther, painted after
    assert np.allclose(p.range_m[10:30, 10:30], 1.0)
    assert np.allclose(p.range_m[30:40, 30:40], 5.0)
    assert np.allclose(p.range_m[0:5, 0:5], 8.0)


def test_pink_noise_has_one_over_f_amplitude():
    noise = pink_noise((512, 512), np.random.default_rng(1))
    assert abs(noise.mean()) < 1e-5 and abs(noise.std() - 1) < 1e-5
    assert spectrum_slope(noise, 4 / 512, 0.45) == pytest.approx(-1.0, abs=0.1)


def test_multiscale_texture_keeps_one_over_f_across_the_detail_cutoff():
    """Low field (1/32 res, upsampled) + periodic detail tile must join into one ≈1/f spectrum."""
    size = 1024
    painter = _Painter(size, size, np.random.default_rng(2), 0.7, 10.0)
    luminance = painter.texture(size, size, contrast=1.0, chroma=0.0)[:, :, 0]
    assert spectrum_slope(luminance, 4 / size, 1 / 64) == pytest.approx(-1.0, abs=0.25)
    assert spectrum_slope(luminance, 1 / 64, 0.4) == pytest.approx(-1.0, abs=0.25)


def test_scene_statistics_are_natural():
    slopes, saturated, dark = [], [], []
    for seed in range(3):
        rgb = generate_scene(512, 512, seed).rgb
        slopes.append(spectrum_slope(rgb.mean(axis=2), 4 / 512, 0.4))
        saturated.append(np.mean(rgb.max(axis=2) >= 1.0))
        dark.append(np.mean(rgb.max(axis=2) < 0.02))
        # colour varies: the channels are not copies of one another
        assert np.std(rgb[:, :, 0] - rgb[:, :, 2]) > 0.01
    assert all(-1.6 < s < -0.8 for s in slopes), slopes
    assert 0 < np.mean(saturated) < 0.1
    assert np.mean(dark) > 0


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="at least 8"):
        generate_scene(4, 64, 0)
    with pytest.raises(ValueError, match="near_m"):
        generate_scene(64, 64, 0, near_m=5.0, far_m=2.0)


@pytest.mark.parametrize("power", [1.4, 2.6])
def test_a_surface_drawn_at_another_power_exponent_keeps_it_across_the_detail_cutoff(monkeypatch, power):
    """A 1/f^p texture's amplitude slope differs from a 1/f² one's by −(p − 2)/2 on both sides of the cutoff: the
    low field's exponent, the detail tile's and the band weights all follow p. (The upsampled low field rolls off
    towards its Nyquist frequency alike at every p, so the slopes are compared with p = 2's, the same draws.)"""
    size = 1024

    def slopes(p):
        painter = _Painter(size, size, np.random.default_rng(3), 0.7, 10.0, exponent_spread=0.4)
        monkeypatch.setattr(painter, "power_exponent", lambda: p)
        luminance = painter.texture(size, size, contrast=1.0, chroma=0.0)[:, :, 0]
        return np.array([spectrum_slope(luminance, 4 / size, 1 / 64), spectrum_slope(luminance, 1 / 64, 0.4)])

    np.testing.assert_allclose(slopes(power) - slopes(2.0), -(power - 2.0) / 2, atol=0.1)


def test_scattered_exponents_follow_their_law_and_leave_the_scene_as_it_was():
    painter = _Painter(64, 64, np.random.default_rng(4), 0.7, 10.0, exponent_spread=0.4)
    draws = np.array([painter.power_exponent() for _ in range(4000)])
    assert draws.mean() == pytest.approx(2.0, abs=0.03) and draws.std() == pytest.approx(0.4, abs=0.03)
    assert draws.min() >= 1.0 and draws.max() <= 3.0
    assert _Painter(64, 64, np.random.default_rng(4), 0.7, 10.0).power_exponent() == 2.0
    plain, natural = generate_scene(256, 256, 9), generate_scene(256, 256, 9, exponent_spread=0.4)
    np.testing.assert_array_equal(plain.range_m, natural.range_m)  # the same layout and ranges
    assert np.abs(np.log(plain.rgb + 1e-3) - np.log(natural.rgb + 1e-3)).mean() > 0.01  # other textures
    np.testing.assert_array_equal(generate_scene(256, 256, 9, exponent_spread=0.0).rgb, plain.rgb)


@pytest.mark.parametrize("spread", [-0.1, 1.5, float("nan")])
def test_a_bad_exponent_spread_is_refused(spread):
    with pytest.raises(ValueError, match="exponent_spread"):
        generate_scene(64, 64, 0, exponent_spread=spread)
