"""PSFs and the PSF tensor: analytic Airy case, the centroid theorem, symmetry, energy, caching."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import j1

from bmi_sdk.optics import PsfTensor, TensorSpec, fit_pupil, fit_pupils, get_lens, psf_from_pupil, trace
from bmi_sdk.optics.paraxial import entrance_pupil, indices
from bmi_sdk.optics.pupil import _fit_batched, _launch, _pairs, stop_radius_mm

MONO = get_lens("bmi_monocentric")


def airy_pixel_integrated(na, lam_um, kernel_px, pitch_um, sub=41):
    """Airy pattern [2J1(v)/v]², v = 2π NA r / λ, integrated over pixels by brute force."""
    off = ((np.arange(sub) + 0.5) / sub - 0.5) * pitch_um
    centres = (np.arange(kernel_px) - kernel_px // 2) * pitch_um
    x = (centres[:, None] + off[None, :]).ravel()
    r = np.hypot(x[:, None], x[None, :])
    v = 2 * np.pi * na * r / lam_um
    with np.errstate(invalid="ignore", divide="ignore"):
        intensity = np.where(v > 0, (2 * j1(v) / v) ** 2, 1.0)
    px = intensity.reshape(kernel_px, sub, kernel_px, sub).sum(axis=(1, 3))
    return px / px.sum()


def test_perfect_pupil_gives_the_pixel_integrated_airy_pattern():
    fit = fit_pupil(MONO, 0.0, math.inf, 0.5876)
    na = 0.12  # narrower than the lens so that the disc lies inside the fitted grid
    size = fit.degree + 1
    coeffs = {name: np.zeros((size, size)) for name in fit.coeffs}
    coeffs["amplitude"][0, 0] = 1.0
    coeffs["stop"][2, 0] = (fit.l_half / na) ** 2  # ρ² = (L² + M²) / NA² in normalised coordinates
    coeffs["stop"][0, 2] = (fit.m_half / na) ** 2
    perfect = replace(fit, coeffs=coeffs, apertures=["stop"])
    reference = airy_pixel_integrated(na, 0.5876, 21, 1.0)
    # The Airy pattern's 1/r³ tails alias back through the transform's replicas; the error falls
    # as the replicas move away (guard), which is what the default's error budget is made of.
    errors = [np.abs(psf_from_pupil(perfect, 21, pitch_um=1.0, guard=g).kernel - reference).sum() for g in (2.0, 5.0)]
    assert errors[1] < 3e-3 and errors[1] < errors[0] / 3


def spot_centroid_um(lens, field_deg, depth_m, lam_um, fit):
    """Geometric spot centroid relative to the chief ray, from a dense uniform launch grid."""
    z_ep, per = entrance_pupil(lens, indices(lens, lam_um))
    r_stop = stop_radius_mm(lens)
    g = np.linspace(-4, 4, 301) * r_stop / abs(per)
    a, b = np.meshgrid(g, g, indexing="ij")
    o, d, opl = _launch(lens, np.array([field_deg]), np.array([depth_m]), np.array([z_ep]),
                        a.ravel()[None], b.ravel()[None])
    rays = trace(lens, lam_um, o, d, opl)
    ok = rays.alive[0] & (np.hypot(*rays.stop_xy_mm[0].T) <= r_stop)
    for j in range(len(lens.surfaces)):
        ok &= rays.rel_height[j][0] <= 1.0
    q = rays.position[0][ok] - fit.chief_point_mm
    return float((q @ fit.e_rad).mean() * 1e3), float((q @ fit.e_sag).mean() * 1e3)


@pytest.mark.parametrize("lens_name, field_deg, depth_m", [("bmi_monocentric", 60.0, 0.7),
                                                            ("fisheye", 30.0, 2.0)])
def test_psf_centroid_equals_geometric_spot_centroid(lens_name, field_deg, depth_m):
    """Diffraction does not move the centroid: the PSF's first moment is the rays' mean landing point.

    This pins the sign and orientation conventions of the whole chain (eikonal, Debye integral,
    kernel axes) against plain ray tracing.
    """
    lens = get_lens(lens_name)
    fit = fit_pupil(lens, field_deg, depth_m, 0.4861)
    kernel_px = 41 if lens_name == "bmi_monocentric" else 161  # ≥ 99.7 % of the energy in both
    psf = psf_from_pupil(fit, kernel_px)
    x = (np.arange(kernel_px) - kernel_px // 2) * 2.0
    cx, cy = spot_centroid_um(lens, field_deg, depth_m, 0.4861, fit)
    assert (psf.kernel.sum(axis=0) * x).sum() == pytest.approx(cx, abs=0.15 + 0.02 * abs(cx))
    assert (psf.kernel.sum(axis=1) * x).sum() == pytest.approx(cy, abs=0.05)
    assert abs(cx) > 0.3  # a real asymmetry is being compared, not two zeros


def test_on_axis_psf_has_the_symmetry_of_a_square_pixel_grid():
    k = psf_from_pupil(fit_pupil(MONO, 0.0, 1.0, 0.5876), 41).kernel
    for other in (k[::-1], k[:, ::-1]):  # mirror symmetries: exact by construction of the ray grid
        assert np.abs(k - other).max() < 1e-5 * k.max()
    # Swapping axes compares two independently fitted directions: equal to the fit's accuracy.
    assert np.abs(k - k.T).max() < 3e-3 * k.max()


def test_off_axis_psf_is_mirror_symmetric_and_compressed_radially():
    k = psf_from_pupil(fit_pupil(MONO, 60.0, 0.7, 0.5876), 41).kernel
    assert np.abs(k - k[::-1]).max() < 1e-6 * k.max()  # meridional plane of symmetry
    x = np.arange(41) - 20
    rad = np.sqrt((k.sum(axis=0) * x**2).sum())
    sag = np.sqrt((k.sum(axis=1) * x**2).sum())
    assert 0.45 < rad / sag < 0.75  # the oblique pupil (≈ cos 60°) narrows the radial extent


@pytest.mark.parametrize("field_deg, depth_m, lam_um", [(0.0, 0.7, 0.6563), (60.0, 0.7, 0.6563), (60.0, 0.7, 0.4861),
                                                        (0.0, math.inf, 0.4), (60.0, math.inf, 0.7)])
def test_energy_and_normalisation_at_the_extremes(field_deg, depth_m, lam_um):
    psf = psf_from_pupil(fit_pupil(MONO, field_deg, depth_m, lam_um), 41)
    assert np.all(np.isfinite(psf.kernel)) and psf.kernel.min() >= 0
    assert psf.kernel.sum() == pytest.approx(1.0, abs=1e-9)
    assert 0.99 <= psf.energy_captured <= 1.0 + 1e-3  # the 41 px energy criterion holds at 0.7 m


def test_pixel_integration_and_pupil_sampling_converge():
    fit = fit_pupil(MONO, 30.0, 2.0, 0.5876)
    ref = psf_from_pupil(fit, 41, oversample=9, guard=3.0).kernel
    errors = {q: np.abs(psf_from_pupil(fit, 41, oversample=q).kernel - ref).sum() for q in (1, 3, 5)}
    assert errors[5] < 0.01 < errors[1] and errors[5] < errors[3]


def test_vignetted_fisheye_pupil_transmits_less():
    fish = get_lens("fisheye")
    on_axis, edge = fit_pupils(fish, [0.0, 60.0], 2.0, 0.5876)
    assert len(edge.apertures) > len(on_axis.apertures)  # surfaces besides the stop clip the edge pupil
    psf = psf_from_pupil(edge, 61)
    assert np.all(np.isfinite(psf.kernel))


def test_tensor_builds_only_what_is_asked_and_caches(tmp_path):
    spec = TensorSpec(field_deg=(0.0, 30.0, 60.0), depth_m=(0.7, 2.0, 10.0))
    tensor = PsfTensor(MONO, spec, cache_dir=tmp_path)
    assert tensor.ensure([2], [0]) == 1
    assert tensor.filled.sum() == 3 and tensor.filled[:, 2, 0].all()  # three channels of one entry
    again = PsfTensor(MONO, spec, cache_dir=tmp_path)
    assert again.ensure([2], [0]) == 0  # served from the disk cache
    assert np.array_equal(again.data[:, 2, 0], tensor.data[:, 2, 0])
    assert np.allclose(tensor.data[:, 2, 0].sum(axis=(1, 2)), 1.0, atol=1e-5)


def test_tensor_save_load_and_corruption(tmp_path):
    spec = TensorSpec(field_deg=(0.0, 60.0), depth_m=(0.7, 5.0))
    tensor = PsfTensor(MONO, spec, use_cache=False)
    tensor.ensure_all(workers=1)
    path = tensor.save(tmp_path / "t.npz", float16=True)
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["complete"] and meta["dtype_at_rest"] == "float16" and meta["lens"]["sha256"] == MONO.sha256()
    loaded = PsfTensor.load(path)
    assert np.abs(loaded.data - tensor.data).max() < 1e-3
    raw = bytearray(path.read_bytes())
    raw[-100] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="hash does not match"):
        PsfTensor.load(path)


def test_cli_psf_export_and_lens_json(tmp_path, bmi):
    out = tmp_path / "psf.npy"
    bmi("psf", "export", "--wavelength-nm", 486.1, "--depth-m", 0.7, "--field-deg", 60, "--out", out)
    k = np.load(out)
    assert k.shape[0] % 2 == 1 and k.shape[0] == k.shape[1] and k.sum() == pytest.approx(1.0, abs=1e-5)
    rows = np.arange(k.shape[0]) - k.shape[0] // 2
    assert abs((k.sum(axis=1) * rows).sum()) < 1e-4  # sagittally centred on the chief ray (mirror symmetry)
    report = json.loads(bmi("lens", "--json").stdout)
    for key in ("efl_mm", "epd_mm", "f_number", "petzval_radius_mm", "seidel_w040_waves"):
        assert isinstance(report[key], float)
    rows = report["wavefront"]
    assert {r["wavelength_nm"] for r in rows} == {656.3, 587.6, 486.1}
    assert any(r["depth_m"] is None for r in rows) and min(r["depth_m"] or 99 for r in rows) == 0.7
    assert set(rows[0]) >= {"wavelength_nm", "depth_m", "w020_waves", "w040_waves", "w060_waves", "rms_waves"}
    bad = bmi("psf", "export", "--wavelength-nm", 587.6, "--depth-m", -1, "--field-deg", 0, "--out", out, check=False)
    assert bad.returncode != 0 and "depth" in bad.stderr


@pytest.mark.parametrize("rotation_deg", [0.0, 12.5, 90.0, -133.5, 179.5])
def test_a_turned_pupil_polynomial_equals_the_pointwise_sum_at_the_turned_points(rotation_deg):
    """evaluate_rotated turns each fitted polynomial's coefficients once; the reference sums c_ij ξ^i η^j at every
    turned (L, M) point directly. At 60° the pupil is elliptical (l_half ≠ m_half), so the scaling is exercised."""
    fits = fit_pupils(MONO, [60.0, 10.0], [0.7, math.inf], [0.4861, 0.6563])
    for fit in fits:
        assert not math.isclose(fit.l_half, fit.m_half, rel_tol=1e-3) or fit.field_deg < 30
        half = max(fit.l_half, fit.m_half)
        u_off = np.linspace(-half, half, 37)
        v_off = np.linspace(-half, half, 41)
        names = ("w_waves", "amplitude", *fit.apertures)
        got = fit.evaluate_rotated(names, u_off, v_off, rotation_deg)
        phi = math.radians(rotation_deg)
        uu, vv = np.meshgrid(u_off, v_off, indexing="ij")
        xi = (uu * math.cos(phi) + vv * math.sin(phi)) / fit.l_half
        eta = (-uu * math.sin(phi) + vv * math.cos(phi)) / fit.m_half
        inside = xi**2 + eta**2 <= 1.3  # where the PSF reads them (outside the apertures clip to 0)
        for name, values in zip(names, got):
            c = fit.coeffs[name]
            expected = sum(c[i, j] * xi**i * eta**j for i in range(fit.degree + 1) for j in range(fit.degree + 1 - i))
            assert values.shape == (37, 41)
            assert np.abs(values - expected)[inside].max() <= 1e-11 * max(1.0, np.abs(expected[inside]).max())


@pytest.mark.parametrize("field_deg, depth_m, offset_px", [(60.0, 0.7, (0.3, -0.4)), (0.0, math.inf, (0.0, 0.0))])
def test_the_psf_equals_a_float64_debye_sum_over_the_whole_pupil_grid(field_deg, depth_m, offset_px):
    """psf_from_pupil transforms only the pupil's transmitting rectangle, in complex64 with the phase's whole waves
    taken off first. The reference: P = T·a·exp(−2πiW) in complex128 on the whole grid (T from np.gradient and
    np.hypot), the Debye sum as float64 complex exponentials at every sub-sample, the pixel box as an explicit
    average of the intensity's Fourier series. W spans 28 (60°, 0.7 m) and 81 waves (on axis, ∞)."""
    from bmi_sdk.optics.psf import _pixel_operator

    fit = fit_pupil(MONO, field_deg, depth_m, 0.5876)
    kernel_px, oversample, guard, pitch_mm = 9, 5, 1.25, 2e-3
    got = psf_from_pupil(fit, kernel_px, 2.0, oversample, guard, offset_px=offset_px)
    lam_mm = fit.wavelength_um * 1e-3
    d_l = lam_mm / (guard * kernel_px * pitch_mm)
    n_l, n_m = (2 * int(np.ceil(h / d_l)) + 1 for h in (fit.l_half, fit.m_half))
    l_off, m_off = ((np.arange(n) - n // 2) * d_l for n in (n_l, n_m))
    w = fit.evaluate("w_waves", fit.l_centre + l_off, fit.m_centre + m_off)
    assert np.ptp(w) > 20  # whole waves: the float32 phase would lose ~1e-5 rad without taking them off
    transmit = np.maximum(fit.evaluate("amplitude", fit.l_centre + l_off, fit.m_centre + m_off), 0.0)
    for name in fit.apertures:
        q = fit.evaluate(name, fit.l_centre + l_off, fit.m_centre + m_off)
        transmit *= np.clip(0.5 + (1.0 - q) / (np.hypot(*np.gradient(q)) + 1e-12), 0.0, 1.0)
    pupil = transmit * np.exp(-2j * np.pi * w)
    x = (np.arange(kernel_px * oversample) - kernel_px * oversample // 2) * pitch_mm / oversample
    k = 2 * np.pi / lam_mm
    ex = np.exp(1j * k * np.outer(x + offset_px[0] * pitch_mm, l_off))
    ey = np.exp(1j * k * np.outer(x + offset_px[1] * pitch_mm, m_off))
    intensity = np.abs(ex @ pupil @ ey.T).T ** 2
    op = _pixel_operator(kernel_px, oversample)
    expected = np.maximum(op @ intensity @ op.T, 0.0)
    expected /= expected.sum()
    assert got.pupil_samples == (n_l, n_m)
    assert np.abs(got.kernel - expected).max() <= 2e-6 * expected.max()


def test_the_moment_based_pupil_fit_equals_a_weighted_least_squares_solve():
    """``_fit_batched`` builds each entry's normal equations from moments and one batched product; the reference is
    numpy's lstsq on the explicit weighted monomial basis, per entry and per fitted column."""
    rng = np.random.default_rng(7)
    entries, rays, degree, columns = 4, 300, 10, 3
    xi, eta = rng.uniform(-1, 1, (2, entries, rays))
    weights = rng.uniform(0, 1, (entries, rays)) * (rng.uniform(size=(entries, rays)) > 0.1)
    values = rng.normal(size=(entries, rays, columns))
    coeffs, residual = _fit_batched(xi, eta, values, weights, degree)
    pairs = _pairs(degree)
    for e in range(entries):
        root_w = np.sqrt(weights[e])[:, None]
        basis = np.stack([xi[e] ** i * eta[e] ** j for i, j in pairs], axis=1)
        expected = np.linalg.lstsq(basis * root_w, values[e] * root_w, rcond=None)[0]
        got = np.stack([coeffs[e, i, j] for i, j in pairs])
        assert np.abs(got - expected).max() <= 1e-8 * np.abs(expected).max()
        assert np.allclose(residual[e], values[e, :, 0] - basis @ expected[:, 0], atol=1e-8)


def test_a_memoised_aim_gives_the_fit_a_fresh_aim_gives_whatever_the_sensor_pose():
    """Aiming depends on the lens up to its stop only: pupils of a moved sensor fitted with the aims the design's fits
    left in the memo (traced in another batch, in another order) equal those fitted one by one with the memo
    cleared, and the memoised aims carry nothing of the pose (the moved sensor's wavefront differs from the
    design's)."""
    from bmi_sdk.optics.pupil import _aim_memo, clear_aim_memo

    offset_mm = np.array([0.007, -0.005, 0.0])
    entries = ([31.0, 55.0], [1.0, 4.0], [0.55, 0.45])
    fresh = []
    for entry in zip(*entries):  # each aimed alone, from scratch
        clear_aim_memo()
        fresh += fit_pupils(MONO, *entry, sensor_offset_mm=offset_mm)
    clear_aim_memo()
    design = fit_pupils(MONO, [55.0, 10.0, 31.0], [4.0, 2.0, 1.0], [0.45, 0.65, 0.55])
    aimed = len(_aim_memo)
    memoised = fit_pupils(MONO, *entries, sensor_offset_mm=offset_mm)
    assert len(_aim_memo) == aimed == 3  # the moved sensor's fits aimed nothing new
    for a, b in zip(fresh, memoised):  # a degree-10 fit carries batch rounding at ~1e-8 in its top coefficients
        assert np.allclose(a.chief_point_mm, b.chief_point_mm, rtol=0, atol=1e-12)
        l_grid = a.l_centre + np.linspace(-a.l_half, a.l_half, 31)
        m_grid = a.m_centre + np.linspace(-a.m_half, a.m_half, 31)
        for name in ("w_waves", "amplitude", *a.apertures):
            assert np.abs(a.evaluate(name, l_grid, m_grid) - b.evaluate(name, l_grid, m_grid)).max() < 1e-6, name
        assert np.abs(psf_from_pupil(a, 41).kernel - psf_from_pupil(b, 41).kernel).sum() < 1e-6
    moved, nominal = memoised[0], design[2]
    assert np.abs(moved.coeffs["w_waves"] - nominal.coeffs["w_waves"]).max() > 1e-3
