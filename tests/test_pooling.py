"""Evidence pooling (bmi_sdk.decode.pooling): the pooled curve against its definition computed by brute force, a
colour edge that stops it, and, through the real renderer and decoder, a textureless patch that reads its
surface's depth only when pooled."""

from __future__ import annotations

import numpy as np
import pytest

from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
from bmi_sdk.decode.classical import whole_curves
from bmi_sdk.decode.evidence import Evidence
from bmi_sdk.decode.pooling import pool_evidence, window_colour
from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.nn.data import simulate_raw
from bmi_sdk.render import PsfMap, render_coded
from bmi_sdk.sensor import NoiseProfile, relative_illumination

GEOMETRY = lens_geometry("bmi_monocentric")


def _parabolas(rows: int, cols: int, best: np.ndarray, depth_count: int = 12, curvature: float = 2.0) -> np.ndarray:
    k = np.arange(depth_count)
    return (curvature * (k[None, None, :] - best[..., None]) ** 2).astype(np.float32)


def test_the_pooled_curve_is_its_definition_summed_window_by_window():
    rng = np.random.default_rng(0)
    rows, cols, depths = 7, 9, 5
    curves = rng.uniform(0, 30, (rows, cols, depths)).astype(np.float32)
    curves[2, 3] = np.nan  # a window of a skipped block: neither pools nor is pooled
    colour = rng.normal(0, 0.3, (rows, cols, 3)).astype(np.float32)
    s, c, tau = 1.3, 0.4, 10.0
    got = pool_evidence(curves, colour, s, c, tau)
    reach = int(np.ceil(2 * s))
    want = np.full_like(curves, np.nan)
    for i in range(rows):
        for j in range(cols):
            if np.isnan(curves[i, j]).any():
                continue
            acc = curves[i, j].astype(np.float64).copy()
            for u in range(rows):
                for v in range(cols):
                    r2 = (u - i) ** 2 + (v - j) ** 2
                    if r2 == 0 or r2 > reach ** 2 or np.isnan(curves[u, v]).any():
                        continue
                    w = np.exp(-r2 / (2 * s ** 2) - np.sum((colour[u, v] - colour[i, j]) ** 2) / (2 * c ** 2))
                    acc += w * np.minimum(curves[u, v], tau)
            want[i, j] = acc
    assert np.array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(want)], want[~np.isnan(want)], rtol=2e-5)


def test_a_window_without_evidence_reads_its_neighbours_depth_but_not_across_a_colour_edge():
    rows, cols = 9, 8  # the right surface is two windows wide: within reach of (4, 6), more windows are left
    best = np.where(np.arange(cols)[None, :] < 6, 3, 8) * np.ones((rows, 1), int)
    curves = _parabolas(rows, cols, best)
    colour = np.where((np.arange(cols) < 6)[None, :, None], [0.0, 0.0, 0.0], [1.0, -0.5, 0.3]) * np.ones((rows, 1, 1))
    curves[4, 6] = 0.0  # flat: no texture, on the right surface, at its edge
    pooled = pool_evidence(curves, colour.astype(np.float32), 2.0, 0.4, 10.0)
    reads = np.argmin(pooled, axis=-1)
    assert reads[4, 6] == 8
    assert np.array_equal(reads[:, :6], best[:, :6]) and np.array_equal(reads[:, 7:], best[:, 7:])
    blind = np.argmin(pool_evidence(curves, colour.astype(np.float32), 2.0, 1e9, 10.0), axis=-1)
    assert blind[4, 6] != 8  # without the colour weight the left surface's windows outvote its own surface's


def test_window_colour_is_the_log_mean_of_r_g_b_floored_for_black_windows():
    r, g1, g2, b = np.array([0.5, 0.0]), np.array([0.2, 0.0]), np.array([0.4, 0.0]), np.array([0.1, 0.0])
    colour = window_colour([r, g1, g2, b])
    np.testing.assert_allclose(colour[0], np.log([0.5, 0.3, 0.1]), rtol=1e-6)
    np.testing.assert_allclose(colour[1], np.log([1e-3] * 3), rtol=1e-6)


