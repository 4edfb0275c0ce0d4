"""The perturbation model in the optics engine: sensor pose in the tracer, exact offsets/scale, frames."""

import math

import numpy as np
import pytest

from bmi_sdk.optics import fit_pupils, get_lens, psf_from_pupil
from bmi_sdk.optics.perturb import (
    Perturbation,
    glare_kernel,
    image_from_meridional,
    meridional_from_image,
    spot_kernels,
    trace_spots,
)

CENTRE = (2249.5, 2999.5)
LAM = 0.5876


@pytest.fixture(scope="module")
def lens():
    return get_lens()


def test_no_perturbation_is_bit_identical(lens):
    plain = fit_pupils(lens, [0.0, 40.0], [2.0, 10.0], LAM)
    posed = fit_pupils(lens, [0.0, 40.0], [2.0, 10.0], LAM, sensor_offset_mm=np.zeros(3), sensor_rotation=np.eye(3))
    for a, b in zip(plain, posed):
        assert np.array_equal(a.chief_point_mm, b.chief_point_mm)
        assert np.array_equal(a.coeffs["w_waves"], b.coeffs["w_waves"])
    k = psf_from_pupil(plain[1], 21).kernel
    assert np.array_equal(k, psf_from_pupil(plain[1], 21, offset_px=(0.0, 0.0), scale=1.0).kernel)


def test_decenter_moves_the_axial_image_point_by_exactly_delta(lens):
    _, nominal, _ = trace_spots(lens, Perturbation(), [0.0], 30.0, [3.0], LAM, CENTRE)
    _, moved, _ = trace_spots(lens, Perturbation(decenter_um=(10.0, -4.0)), [0.0], 30.0, [3.0], LAM, CENTRE)
    # (row, col) px: the image follows the lens by δ / pitch (2 µm).
    np.testing.assert_allclose(moved[0] - nominal[0], [-2.0, 5.0], atol=1e-4)


def test_frames_round_trip_and_tilt_moves_the_view(lens):
    v = np.array([[0.3, -0.7]])
    for phi in (0.0, 37.0, 90.0, 211.0):
        np.testing.assert_allclose(image_from_meridional(meridional_from_image(v, phi), phi), v, atol=1e-15)
    # 1′ about +col turns the whole view: the axial spot moves by about R·τ = 7.2 mm × 2.9e-4 ≈ 1.05 px along row.
    _, a, _ = trace_spots(lens, Perturbation(), [0.0], 0.0, [3.0], LAM, CENTRE)
    _, b, _ = trace_spots(lens, Perturbation(tilt_arcmin=(1.0, 0.0)), [0.0], 0.0, [3.0], LAM, CENTRE)
    d = b[0] - a[0]
    assert abs(d[1]) < 1e-6 and 1.0 < abs(d[0]) < 1.1


def test_tilt_barely_changes_the_psf_but_decenter_does(lens):
    """The lens is nearly monocentric: a tilt about its centre is nearly a rotation of the view."""
    def kernel(p):
        _, land, _ = trace_spots(lens, p, [50.0], 0.0, [2.5], LAM, CENTRE)
        # the same position relative to the chief ray: shape only
        return spot_kernels(lens, p, [50.0], 0.0, [2.5], LAM, land, 31, CENTRE, sample_offset_px=[(0.0, 0.0)]).kernels[0]

    k0 = kernel(Perturbation())
    tilt = np.abs(kernel(Perturbation(tilt_arcmin=(0.0, 1.0))) - k0).sum()
    dec = np.abs(kernel(Perturbation(decenter_um=(10.0, 0.0))) - k0).sum()
    assert tilt < 0.02 < dec


def test_sensor_radius_moves_focus_off_axis_only(lens):
    def l1(theta):
        _, land, _ = trace_spots(lens, Perturbation(), [theta], 0.0, [10.0], LAM, CENTRE)
        k = [spot_kernels(lens, p, [theta], 0.0, [10.0], LAM, land, 21, CENTRE, sample_offset_px=[(0.0, 0.0)]).kernels[0]
             for p in (Perturbation(), Perturbation(sensor_radius_error_pct=1.0))]
        return np.abs(k[1] - k[0]).sum()

    assert l1(0.0) < 1e-3 < 0.05 < l1(50.0)


