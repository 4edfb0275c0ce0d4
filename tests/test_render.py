"""Forward simulator: PSF map, zone convolution against brute force, layered compositing."""

import numpy as np
import pytest
from scipy.signal import fftconvolve

from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens
from bmi_sdk.render import PsfMap, layer_index, render_coded, render_reference, rotate_kernel

MONO = get_lens("bmi_monocentric")
SMALL = TensorSpec(field_deg=tuple(np.round(np.arange(0, 101) * 0.6, 6)), depth_m=(0.7, 1.0, 2.0, 10.0))


@pytest.fixture(scope="module")
def tensor():
    return PsfTensor(MONO, SMALL)


def scene(h, w, rng, depths=(0.7, 1.0, 2.0, 10.0)):
    """Random texture over blocks of the given depths (occlusion edges included)."""
    rgb = rng.uniform(0.05, 1.0, (h, w, 3)).astype(np.float32)
    blocks = rng.integers(0, len(depths), (h // 8 + 1, w // 8 + 1))
    range_m = np.asarray(depths, dtype=np.float32)[np.kron(blocks, np.ones((8, 8), int))[:h, :w]]
    return rgb, range_m


def test_rotate_kernel_orientation():
    k = np.zeros((9, 9), np.float32)
    k[4, 6] = 1.0  # two pixels along +col (the radial axis)
    assert np.unravel_index(rotate_kernel(k, 90.0).argmax(), (9, 9)) == (6, 4)  # → +row (down)
    assert np.unravel_index(rotate_kernel(k, 180.0).argmax(), (9, 9)) == (4, 2)
    r = rotate_kernel(k, 30.0)
    rows, cols = np.mgrid[0:9, 0:9]
    centroid = ((r * rows).sum() - 4, (r * cols).sum() - 4)
    assert centroid == pytest.approx((2 * np.sin(np.radians(30)), 2 * np.cos(np.radians(30))), abs=0.1)
    assert r.sum() == pytest.approx(1.0)


def test_layer_order_and_unknown_depths():
    grid = np.array([0.7, 1.0, 2.0, 10.0])
    layers = layer_index(np.array([[0.7, 0.8, 1.6, 50.0, np.nan, -1.0]]), grid)
    assert layers.tolist() == [[3, 3, 1, 0, 0, 0]]  # 0 = farthest; beyond and unknown → farthest


def test_zone_method_matches_the_per_pixel_reference(tensor):
    rgb, range_m = scene(40, 40, np.random.default_rng(1))
    row0, col0 = 400, 5200  # ~45° out, where the PSF varies across the window
    fast = render_coded(rgb, range_m, tensor, BMI_SENSOR, row0, col0, zone_px=16, psf_mode="tensor")
    slow = render_reference(rgb, range_m, tensor, BMI_SENSOR, row0, col0)
    assert np.abs(fast - slow).mean() < 2e-4 and np.abs(fast - slow).max() < 5e-3


def test_with_one_psf_for_all_layers_the_model_is_a_plain_convolution(tensor):
    """Occlusion-aware compositing reduces exactly to h * I when every layer blurs alike."""
    y, x = np.mgrid[-20:21, -20:21]
    gauss = np.exp(-(x**2 + y**2) / (2 * 3.0**2))
    shape = (len(SMALL.channels), len(SMALL.field_deg), len(SMALL.depth_m), 41, 41)
    flat = PsfTensor.from_kernels(MONO, SMALL, np.broadcast_to(gauss / gauss.sum(), shape))
    rgb, range_m = scene(48, 48, np.random.default_rng(2))
    out = render_coded(rgb, range_m, flat, BMI_SENSOR, 2000, 2000, zone_px=16, psf_mode="tensor")
    expected = np.stack([fftconvolve(rgb[..., c], flat.data[0, 0, 0], mode="same") for c in range(3)], axis=-1)
    assert np.abs(out[20:-20, 20:-20] - expected[20:-20, 20:-20]).max() < 2e-3  # rotating a round Gaussian
    # is the only approximation; the window edge differs by design (E_k renormalises there)


def test_flat_scene_stays_flat_away_from_edges(tensor):
    for depth in (0.7, 10.0):
        rgb = np.ones((96, 96, 3), np.float32)
        out = render_coded(rgb, np.full((96, 96), depth, np.float32), tensor, BMI_SENSOR, 3000, 4500, zone_px=32,
                           psf_mode="tensor")
        inner = out[20:-20, 20:-20]
        assert np.abs(inner - 1.0).max() < 1e-4  # unit-sum kernels: energy neither made nor lost
        assert np.abs(out - 1.0).max() < 1e-3  # E_k renormalises at the window's edge: no darkening


@pytest.mark.parametrize("psf_mode, tolerance", [("exact", 0.02), ("tensor", 0.25)])
def test_point_source_lands_with_its_psf_and_orientation(tensor, psf_mode, tolerance):
    """A point renders as the exact PSF of its pixel; the tensor mode within its measured rotation error."""
    exact = PsfMap(tensor, BMI_SENSOR, mode="exact")
    size = 45
    for row0, col0 in ((2222, 5214), (198, 2970)):  # right of centre (φ≈0), above centre (φ≈−90°)
        rgb = np.zeros((size, size, 3), np.float32)
        rgb[22, 22] = 1.0
        range_m = np.full((size, size), 0.7, np.float32)
        # zone centres at absolute multiples of 22 px: the point sits on one, where its tent weight is 1
        out = render_coded(rgb, range_m, tensor, BMI_SENSOR, row0, col0, zone_px=22, psf_mode=psf_mode)
        theta, phi = BMI_SENSOR.field_angles(row0 + 22, col0 + 22)
        expected = exact.kernels(float(theta), float(phi), [0])[:, 0].transpose(1, 2, 0)
        got = out[2:43, 2:43]
        assert np.abs(got - expected).sum() / 3 < tolerance
        # The radial axis is the narrow one at ~45°–50°: along columns at φ≈0, along rows at φ≈−90°.
        g = got[..., 1]
        idx = np.arange(41) - 20
        spread_cols = (g.sum(axis=0) * idx**2).sum()
        spread_rows = (g.sum(axis=1) * idx**2).sum()
        assert (spread_cols < spread_rows) == (abs(float(phi)) < 45)


def test_exact_kernels_turn_with_the_azimuth(tensor):
    exact = PsfMap(tensor, BMI_SENSOR, mode="exact")
    k0 = exact.kernels(45.0, 0.0, [1])
    k90 = exact.kernels(45.0, 90.0, [1])
    assert np.abs(k90 - np.rot90(k0, k=-1, axes=(2, 3))).max() < 1e-5 * k0.max()


def test_the_decoders_zone_kernels_hold_an_exact_maps_own_kernels_not_a_copy(tensor):
    """An exact map's memoised kernels are handed out as they are, read-only, and the decoder's zone memo keeps
    those same arrays: a full frame's exact kernels are held once (~0.2 GB), not twice."""
    from bmi_sdk.decode import inverse_depth_candidates
    from bmi_sdk.decode.kernels import ZoneKernels

    exact = PsfMap(tensor, BMI_SENSOR, mode="exact")
    candidates = inverse_depth_candidates(tensor.depth_m, 6)
    zones = ZoneKernels(exact, candidates, (2.0,), 64)
    zone = (20.0, 30.0)
    stacked = zones.kernels(zone, [0, 2])
    sets = exact.kernel_sets(*zone, candidates.index[[0, 2]])
    assert sets[0] is exact.kernel_sets(*zone, candidates.index[[0]])[0]  # the memo's array, not a new one
    assert np.array_equal(stacked, np.stack(sets, axis=1))
    assert np.array_equal(stacked, exact.kernels(*zone, candidates.index[[0, 2]]))
    with pytest.raises(ValueError, match="read-only"):
        sets[1][0, 0, 0] = 1.0
    held = [zones.kernels(zone, [j]) for j in (0, 2)]  # asked again: served from the zone memo
    assert all(np.shares_memory(zones._kernels[zone + (j,)], s) for j, s in zip((0, 2), sets))
    assert all(np.array_equal(h[:, 0], s) for h, s in zip(held, sets))
    stacked[:] = 0.0  # what a caller gets is its own array: writing it leaves the memo intact
    assert sets[0].sum() > 0


def test_empty_and_near_zero_coverage_layers_stay_finite(tensor):
    rgb = np.ones((64, 64, 3), np.float32)
    range_m = np.full((64, 64), 0.7, np.float32)
    range_m[30:33, 30:33] = 10.0  # a tiny far patch: E_k ≈ 0 around it for the far layer
    out = render_coded(rgb, range_m, tensor, BMI_SENSOR, 1000, 1000, zone_px=16, psf_mode="tensor")
    assert np.all(np.isfinite(out)) and out.max() <= 1.0 + 1e-5


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_black_and_saturated_scenes(tensor, value):
    rgb = np.full((48, 48, 3), value, np.float32)
    rng = np.random.default_rng(3)
    _, range_m = scene(48, 48, rng)
    out = render_coded(rgb, range_m, tensor, BMI_SENSOR, 100, 100, zone_px=16, psf_mode="tensor")
    inner = out[20:-20, 20:-20]
    assert np.abs(inner - value).max() < 1e-3


def test_sensor_corner_window(tensor):
    rgb, range_m = scene(32, 32, np.random.default_rng(4))
    out = render_coded(rgb, range_m, tensor, BMI_SENSOR, 4500 - 32, 6000 - 32, zone_px=16, psf_mode="tensor")
    assert np.all(np.isfinite(out)) and out.mean() > 0.1


def test_bad_input_is_refused(tensor):
    with pytest.raises(ValueError, match="H × W × 3"):
        render_coded(np.zeros((8, 8)), np.ones((8, 8)), tensor)
    with pytest.raises(ValueError, match="does not match"):
        render_coded(np.zeros((8, 8, 3)), np.ones((4, 8)), tensor)
    with pytest.raises(ValueError, match="finite and non-negative"):
        render_coded(np.full((8, 8, 3), np.nan), np.ones((8, 8)), tensor)


def test_a_window_rendered_alone_equals_the_same_region_of_a_larger_render(tensor):
    rgb, range_m = scene(96, 96, np.random.default_rng(5))
    big = render_coded(rgb, range_m, tensor, BMI_SENSOR, 1000, 1000, zone_px=32, psf_mode="tensor")
    part = render_coded(rgb[20:76, 24:80], range_m[20:76, 24:80], tensor, BMI_SENSOR, 1020, 1024, zone_px=32,
                        psf_mode="tensor")
    # Away from the small window's own edge (one kernel), the two agree: zones are anchored to the sensor.
    assert np.abs(part[21:-21, 21:-21] - big[41:55, 45:59]).max() < 1e-5


# -- a perturbed lens in exact mode ---------------------------------------------------------------------

def _centroid_px(kernel):
    """(row, col) centroid of a (K, K) kernel relative to its centre pixel."""
    rows, cols = np.mgrid[0:kernel.shape[0], 0:kernel.shape[1]] - kernel.shape[0] // 2
    return np.array([(kernel * rows).sum(), (kernel * cols).sum()]) / kernel.sum()


def test_exact_kernels_without_a_perturbation_are_the_traced_pupils_psf_bit_for_bit(tensor):
    """perturbation None or all zero: the kernels of the plain exact map, defined by fit_pupils + psf_from_pupil."""
    from bmi_sdk.optics.perturb import Perturbation
    from bmi_sdk.optics.psf import psf_from_pupil
    from bmi_sdk.optics.pupil import fit_pupils

    spec, theta, phi, depth_index = SMALL, 33.3, 17.0, 2
    lam_nm = sorted({lam for ch in spec.channels for lam, _ in ch})
    fits = fit_pupils(MONO, theta, np.full(len(lam_nm), spec.depth_m[depth_index]), np.array(lam_nm) * 1e-3,
                      grid=spec.fit_grid, degree=spec.fit_degree)
    mono = {lam: psf_from_pupil(f, spec.kernel_px, BMI_SENSOR.pitch_um, spec.oversample, spec.guard,
                                rotation_deg=phi).kernel for lam, f in zip(lam_nm, fits)}
    k = np.stack([sum(w * mono[lam] for lam, w in ch) for ch in spec.channels])
    expected = (k / k.sum(axis=(1, 2), keepdims=True)).astype(np.float32)
    for p in (None, Perturbation(), Perturbation(stray_light_spread_px=3.0)):
        got = PsfMap(tensor, BMI_SENSOR, perturbation=p).kernels(theta, phi, [depth_index])[:, 0]
        assert got.dtype == np.float32 and np.array_equal(got, expected)


def test_a_decentred_lens_moves_the_kernel_where_the_trace_lands_its_chief_ray(tensor):
    """Independent paths: chief-ray landing shift from perturb.trace_spots vs the rendered kernel's centroid."""
    from bmi_sdk.optics.perturb import Perturbation, trace_spots

    nominal = PsfMap(tensor, BMI_SENSOR)
    theta, phi, depth_index, green = 20.0, 30.0, 1, 1  # 1 m (sharp); channel 1 is the 587.6 nm line
    lam_um = SMALL.channels[green][0][0] * 1e-3
    k0 = nominal.kernels(theta, phi, [depth_index])[green, 0]
    for decenter_um in ((10.0, 0.0), (3.0, -7.0), (1e-6, 0.0)):
        p = Perturbation(decenter_um=decenter_um)
        k = PsfMap(tensor, BMI_SENSOR, perturbation=p).kernels(theta, phi, [depth_index])[green, 0]
        landing = [trace_spots(MONO, q, [theta], phi, SMALL.depth_m[depth_index], lam_um, BMI_SENSOR.centre_px)[1][0]
                   for q in (p, Perturbation())]
        expected = landing[0] - landing[1]  # (row, col) px
        assert np.hypot(*expected) == pytest.approx(np.hypot(*decenter_um) / BMI_SENSOR.pitch_um, rel=0.1)
        assert _centroid_px(k) - _centroid_px(k0) == pytest.approx(expected, abs=0.05)
    # The (almost) zero decenter went through the perturbed trace too: no shift, the nominal kernel.
    assert np.abs(k - k0).max() < 1e-4 * k0.max()


def test_a_calibrated_optical_centre_takes_the_whole_image_shift_out(tensor):
    """centre_calibrated: the on-axis spot is where the design puts it; off axis only the field-dependent rest moves."""
    from bmi_sdk.optics.perturb import Perturbation, trace_spots

    p = Perturbation(decenter_um=(10.0, 0.0), tilt_arcmin=(0.0, 1.0))
    depth_index, green = 1, 1
    lam_um = SMALL.channels[green][0][0] * 1e-3
    depth_m = SMALL.depth_m[depth_index]

    def landing(q, theta, phi):
        return trace_spots(MONO, q, [theta], phi, depth_m, lam_um, BMI_SENSOR.centre_px)[1][0]

    whole_image = landing(p, 0.0, 0.0) - landing(Perturbation(), 0.0, 0.0)
    assert np.hypot(*whole_image) > 4.0  # 10 µm of decenter moves the image ~5 px
    for theta, phi in ((0.0, 0.0), (40.0, 120.0)):
        k0 = PsfMap(tensor, BMI_SENSOR).kernels(theta, phi, [depth_index])[green, 0]
        k = PsfMap(tensor, BMI_SENSOR, perturbation=p, centre_calibrated=True).kernels(theta, phi, [depth_index])
        expected = landing(p, theta, phi) - landing(Perturbation(), theta, phi) - whole_image
        assert _centroid_px(k[green, 0]) - _centroid_px(k0) == pytest.approx(expected, abs=0.05)
    assert np.hypot(*expected) < 1.0  # what is left at 40° is a fraction of a pixel


def test_tensor_mode_refuses_a_perturbation(tensor):
    from bmi_sdk.optics.perturb import Perturbation

    with pytest.raises(ValueError, match="psf_mode='exact'"):
        PsfMap(tensor, BMI_SENSOR, mode="tensor", perturbation=Perturbation(tilt_arcmin=(1.0, 0.0)))
    PsfMap(tensor, BMI_SENSOR, mode="tensor", perturbation=Perturbation())  # the design is fine


def test_zones_on_one_theta_ring_share_the_design_fits_and_give_the_kernels_each_would_alone(tensor, monkeypatch):
    """The design's pupil fit depends on θ alone: a map that traced (θ, φ1) first turns the same fits for (θ, φ2)
    (no second trace), and its kernels equal those of a fresh map asked for (θ, φ2) alone. A memo bound of a
    few fits (here 4) keeps only the most recent, and the kernels stay the same."""
    from bmi_sdk.render import psf_map as psf_map_module

    theta, depth_indices = 41.5, [0, 2]
    alone = PsfMap(tensor, BMI_SENSOR).kernels(theta, -72.5, depth_indices)
    traced = []
    real_fit_pupils = psf_map_module.fit_pupils
    monkeypatch.setattr(psf_map_module, "fit_pupils", lambda *a, **k: traced.append(a[1]) or real_fit_pupils(*a, **k))
    ring = PsfMap(tensor, BMI_SENSOR)
    ring.kernels(theta, 17.0, depth_indices)
    shared = ring.kernels(theta, -72.5, depth_indices)
    assert traced == [theta] and np.array_equal(shared, alone)
    monkeypatch.setattr(psf_map_module, "FIT_MEMO_ENTRIES", 4)
    small = PsfMap(tensor, BMI_SENSOR)
    small.kernels(theta, 17.0, depth_indices)
    assert len(small._fits) == 4 and np.array_equal(small.kernels(theta, -72.5, depth_indices), alone)


def test_two_threads_tracing_different_zones_give_the_one_thread_kernels_and_counts(tensor):
    """PsfMap.kernel_sets on distinct field positions from two threads at once (a first frame's block threads):
    every kernel as one thread traces it, and every trace counted once."""
    import threading

    positions = [(12.0, 30.0), (12.0, -150.0), (47.5, 80.0), (47.5, 5.0)]
    serial = PsfMap(tensor, BMI_SENSOR)
    expected = [np.stack(serial.kernel_sets(t, p, [0, 1, 2])) for t, p in positions]
    shared = PsfMap(tensor, BMI_SENSOR)
    got: dict = {}

    def trace(which):
        for n in which:
            got[n] = np.stack(shared.kernel_sets(*positions[n], [0, 1, 2]))

    threads = [threading.Thread(target=trace, args=(which,)) for which in ((0, 2), (1, 3))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.array_equal(got[n], expected[n]) for n in range(len(positions)))
    assert shared.kernels_traced == serial.kernels_traced == 3 * len(positions)


def test_a_built_lens_lands_its_kernels_where_trace_spots_lands_the_design_chief_ray_on_every_ring_zone(tensor):
    """A built lens's kernels are centred where the design's chief ray lands (module doc). The map traces the
    design's chief rays once per θ ring and lands them at each φ; trace_spots traces and lands them at that φ
    itself. Both give the same landing, so the kernels equal the spot kernels placed at trace_spots' landing."""
    from bmi_sdk.optics import spectral
    from bmi_sdk.optics.perturb import Perturbation, spot_kernels, trace_spots

    p = Perturbation(decenter_um=(6.0, -4.0), tilt_arcmin=(1.5, 0.0))
    ring = PsfMap(tensor, BMI_SENSOR, perturbation=p)
    theta, depth_index = 37.5, 1
    lam_um = np.array(spectral.wavelengths_nm(SMALL.channels)) * 1e-3
    depth_m = np.full(len(lam_um), SMALL.depth_m[depth_index])
    for phi in (22.0, -97.5):
        got = ring.kernels(theta, phi, [depth_index])[:, 0]
        _, landing, _ = trace_spots(MONO, Perturbation(), np.full(len(lam_um), theta), phi, depth_m, lam_um,
                                    BMI_SENSOR.centre_px, BMI_SENSOR.pitch_um)
        mono = spot_kernels(MONO, p, np.full(len(lam_um), theta), phi, depth_m, lam_um, landing, SMALL.kernel_px,
                            BMI_SENSOR.centre_px, BMI_SENSOR.pitch_um, SMALL.oversample, SMALL.guard, SMALL.fit_grid,
                            SMALL.fit_degree).kernels
        expected = spectral.channel_kernels({lam: mono[m][None] for m, lam in
                                             enumerate(spectral.wavelengths_nm(SMALL.channels))},
                                            SMALL.channels, clip_negative=True)[:, 0]
        assert np.abs(got - expected).max() <= 1e-6 * expected.max()
    assert sum(key[0] for key in ring._fits) == len(lam_um)  # the chief rays of (θ, depth, λ): traced once