def test_whole_curves_keep_every_scored_candidate_and_interpolate_the_rest():
    coarse, which = np.array([0, 4, 8, 11]), np.array([3, 4, 5])
    truth = np.array([[(k - 4.3) ** 2 for k in range(12)], [(k - 9.0) ** 2 + 1 for k in range(12)]])
    curves = whole_curves(coarse, truth[:, coarse], which, truth[:, which], 12)
    scored = np.union1d(coarse, which)
    np.testing.assert_allclose(curves[:, scored], (truth - truth[:, scored].min(1, keepdims=True))[:, scored],
                               atol=1e-5)
    # between scored candidates, linear interpolation (k = 1, 2 between 0 and 3; 9, 10 between 8 and 11)
    np.testing.assert_allclose(curves[0, 1], curves[0, 0] + (curves[0, 3] - curves[0, 0]) / 3, rtol=1e-6)
    np.testing.assert_allclose(curves[1, 10], curves[1, 8] + 2 * (curves[1, 11] - curves[1, 8]) / 3, rtol=1e-6)
    assert Evidence(curves[:, None, :], np.linspace(1.4, 0.1, 12)).refine()[2].ravel().tolist() == [4, 8]


def test_pooling_needs_positive_scales():
    with pytest.raises(ValueError, match="pool"):
        ClassicalConfig(pool_sigma_px=-1.0)
    with pytest.raises(ValueError, match="pool"):
        ClassicalConfig(pool_colour_sigma=0.0)
    with pytest.raises(ValueError, match="pooling needs"):
        pool_evidence(np.zeros((2, 2, 3), np.float32), np.zeros((2, 2, 3), np.float32), 0.0, 0.4, 10.0)


@pytest.mark.parametrize("field_deg", [10.0, 40.0])
def test_a_textureless_patch_of_a_plane_reads_the_planes_depth_when_pooled(field_deg):
    """A 1/f²-textured plane at 2 m whose centre 112² is one flat grey (the texture's mean), through the real
    renderer. The patch's inner windows hold no texture: alone they read anything (AbsRel 0.17–0.24, up to 4×);
    pooled with their textured neighbours of the same colour, the plane's depth."""
    from bmi_sdk.bench.decoder import plane_texture

    size, depth_m, m = 256, 2.0, 24
    tensor = lens_tensor("bmi_monocentric")
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    rgb = plane_texture(size + 2 * m, "pink", np.random.default_rng(3))
    lo = m + size // 2 - 56
    rgb[lo:lo + 112, lo:lo + 112] = rgb.mean(axis=(0, 1))
    r, c = GEOMETRY.pixel_of_field(field_deg, 30.0)
    row0, col0 = int(r - size / 2) // 2 * 2, int(c - size / 2) // 2 * 2
    optical = render_coded(rgb, np.full((size + 2 * m,) * 2, depth_m, np.float32), tensor, GEOMETRY, row0 - m,
                           col0 - m, psf_map=psf_map)[m:-m, m:-m]
    optical *= relative_illumination(GEOMETRY, row0, col0, size, size)[..., None]
    raw = simulate_raw(optical, 0.005, np.random.default_rng(4), row0, col0)
    patch = np.zeros((size, size), bool)
    patch[size // 2 - 56:size // 2 + 56, size // 2 - 56:size // 2 + 56] = True
    errors = {}
    for pool_px in (0.0, ClassicalConfig().pool_sigma_px):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(pool_sigma_px=pool_px))
        out = decoder.decode(raw, 256, 4095, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
        errors[pool_px] = np.abs(out.depth_m[patch] - depth_m) / depth_m
    pooled = errors[ClassicalConfig().pool_sigma_px]
    assert pooled.mean() < 0.02 and pooled.max() < 0.1
    assert errors[0.0].mean() > 0.1