def test_exact_offset_is_a_pixel_shift_and_quarter_turns_match_the_rotated_transform(lens):
    fit = fit_pupils(lens, 30.0, 4.0, LAM)[0]
    k0 = psf_from_pupil(fit, 21).kernel
    k1 = psf_from_pupil(fit, 21, offset_px=(1.0, 0.0)).kernel
    # sampling one pixel further along +col is the same kernel one column over (up to the unit-sum renormalisation)
    ratio = k1[:, :-1].sum() / k0[:, 1:].sum()
    np.testing.assert_allclose(k1[:, :-1], k0[:, 1:] * ratio, atol=2e-6)
    p = Perturbation(decenter_um=(7.0, -3.0), psf_scale_pct=3.0)
    _, land, _ = trace_spots(lens, p, [40.0], 90.0, [1.5], LAM, CENTRE)
    fast = spot_kernels(lens, p, [40.0], 90.0, [1.5], LAM, np.rint(land), 31, CENTRE).kernels[0]
    fits, _, _ = trace_spots(lens, p, [40.0], 90.0, [1.5], LAM, CENTRE)
    off = (np.rint(land)[0, 1] - land[0, 1], np.rint(land)[0, 0] - land[0, 0])
    slow = psf_from_pupil(fits[0], 31, rotation_deg=90.0 + 1e-9, offset_px=off, scale=1.03).kernel
    assert np.abs(fast - slow).max() < 1e-5 * fast.max()


def test_glare_and_validation():
    g = glare_kernel(41, (0.3, -0.2), 8.0)
    assert math.isclose(g.sum(), 1.0)
    cy, cx = np.unravel_index(np.argmax(g), g.shape)
    assert (cy, cx) == (20, 20)
    with pytest.raises(ValueError, match="stray_light_fraction"):
        Perturbation(stray_light_fraction=1.5)
    with pytest.raises(ValueError, match="decenter_um"):
        Perturbation().with_term("decenter_um=10")
    p = Perturbation().with_term("decenter_um=10,0").with_term("stray_light_fraction=0.03")
    assert p.decenter_um == (10.0, 0.0) and Perturbation.from_vector(p.to_vector()) == p


def test_a_built_tensor_is_keyed_by_its_errors_and_carries_them_to_exact_kernels(lens, tmp_path):
    """A tensor's identity includes the errors it was built with, a saved tensor keeps them, and an exact-mode
    PsfMap over it (e.g. a calibration's corrected tensor) traces every error, not the nominal lens."""
    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.optics import PsfTensor, TensorSpec
    from bmi_sdk.render import PsfMap

    p = Perturbation(decenter_um=(8.0, -3.0), stray_light_fraction=0.02, sensor_radius_error_pct=0.5)
    spec = TensorSpec(field_deg=(0.0, 40.0), depth_m=(2.0,), kernel_px=21)
    nominal = PsfTensor(lens, spec, cache_dir=tmp_path / "cache")
    built = PsfTensor(lens, spec, cache_dir=tmp_path / "cache", perturbation=p)
    assert built.key != nominal.key and built.cache_dir != nominal.cache_dir
    assert PsfTensor(lens, spec, perturbation=Perturbation()).key == nominal.key  # no errors: the design
    assert built.ensure([0, 1], [0]) == 2
    assert PsfTensor(lens, spec, cache_dir=tmp_path / "cache", perturbation=p).ensure([0, 1], [0]) == 0  # cached
    again = PsfTensor.load(built.save(tmp_path / "built.npz"))
    assert again.perturbation == p and again.key == built.key
    np.testing.assert_array_equal(again.data, built.data)

    carried = PsfMap(again, BMI_SENSOR, mode="exact").kernels(40.0, 30.0, [0])
    named = PsfMap(nominal, BMI_SENSOR, mode="exact", perturbation=p).kernels(40.0, 30.0, [0])
    np.testing.assert_array_equal(carried, named)
    design = PsfMap(nominal, BMI_SENSOR, mode="exact").kernels(40.0, 30.0, [0])
    assert np.abs(carried - design).sum() > 0.05
    with pytest.raises(ValueError, match="built with"):
        PsfMap(again, BMI_SENSOR, mode="exact", perturbation=Perturbation(decenter_um=(1.0, 0.0)))
    given = PsfTensor.from_kernels(lens, spec, built.data)
    assert given.key.startswith("given-") and not given.reproducible
    with pytest.raises(ValueError, match="given kernels"):
        PsfMap(given, BMI_SENSOR, mode="exact")


def test_a_chief_ray_landing_does_not_depend_on_the_pupil_fit(lens):
    """``chief_landing_px`` traces only the chief rays; ``trace_spots`` traces them, then the pupil grid and its fit.
    Kernels and rays may be placed by the former only because the chief ray is aimed and traced apart from the fit:
    both land every spot on the same point to the last bit, perturbed or not (a shift, decenter, tilt and a sensor
    of the wrong radius; infinity included)."""
    from bmi_sdk.optics.perturb import chief_landing_px

    theta, phi, depth = [0.0, 23.0, 51.0, 59.0], [0.0, 40.0, 200.0, 311.0], [0.7, 2.0, math.inf, 9.0]
    built = Perturbation(decenter_um=(6.0, 2.0), tilt_arcmin=(0.4, -0.3), sensor_radius_error_pct=1.0,
                         psf_shift_px=(0.3, -0.2))
    landings = []
    for p in (Perturbation(), built):
        full = trace_spots(lens, p, theta, phi, depth, LAM, CENTRE)[1]
        landings.append(chief_landing_px(lens, p, theta, phi, depth, LAM, CENTRE))
        np.testing.assert_array_equal(landings[-1], full)
    assert np.abs(landings[1] - landings[0]).max() > 1.0  # the built lens lands its spots elsewhere


def test_a_calibrated_camera_s_exact_kernels_are_kept_on_disk(lens, tmp_path, monkeypatch):
    """An exact-mode map with a cache_dir writes each (θ, φ)'s kernels once: another map of the same camera reads
    them without tracing, traces only depths not yet there, another camera gets another folder, and a damaged
    shard is recomputed with a warning (never used)."""
    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.optics import PsfTensor, TensorSpec
    from bmi_sdk.optics.tensor import PsfCacheWarning
    from bmi_sdk.render import PsfMap

    spec = TensorSpec(field_deg=(0.0, 40.0), depth_m=(1.0, 2.0, 4.0), kernel_px=21)

    def camera_map(p):
        return PsfMap(PsfTensor(lens, spec, use_cache=False, perturbation=p), BMI_SENSOR, mode="exact",
                      cache_dir=tmp_path)

    p = Perturbation(decenter_um=(5.0, 0.0), stray_light_fraction=0.01)
    first = camera_map(p)
    traced = first.kernels(33.0, 21.0, [0, 2])
    shards = list(first.exact_cache_dir.glob("*.npz"))
    assert len(shards) == 1
    second = camera_map(p)
    monkeypatch.setattr(second, "_perturbed_mono", lambda *a: pytest.fail("read from disk, not traced"))
    np.testing.assert_array_equal(second.kernels(33.0, 21.0, [0, 2]), traced)
    monkeypatch.undo()
    second.kernels(33.0, 21.0, [1])  # a depth not cached yet is traced and added to the shard
    with np.load(shards[0]) as z:  # a sparse shard: the three depths held, nothing for the grid's others
        assert z["depth_index"].tolist() == [0, 1, 2] and z["psf"].shape[1] == 3
    assert camera_map(Perturbation(decenter_um=(6.0, 0.0))).exact_cache_dir != first.exact_cache_dir
    shards[0].write_bytes(shards[0].read_bytes()[:200])  # truncated
    with pytest.warns(PsfCacheWarning, match="recomputing"):
        np.testing.assert_array_equal(camera_map(p).kernels(33.0, 21.0, [0, 2]), traced)

