"""The classical decoder (bmi_sdk.decode): the evidence's algebra against brute force, the refinement against an
analytic parabola, depth from a textured plane through the real renderer, extreme frames, skipped blocks,
output files, and the simulate → calibrate → infer loop with the calibrated camera's kernels."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bmi_sdk.built_camera import BuiltCamera
from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder, inverse_depth_candidates
from bmi_sdk.decode.aif import _blend, _needed, bracket
from bmi_sdk.decode.bayer import estimate_noise_sigma, normalised_planes
from bmi_sdk.decode.classical import local_spread, upsample_grid
from bmi_sdk.decode.evidence import Evidence, fold_power, folded_model, plane_nll, rfft_multiplicity
from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.nn.data import simulate_raw
from bmi_sdk.optics.perturb import Perturbation
from bmi_sdk.render import PsfMap, render_coded
from bmi_sdk.scenes import generate_scene
from bmi_sdk.sensor import NoiseProfile, relative_illumination

BLACK, WHITE = 256, 4095
GEOMETRY = lens_geometry("bmi_monocentric")


def test_fold_is_the_spectrum_of_the_four_bayer_planes():
    """Σ over the four 2×-subsampled planes of |DFT_n|² = ¼ Σ over the four aliases of |DFT_2n|² (exact)."""
    rng = np.random.default_rng(0)
    n = 16
    z = rng.standard_normal((2 * n, 2 * n))
    planes = sum(np.abs(np.fft.rfft2(z[r::2, c::2])) ** 2 for r in (0, 1) for c in (0, 1))
    folded = fold_power(np.abs(np.fft.fft2(z)) ** 2, n)[:, :n // 2 + 1]
    assert np.allclose(planes, folded / 4, rtol=1e-10, atol=1e-9)


def _near_kernel_planes(floor_cycles: float, fields: int) -> tuple[np.ndarray, list]:
    """(kernel, planes): Gaussian fields with a 1/f² spectrum floored at ``floor_cycles``, blurred by the camera's
    near kernel (0.8 m on axis: its OTF oscillates about once per bin of a 64-px window), each sampled as a Bayer
    plane (256² of a 512² field)."""
    from scipy import fft as sfft

    from bmi_sdk.decode.evidence import power_law_prior

    psf_map = PsfMap(lens_tensor("bmi_monocentric"), GEOMETRY, mode="tensor")
    kernel = psf_map.kernels(0.0, 0.0, np.array([int(np.argmin(np.abs(psf_map.tensor.depth_m - 0.8)))]))[1, 0]
    n, k = 512, kernel.shape[0]
    f = sfft.fftfreq(n)
    otf = np.zeros((n, n))
    otf[:k, :k] = kernel
    otf = sfft.fft2(np.roll(otf, (-(k // 2), -(k // 2)), (0, 1)))
    rng = np.random.default_rng(4)
    planes = []
    for _ in range(fields):
        field = sfft.ifft2(sfft.fft2(rng.standard_normal((n, n))) * np.sqrt(power_law_prior(f, f, floor_cycles))
                           * otf).real
        planes.append(field[::2, ::2])
    return kernel, planes


def _near_kernel_periodogram(floor_cycles: float, fields: int) -> tuple[np.ndarray, np.ndarray]:
    """(kernel, mean periodogram) of ``_near_kernel_planes`` cut into Hann windows of 32 samples, stride 16."""
    from bmi_sdk.decode.evidence import hann_taper, window_spectra

    kernel, planes = _near_kernel_planes(floor_cycles, fields)
    spectra = [window_spectra(plane.astype(np.float32), 32, 16, hann_taper(32))[0] for plane in planes]
    return kernel, np.concatenate(spectra).mean(axis=0)


def test_tapered_model_is_the_expected_periodogram_of_a_blurred_1_over_f2_field():
    """Monte Carlo: a Gaussian field with the prior's 1/f² spectrum (floored at one window bin), blurred by the
    camera's near kernel, sampled as a Bayer plane and cut into Hann windows (``_near_kernel_periodogram``). The
    mean periodogram matches the taper-smoothed model bin by bin (p95 within 5 %); the unsmoothed spectrum misses
    by up to an order of magnitude near the OTF's zeros."""
    from scipy import fft as sfft

    from bmi_sdk.decode.evidence import power_law_prior

    kernel, mean = _near_kernel_periodogram(1 / 64, 8)
    k = kernel.shape[0]
    used = rfft_multiplicity(32) > 0

    def misfit(model):
        ratio = np.log(mean[used] / model[used])
        return np.abs(ratio - np.median(ratio))

    assert np.percentile(misfit(folded_model(kernel[None], 32)[0]), 95) < 0.05
    full = np.zeros((64, 64))  # the unsmoothed model: Σ_aliases |K|² S on the plane's bins
    full[:k, :k] = kernel
    f64 = sfft.fftfreq(64)
    unsmoothed = fold_power(np.abs(sfft.fft2(full)) ** 2 * power_law_prior(f64, f64, 1 / 64), 32)[:, :17]
    assert misfit(unsmoothed).max() > 1.5


def test_the_exact_model_is_the_expected_periodogram_down_to_dcs_neighbours():
    """Monte Carlo as above, the field's 1/f² floored at one bin of the exact model's oversampled grid (1/256
    cycles/px), so the window's lowest frequencies carry the prior's full power and its mean removal matters. The
    exact expected periodogram matches the mean periodogram on every bin but DC (p95 within 5 %), DC's eight
    neighbours included; the taper-smoothed model, which does not hold the mean's removal, misses those by > 20 %
    (which is why the likelihood leaves them out of it, ``rfft_multiplicity``)."""
    from bmi_sdk.decode.evidence import expected_periodogram

    kernel, mean = _near_kernel_periodogram(1 / 256, 16)
    bins = np.ones(mean.shape, bool)
    bins[0, 0] = False
    dc_neighbours = (rfft_multiplicity(32) == 0) & bins

    def misfit(model):
        ratio = np.log(mean[bins] / model[bins])
        return np.abs(ratio - np.median(ratio)), np.abs(np.log(mean[dc_neighbours] / model[dc_neighbours])
                                                        - np.median(ratio))

    exact_all, exact_dc = misfit(expected_periodogram(kernel[None], 32)[0])
    assert np.percentile(exact_all, 95) < 0.05 and exact_dc.max() < 0.08
    assert misfit(folded_model(kernel[None], 32)[0])[1].max() > 0.2


def test_a_window_with_clipped_samples_left_out_has_its_masked_tapers_expected_periodogram():
    """Monte Carlo as above (the near kernel, 1/f² floored at one bin of the exact model's grid): every window loses
    the same samples, a disc off its centre and two lone ones, as a clipped highlight and noise spikes over white
    would take them. Their mean periodogram with those samples weighted out (``masked_window`` under the taper times
    ``clipped_weights``, the mean removed under it) matches the exact expected periodogram under that taper on every
    bin but DC (p95 within 5 %). The Hann taper's model, and a hard hole's, miss it by more: a taper with holes
    passes power from the field's strong low frequencies, and the mean's removal, into every bin."""
    from bmi_sdk.decode.clipped import clipped_weights, masked_window
    from bmi_sdk.decode.evidence import hann_taper, plane_autocovariance, taper_terms, tapered_periodogram

    kernel, planes = _near_kernel_planes(1 / 256, 16)
    yy, xx = np.mgrid[:32, :32]
    clipped = (yy - 12) ** 2 + (xx - 20) ** 2 < 3 ** 2
    clipped[25, 6] = clipped[4, 9] = True
    taper = hann_taper(32)
    masked_taper = taper * clipped_weights(clipped, 8.0).astype(np.float64)
    powers, energies = [], []
    for plane in planes:
        for r in range(0, 256 - 32 + 1, 16):
            for c in range(0, 256 - 32 + 1, 16):
                power, energy, _ = masked_window(plane[r:r + 32, c:c + 32], masked_taper, taper)
                powers.append(power)
                energies.append(energy)
    assert np.allclose(energies, float((masked_taper ** 2).sum()), rtol=1e-9)
    mean = np.mean(powers, axis=0)
    bins = np.ones(mean.shape, bool)
    bins[0, 0] = False
    r = plane_autocovariance(kernel[None], 32)

    def misfit(model):  # the shape only: the prior's level is a free parameter of the likelihood
        ratio = np.log(mean[bins] / model[bins])
        return np.abs(ratio - np.median(ratio))

    assert np.percentile(misfit(tapered_periodogram(r, taper_terms(masked_taper))[0]), 95) < 0.05
    assert np.percentile(misfit(tapered_periodogram(r, taper_terms(taper))[0]), 95) > 0.1
    hard_hole = np.where(clipped, 0.0, taper)
    assert np.percentile(misfit(tapered_periodogram(r, taper_terms(hard_hole))[0]), 95) > 0.1
    assert masked_window(plane[:32, :32], taper * clipped_weights(yy < 24, 8.0), taper) is None  # too little is left


@pytest.mark.parametrize("depth_m", [1.7, 3.4])
def test_the_laplace_sigma_is_the_spread_of_the_estimate_on_data_drawn_from_the_model(depth_m):
    """Monte Carlo: 1/f² Gaussian fields blurred by one of the candidates' kernels, a Bayer plane with white noise,
    cut into 1536 independent Hann windows; each is decoded by the evidence alone (β profiled, parabola in 1/d).
    The spread of the estimates is the reported Laplace σ (the likelihood's curvature times the taper's
    inflation) to within 20 %. Without the likelihood's ½ and the inflation it would be 2.75× too small."""
    from scipy import fft as sfft

    from bmi_sdk.decode.evidence import hann_taper, power_law_prior, taper_variance_inflation, window_spectra

    tensor = lens_tensor("bmi_monocentric")
    candidates = inverse_depth_candidates(tensor.depth_m, 48)
    kernels = PsfMap(tensor, GEOMETRY, mode="tensor").kernels(0.0, 0.0, candidates.index)[1]
    true = int(np.argmin(np.abs(candidates.depth_m - depth_m)))
    models = folded_model(kernels, 32)
    n, k = 1024, kernels.shape[-1]
    f = sfft.fftfreq(n)
    otf = np.zeros((n, n))
    otf[:k, :k] = kernels[true]
    otf = sfft.fft2(np.roll(otf, (-(k // 2), -(k // 2)), (0, 1)))
    taper = hann_taper(32)
    rng = np.random.default_rng(1)
    estimates, sigmas = [], []
    for _ in range(6):
        field = 0.02 * sfft.ifft2(sfft.fft2(rng.standard_normal((n, n))) * np.sqrt(power_law_prior(f, f, 1 / 64))
                                  * otf).real
        plane = (field[::2, ::2] + 0.005 * rng.standard_normal((n // 2, n // 2))).astype(np.float32)
        spectra = window_spectra(plane, 32, 32, taper)[0]
        nll = plane_nll(spectra.reshape(-1, 32, 17), models, 0.005 ** 2, float((taper ** 2).sum()))
        depth, sigma_inv, _ = Evidence(nll, candidates.inv_depth_per_m).refine()
        estimates.append(1.0 / depth)
        sigmas.append(sigma_inv * np.sqrt(taper_variance_inflation(taper)))
    error = np.concatenate(estimates) - candidates.inv_depth_per_m[true]
    ratio = error.std() / np.sqrt(np.mean(np.concatenate(sigmas) ** 2))
    assert abs(error.mean()) < 0.2 * error.std()
    assert 0.8 < ratio < 1.2
    assert taper_variance_inflation(taper) == pytest.approx((35 / 18) ** 2, rel=1e-6)


def test_inverse_depth_information_is_the_curvature_of_the_expected_likelihood():
    """For an analytic model family A_u(ω) (a Gaussian OTF whose width grows with u = 1/d), the information is the
    Hessian of the expected NLL ½ Σ m (V₀/V + log V) in (u, log β') at the truth, β' profiled out (its Schur
    complement), taken here by finite differences."""
    from bmi_sdk.decode.evidence import inverse_depth_information

    n = 32
    fr = np.fft.fftfreq(n)[:, None]
    fc = np.fft.rfftfreq(n)[None, :]
    f2 = fr ** 2 + fc ** 2

    def model(u):
        return np.exp(-f2 * (6.0 * u) ** 2) / (f2 + 1.0 / n ** 2)

    mult = rfft_multiplicity(n)
    u0, beta0 = 0.5, 30.0

    def expected_nll(u, log_beta):
        v0, v = beta0 * model(u0) + 1.0, np.exp(log_beta) * model(u) + 1.0
        return 0.5 * float((mult * (v0 / v + np.log(v))).sum())

    du, db = 1e-3, 1e-3
    x0 = (u0, np.log(beta0))
    f = lambda a, b: expected_nll(x0[0] + a, x0[1] + b)  # noqa: E731
    h_uu = (f(du, 0) - 2 * f(0, 0) + f(-du, 0)) / du ** 2
    h_bb = (f(0, db) - 2 * f(0, 0) + f(0, -db)) / db ** 2
    h_ub = (f(du, db) - f(du, -db) - f(-du, db) + f(-du, -db)) / (4 * du * db)
    grid = u0 + np.linspace(-2e-3, 2e-3, 5)
    got = inverse_depth_information(np.stack([model(u) for u in grid]), grid, beta0)[2]
    assert got == pytest.approx(h_uu - h_ub ** 2 / h_bb, rel=1e-3)
    assert got < h_uu  # an unknown contrast costs information


def test_the_window_bound_is_the_relative_spread_of_a_far_planes_window_depths():
    """``bench.decoder.window_depth_bound`` is σ_d / d of one window: a 1/f² plane blurred (periodically) by the
    50° zone's exact kernels of the candidate nearest 7.8 m, standard noise, cut into 64 independent windows, each
    read by the evidence alone; their relative depth errors scatter by the bound to within 25 %. The decoder reads
    far planes at the bound (a bench table once divided the bound by d again, and the docs read 5× excess)."""
    from bmi_sdk.bench.decoder import window_depth_bound, window_depths, zone_plane_raw
    from bmi_sdk.decode.kernels import ZoneKernels

    decoder = ClassicalDecoder.for_psf_map(PsfMap(lens_tensor("bmi_monocentric"), GEOMETRY, mode="exact"),
                                           ClassicalConfig())
    cand, zone = decoder.candidates, ZoneKernels.zone(50.0, 30.0)
    raw, true = zone_plane_raw(decoder, zone, 7.8, 512, seed=3)
    depth = window_depths(decoder, raw, [zone])[0]
    relative_spread = np.std(depth / cand.depth_m[true] - 1.0)
    bound = window_depth_bound(decoder, raw, 0, 0, 50.0, float(cand.depth_m[true]))
    assert len(depth) == 64 and 0.75 < relative_spread / bound < 1.33


def _hann_bank_spectra(widths, true_index: int, windows: int, n: int, seed: int):
    """(models, window powers, taper energy, noise variance): centred separable Hann kernels of ``widths`` (19² px)
    folded for n-sample windows, and the periodograms of ``windows`` windows drawn from the model of kernel
    ``true_index`` (β 3e-3, noise variance 1e-4: exponential bins around the expected power)."""
    kernels = np.zeros((len(widths), 19, 19))
    for d, width in enumerate(widths):
        w = np.hanning(width + 2)[1:-1]
        lo = (19 - width) // 2
        kernels[d, lo:lo + width, lo:lo + width] = np.outer(w, w) / np.outer(w, w).sum()
    model = folded_model(kernels, n)
    taper_energy, noise_var = 100.0, 1e-4
    v_true = 3e-3 * model[true_index] * taper_energy + noise_var * taper_energy
    power = (v_true * np.random.default_rng(seed).exponential(size=(windows,) + v_true.shape)).astype(np.float32)
    return model, power, taper_energy, noise_var


def test_plane_nll_equals_the_brute_force_profile_over_beta():
    """β profiled on the grid + parabola agrees with a dense brute-force minimum of the exact NLL (to 0.5 nats)
    for the kernel that made the data; for a wrong kernel whose best β lies past the grid it is an upper bound."""
    n = 16
    model, power, taper_energy, noise_var = _hann_bank_spectra((7, 19), true_index=0, windows=5, n=n, seed=1)
    got = plane_nll(power, model, noise_var, taper_energy)
    mult = rfft_multiplicity(n)
    for w in range(5):
        for d in range(2):
            v = np.exp(np.linspace(-16, 2, 4001))[:, None, None] * model[d] * taper_energy + noise_var * taper_energy
            brute = 0.5 * (mult * (power[w] / v + np.log(v))).sum(axis=(1, 2)).min()  # a real field's NLL
            if d == 0:
                assert got[w, d] == pytest.approx(brute, abs=0.5)
            else:
                assert got[w, d] > brute - 0.5
    assert np.all(got[:, 0] < got[:, 1])  # the kernel that made the data wins


def test_the_skipped_low_bins_are_those_within_that_many_cycles_of_dc_on_both_axes():
    """``rfft_multiplicity``: 1 cycle skips DC and its 8 neighbours (the rfft's 6 bins of them), 2 cycles (a weakly
    textured window's, ``WEAK_TEXTURE_LOW_CYCLES``) the 5 × 5 block about DC (15 rfft bins); every other bin keeps its
    multiplicity. A value outside [1, n/4] is refused."""
    full = rfft_multiplicity(32, 1) + (rfft_multiplicity(32, 1) == 0) * 2.0
    full[:, [0, -1]] = 1.0
    for cycles, dropped in ((1, 6), (2, 15), (8, 9 * 17)):
        m = rfft_multiplicity(32, cycles)
        ky = np.minimum(np.arange(32), 32 - np.arange(32))[:, None]
        kx = np.arange(17)[None, :]
        near = np.maximum(ky, kx) <= cycles
        assert int((m == 0).sum()) == dropped and np.all(m[near] == 0)
        np.testing.assert_array_equal(m[~near], full[~near])
    for bad in (0, 9, 1.5, True, -1):
        with pytest.raises(ValueError, match="low_cycles_skipped must be an integer in \\[1, 8\\]"):
            rfft_multiplicity(32, bad)


def test_shading_of_one_cycle_per_window_leaves_the_evidence_unchanged_when_two_cycles_are_skipped():
    """A smooth shading across each window (one cosine cycle per window, 6× the texture's amplitude) is not the
    texture the prior describes. Through the window's periodic Hann taper it lands in the bins within 2 cycles of DC
    alone, so skipping 2 cycles (a weakly textured window's) scores the shaded windows exactly as the unshaded ones,
    to float32 rounding, while skipping 1 lets it move their NLLs by nats (β's profile absorbs part of it)."""
    from bmi_sdk.decode.evidence import hann_taper, window_spectra

    n = 16
    model, _, taper_energy, noise_var = _hann_bank_spectra((5, 9, 13), true_index=1, windows=1, n=n, seed=2)
    rng = np.random.default_rng(8)
    texture = rng.normal(0.0, 0.05, (4 * n, 4 * n)).astype(np.float32)
    shading = (0.3 * np.cos(2.0 * np.pi * np.arange(4 * n) / n))[None, :].astype(np.float32)
    taper = hann_taper(n)
    plain, shaded = (window_spectra(p, n, n // 2, taper)[0] for p in (texture, texture + shading))
    for cycles, moved in ((2, False), (1, True)):
        a, b = (plane_nll(x, model, noise_var, taper_energy, low_cycles_skipped=cycles) for x in (plain, shaded))
        if moved:
            assert np.median(np.abs(b - a)) > 2.0
        else:
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-2)


def test_a_windows_texture_contrast_is_its_textures_rms_over_its_mean_and_a_blur_takes_its_sharpness():
    """``texture_bands`` on white textures of known contrast (RMS 0.05 of a mean 0.4) under noise of σ 0.01: a
    tapered periodogram's expected power is Σt² (texture variance + noise variance) at every bin away from DC, so
    the band's power less the noise, over the mean, reads the contrast (median over the windows within 3 %), and a
    white texture's upper band holds as much power per bin as its contrast band (sharpness 1). Three times the
    exposure (signal and noise σ alike) reads the same; a Gaussian blur of σ 3 samples empties the upper band
    (sharpness near 0); a window of no signal is never weak."""
    from scipy.ndimage import gaussian_filter

    from bmi_sdk.decode.evidence import hann_taper, texture_bands, window_spectra

    n, contrast, mean, sigma = 32, 0.05, 0.4, 0.01
    taper = hann_taper(n)
    energy = float((taper ** 2).sum())
    rng = np.random.default_rng(11)
    fields = [rng.normal(0.0, 1.0, (2, 160, 160)) for _ in range(4)]

    def read(exposure: float, blur: float = 0.0) -> tuple:
        planes = [exposure * (mean * (1 + contrast * (gaussian_filter(t, blur) / gaussian_filter(t, blur).std()
                                                       if blur else t)) + sigma * e) for t, e in fields]
        windows = [window_spectra(p.astype(np.float32), n, n // 4, taper) for p in planes]
        return texture_bands([w[0] for w in windows], [w[1] for w in windows],
                             [np.full(len(w[1]), (exposure * sigma) ** 2) for w in windows], energy)

    got, sharpness = read(1.0)
    assert got.shape == (17 * 17,) and np.median(got) == pytest.approx(contrast, rel=0.03)
    assert np.median(sharpness) == pytest.approx(1.0, abs=0.1)
    np.testing.assert_allclose(read(3.0)[0], got, rtol=1e-4)
    assert np.median(read(1.0, blur=3.0)[1]) < 0.02
    dark = texture_bands([np.ones((1, n, n // 2 + 1), np.float32)] * 4, [np.zeros(1)] * 4, [np.zeros(1)] * 4,
                         energy)
    assert np.all(np.isinf(dark[0]))


def test_a_candidates_nll_on_a_shared_beta_grid_does_not_depend_on_the_other_candidates_scored():
    """The fine pass scores a few candidates on the coarse pass's β grid (``grid_model``): each candidate's NLL
    is then what it was when scored beside the coarse set, to the float32 product's rounding (BLAS splits a
    product of another width differently on some processors), so the two passes' NLLs form one curve; a grid
    placed by other candidates moves them by tenths of a nat."""
    model, power, taper_energy, noise_var = _hann_bank_spectra((5, 9, 13, 17, 19), true_index=2, windows=6, n=16,
                                                               seed=5)
    coarse = model[[0, 2, 4]]
    together = plane_nll(power, model, noise_var, taper_energy, grid_model=coarse)
    alone = [plane_nll(power, model[[d]], noise_var, taper_energy, grid_model=coarse)[:, 0] for d in range(5)]
    np.testing.assert_allclose(np.stack(alone, axis=1), together, rtol=0, atol=1e-4)
    np.testing.assert_allclose(together[:, [0, 2, 4]], plane_nll(power, coarse, noise_var, taper_energy), rtol=0,
                               atol=1e-4)
    # without the shared grid a candidate scored alone sits on a grid of its own: another number
    assert np.abs(plane_nll(power, model[[1]], noise_var, taper_energy)[:, 0] - together[:, 1]).max() > 1e-3


def test_plane_nll_with_per_window_noise_equals_the_brute_force_with_each_windows_own_noise():
    """Signal-dependent noise: windows of one block whose noise variances differ by 100× (dark and bright regions
    under shot noise) each get the brute-force profile NLL of their own variance, within the grouping's ±5 %
    (which moves the NLL by far less than a nat here) and the β parabola's 0.5 nats."""
    rng = np.random.default_rng(2)
    n = 16
    w = np.hanning(11)[1:-1]
    kernel = np.zeros((1, 19, 19))
    kernel[0, 5:14, 5:14] = np.outer(w, w) / np.outer(w, w).sum()
    model = folded_model(kernel, n)
    taper_energy = 100.0
    noise_var = np.repeat([1e-5, 3e-5, 1e-4, 1e-3], 3) * rng.uniform(0.97, 1.03, 12)
    v_true = (3e-3 * model[0] + noise_var[:, None, None]) * taper_energy
    power = (v_true * rng.exponential(size=v_true.shape)).astype(np.float32)
    got = plane_nll(power, model, noise_var, taper_energy)
    mult = rfft_multiplicity(n)
    for k in range(12):
        v = (np.exp(np.linspace(-16, 2, 4001))[:, None, None] * model[0] + noise_var[k]) * taper_energy
        brute = 0.5 * (mult * (power[k] / v + np.log(v))).sum(axis=(1, 2)).min()
        assert got[k, 0] == pytest.approx(brute, abs=0.5)
    # one value for every window is the scalar call
    assert np.allclose(plane_nll(power, model, np.full(12, 1e-4), taper_energy), plane_nll(power, model, 1e-4, taper_energy))


def test_the_noise_the_evidence_uses_given_then_profile_then_estimated():
    from bmi_sdk.decode.classical import frame_noise
    from bmi_sdk.sensor import NoiseProfile

    planes = np.random.default_rng(3).normal(0.3, 0.01, (4, 64, 64)).astype(np.float32)
    profile = NoiseProfile(2e-4, 1e-6)
    assert frame_noise(ClassicalConfig(noise_sigma=0.02), planes, profile) == (NoiseProfile(0.0, 0.02 ** 2), "given")
    assert frame_noise(ClassicalConfig(), planes, profile) == (profile, "profile")
    estimated, source = frame_noise(ClassicalConfig(), planes, None)
    assert source == "estimated" and estimated.scale == 0 and np.sqrt(estimated.offset) == pytest.approx(0.01, rel=0.2)
    for bad in ("estimate", "guess"):  # a profile present is always used
        with pytest.raises(ValueError, match="noise_model"):
            ClassicalConfig(noise_model=bad)
    with pytest.raises(ValueError, match="window_model"):
        ClassicalConfig(window_model="untapered")


def test_refinement_recovers_an_analytic_parabola_on_uneven_candidates():
    inv = np.array([1.4, 1.2, 1.0, 0.9, 0.6, 0.3, 0.1])     # 1/d, uneven steps
    x0, sigma = 0.72, 0.05
    nll = (inv - x0) ** 2 / (2 * sigma ** 2) + 7.0
    depth, sigma_inv, best = Evidence(nll[None, None], inv).refine()
    assert best[0, 0] == 4
    assert depth[0, 0] == pytest.approx(1 / x0, rel=1e-9)
    assert sigma_inv[0, 0] == pytest.approx(sigma, rel=1e-9)


def test_candidates_are_even_in_inverse_depth_and_on_the_grid():
    grid = np.round(0.7 + np.arange(94) * 0.1, 6)
    cands = inverse_depth_candidates(grid, 48)
    assert cands.depth_m[0] == 0.7 and cands.depth_m[-1] == pytest.approx(9.9 + 0.1, abs=1e-6)
    assert np.all(np.diff(cands.depth_m) > 0) and np.all(np.isin(cands.depth_m, grid))
    assert np.array_equal(grid[cands.index], cands.depth_m)
    steps = -np.diff(cands.inv_depth_per_m)
    assert steps[-5:].max() < 0.1  # far end: about (1/0.7 − 1/10)/47, snapped to 0.1 m steps
    with pytest.raises(ValueError, match="at least 3"):
        inverse_depth_candidates(grid, 2)


def test_bracket_blends_neighbouring_candidates_linearly_in_inverse_depth():
    cand_inv = 1 / np.array([1.0, 2.0, 4.0])
    lo, frac = bracket(np.array([1.0, 0.75, 0.25, 2.0, 0.1]), cand_inv)
    assert lo.tolist() == [0, 0, 1, 0, 1] and frac == pytest.approx([0.0, 0.5, 1.0, 0.0, 1.0])


def test_blend_gathers_each_pixels_two_candidates_as_the_hat_weights_say():
    """``aif._blend`` (each pixel's two candidates gathered from only the needed ones) against the plain sum over
    every candidate of its hat weight in 1/d: pixels on a candidate, between two, and beyond both ends; a
    strided view as the AiF passes it."""
    rng = np.random.default_rng(7)
    cand_inv = 1 / np.array([0.8, 1.0, 1.5, 2.5, 4.0, 9.0])
    inv = rng.choice([1 / 1.0, 1 / 2.5, 1 / 9.0, 2.0, 0.05], (9, 11)) + rng.choice([0.0, 0.0, -0.1], (9, 11))
    lo, frac = bracket(inv, cand_inv)
    needed = _needed(lo, frac, len(cand_inv))
    values = rng.standard_normal((len(cand_inv), 3, 12, 14)).astype(np.float32)
    view = values[needed][..., 1:10, 2:13]  # each needed candidate's planes, cut as a block's core is
    hat = np.stack([np.interp(-np.clip(inv, cand_inv[-1], cand_inv[0]), -cand_inv, np.eye(len(cand_inv))[j])
                    for j in range(len(cand_inv))])  # (candidates, h, w): each candidate's weight at each pixel
    expected = np.einsum("jhw,jchw->hwc", hat, values[..., 1:10, 2:13])
    assert set(needed.tolist()) == set(np.flatnonzero(hat.reshape(len(cand_inv), -1).max(axis=1) > 0).tolist())
    assert np.allclose(_blend(view, lo, frac, needed), expected, atol=1e-6)


def test_noise_estimate_on_a_blurred_frame():
    rng = np.random.default_rng(2)
    clean = np.repeat(np.repeat(rng.random((40, 40)), 4, 0), 4, 1)  # piecewise constant: mostly flat blocks
    raw = np.clip(np.rint(BLACK + (clean * 0.5 + 0.2 + rng.normal(0, 0.01, clean.shape)) * (WHITE - BLACK)),
                  0, WHITE).astype(np.uint16)
    assert estimate_noise_sigma(normalised_planes(raw, BLACK, WHITE)) == pytest.approx(0.01, rel=0.2)


def test_spread_and_upsampling_of_the_window_grid():
    grid = np.zeros((5, 5))
    grid[:, 3:] = 1.0
    spread = local_spread(grid)
    assert spread[2, 0] == 0.0 and spread[2, 2] == pytest.approx(np.sqrt(2 / 9), rel=1e-9)
    up = upsample_grid(np.array([[1.0, 3.0], [np.nan, 3.0]]), 16, 24, 24)
    # sample k sits at pixel k·16 − ½, so pixel x reads grid position (x + ½) / 16
    assert up[0, 7] == pytest.approx(1.0 + 2.0 * (7.5 / 16), abs=1e-6) and np.isfinite(up).all()
    assert up[0, 16] == pytest.approx(3.0, abs=1e-6) and up[0, 0] == pytest.approx(1.0 + 2.0 * 0.5 / 16, abs=1e-6)


def test_the_refinement_channels_of_any_tile_are_the_whole_windows_channels_there():
    """The learned decoder makes a frame's channels tile by tile (``FeatureTiles``): every tile, those that reach
    past the frame and read it mirrored included, must hold bit for bit what the whole window's channels hold at
    the same pixels, and a grid upsampled over part of a frame must equal that part of the whole upsampling."""
    from bmi_sdk.decode.classical import DecodeResult
    from bmi_sdk.decode.features import FeatureTiles, refinement_features
    from bmi_sdk.model_io import reflect_indices

    rng = np.random.default_rng(5)
    h, w, stride = 100, 132, 16
    grid_shape = (-(-h // stride) + 1, -(-w // stride) + 1)
    grid = rng.random(grid_shape)
    grid[0, :3] = np.nan  # a skipped block
    full = upsample_grid(grid, stride, h, w)
    assert np.array_equal(upsample_grid(grid, stride, 37, 51, 29, 70), full[29:66, 70:121])
    valid = np.ones((h, w), bool)
    valid[:9, :20] = False
    depth = np.where(valid, 1.0 + 5.0 * rng.random((h, w)), np.nan).astype(np.float32)
    evidence = (rng.random(grid_shape + (4,)) * 30.0).astype(np.float32)
    evidence[1, 1] = np.nan
    result = DecodeResult(depth, (0.1 * depth).astype(np.float32), rng.random((h, w, 3)).astype(np.float32) * 2.5,
                          valid, grid, grid, grid, grid, evidence, np.arange(4.0))
    whole = refinement_features(result, stride)
    tiles = FeatureTiles(result, stride)
    assert whole.shape == (tiles.count, h, w) and np.isfinite(whole).all() and (whole[:, ~valid] == 0).all()
    for r, c, size in ((0, 0, 64), (-20, 90, 64), (60, -30, 48), (40, 40, 32)):
        rows, cols = reflect_indices(r, size, h), reflect_indices(c, size, w)
        assert np.array_equal(tiles.gather(rows, cols), whole[np.ix_(np.arange(tiles.count), rows, cols)])


def _plane_frame(depth_m: float, field_deg: float, size: int = 160, sigma: float = 0.005, texture: str = "scene",
                 psf_mode: str = "tensor"):
    """A fronto-parallel plane at ``depth_m`` rendered at ``field_deg`` (φ 30°), textured by ``bench.decoder``'s
    ``plane_texture`` ("scene": a procedural scene's picture; "pink": a 1/f² field, the issue's textured plane),
    with the rotated tensor kernels or a lens's exact ones (``psf_mode``)."""
    from bmi_sdk.bench.decoder import plane_texture

    tensor = lens_tensor("bmi_monocentric")
    rgb = plane_texture(size + 48, texture, np.random.default_rng(3))
    r, c = GEOMETRY.pixel_of_field(field_deg, 30.0)
    row0, col0 = int(r - size / 2) // 2 * 2, int(c - size / 2) // 2 * 2
    psf_map = PsfMap(tensor, GEOMETRY, mode=psf_mode)
    optical = render_coded(rgb, np.full((size + 48, size + 48), depth_m, np.float32), tensor, GEOMETRY,
                           row0 - 24, col0 - 24, psf_map=psf_map)[24:-24, 24:-24]
    optical *= relative_illumination(GEOMETRY, row0, col0, size, size)[..., None]
    return simulate_raw(optical, sigma, np.random.default_rng(4), row0, col0), row0, col0, psf_map, rgb


@pytest.fixture(scope="module")
def nominal_decoder():
    psf_map = PsfMap(lens_tensor("bmi_monocentric"), GEOMETRY, mode="tensor")
    return ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig())


@pytest.mark.parametrize("depth_m, field_deg", [(1.0, 0.0), (2.0, 10.0), (4.0, 50.0)])
def test_a_textured_plane_decodes_within_five_percent(nominal_decoder, depth_m, field_deg):
    """The physics end to end: a 1/f²-textured plane rendered through the real renderer, decoded from the raw Bayer
    frame with the camera's noise. 1 m on axis is the largest kernel (~41 px in a 64-px window): its OTF
    oscillates about once per bin, and without the taper's smoothing of the model it read at AbsRel 0.16."""
    raw, row0, col0, _, _ = _plane_frame(depth_m, field_deg, texture="pink")
    out = nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
    absrel = np.mean(np.abs(out.depth_m[out.valid] - depth_m) / depth_m)
    assert out.valid.all() and absrel < 0.05
    assert np.all(np.isfinite(out.depth_sigma_m)) and np.all(out.depth_sigma_m > 0)
    assert out.stats["blocks_run"] == 1 and out.stats["noise_source"] == "profile"
    assert out.stats["noise_sigma"] == pytest.approx(0.005, rel=0.01)
    assert out.aif.shape == (160, 160, 3) and np.all(np.isfinite(out.aif))


@pytest.mark.parametrize("depth_m, field_deg", [(1.0, 0.0), (4.0, 50.0)])
def test_a_textured_plane_scored_with_the_exact_model_decodes_within_five_percent(depth_m, field_deg):
    """The same planes with every window scored by the exact expected periodogram (``exact_model_below`` 1), and
    with half the windows by it (the gate between the two models at the frame's median signal): each reads the
    plane as well, so neither model nor the split between them biases depth."""
    raw, row0, col0, psf_map, _ = _plane_frame(depth_m, field_deg, texture="pink")
    planes = raw.astype(np.float64) / WHITE
    for gate in (1.0, float(np.median(planes))):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(exact_model_below=gate))
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
        absrel = np.mean(np.abs(out.depth_m[out.valid] - depth_m) / depth_m)
        assert out.valid.all() and absrel < 0.05, (gate, absrel)
        assert np.all(np.isfinite(out.depth_sigma_m)) and np.all(out.depth_sigma_m > 0)
    with pytest.raises(ValueError, match="exact_model_below"):
        ClassicalConfig(exact_model_below=-0.1)
    with pytest.raises(ValueError, match="exact_model_below"):
        ClassicalConfig(exact_model_below=float("nan"))


def test_a_dark_walls_bias_is_halved_by_the_exact_model():
    """A dark, faint 1/f² wall (mean 0.05 of white, contrast 0.22) at 2.3 m on axis, σ 0.005: at this signal-to-noise
    ratio only its lowest frequencies carry signal, where the tapered model's approximations (no mean removal, the
    prior floored at one bin) pull the read near, by about 12 % (median window read). The exact expected periodogram
    (``exact_model_below``) reads it within about 6 %."""
    from bmi_sdk.scenes.procedural import pink_noise

    tensor = lens_tensor("bmi_monocentric")
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    n, margin, depth_m = 384, 48, 2.3
    row0, col0 = 2250 - n // 2, 3000 - n // 2
    texture = np.clip(0.05 * (1 + 0.22 * pink_noise((n, n), np.random.default_rng(3))), 0, 1)
    optical = render_coded(np.repeat(texture[..., None], 3, axis=2).astype(np.float32),
                           np.full((n, n), depth_m, np.float32), tensor, GEOMETRY, row0, col0, psf_map=psf_map)
    t = n - 2 * margin
    raw = simulate_raw(optical[margin:margin + t, margin:margin + t], 0.005, np.random.default_rng(1),
                       row0 + margin, col0 + margin)
    bias = {}
    for gate in (0.0, 1.0):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(exact_model_below=gate))
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0 + margin, col0 + margin,
                             noise_profile=NoiseProfile.additive(0.005), aif=False)
        bias[gate] = abs(float(np.nanmedian(1.0 / out.grid_inv_depth)) / depth_m - 1.0)
    assert bias[0.0] > 0.08 and bias[1.0] < 0.6 * bias[0.0], bias


def _shaded_wall_raw(contrast: float, seed: int = 0):
    """(raw, row0, col0, psf_map, truth_m): a 1/f² wall of mean 0.3 and texture ``contrast`` at 3 m, 20° of field,
    under a smooth shading (1 + 0.3 cos, period 200 px: a lamp's falloff across a wall), 336² px at σ 0.005
    (``bench.decoder.window_raw``)."""
    from bmi_sdk.bench.decoder import window_raw
    from bmi_sdk.scenes.procedural import pink_noise

    tensor = lens_tensor("bmi_monocentric")
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    n, depth_m = 384, 3.0
    shading = 1.0 + 0.3 * np.cos(2.0 * np.pi * np.arange(n) / 200.0)[None, :]
    wall = np.clip(0.3 * (1.0 + contrast * pink_noise((n, n), np.random.default_rng(seed))) * shading, 0, 1)
    raw, row0, col0 = window_raw(np.repeat(wall[..., None], 3, axis=2).astype(np.float32),
                                 np.full((n, n), depth_m, np.float32), tensor, GEOMETRY, 20.0, 30.0, 1, psf_map)
    return raw, row0, col0, psf_map, depth_m


def test_a_weakly_textured_wall_under_smooth_shading_reads_near_its_depth_once_its_lowest_ring_is_skipped():
    """A wall of faint texture (contrast 0.03) under a lamp's smooth shading: the shading puts far more power into
    each window's lowest bins than the texture does, and no candidate's stationary model explains it, so scored on
    every bin the wall reads about 50 % off. Its windows' texture contrast is below ``weak_texture_below`` 0.07 (the
    evidence decoder's), so their NLLs skip the ring within 2 cycles of DC, which holds the shading, and the wall
    reads within about 20 % (``stats["windows_weak_texture"]`` counts them: most of the grid's windows). The same
    wall with a texture of contrast 0.3 has no weak window: it reads exactly as without the knob."""
    raw, row0, col0, psf_map, depth_m = _shaded_wall_raw(0.03)
    absrel, weak_windows = {}, {}
    for gate in (0.0, 0.07):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(weak_texture_below=gate))
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005),
                             aif=False)
        absrel[gate] = float(np.mean(np.abs(out.depth_m[out.valid] - depth_m) / depth_m))
        weak_windows[gate] = out.stats["windows_weak_texture"]
    windows = out.grid_inv_depth.size
    assert absrel[0.0] > 0.35 and absrel[0.07] < 0.25 and absrel[0.07] < 0.5 * absrel[0.0], absrel
    assert weak_windows[0.0] == 0 and weak_windows[0.07] > 0.6 * windows, (weak_windows, windows)
    raw, row0, col0, psf_map, depth_m = _shaded_wall_raw(0.3)
    reads = [ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(weak_texture_below=gate)).decode(
        raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005), aif=False).grid_inv_depth
        for gate in (0.0, 0.07)]
    np.testing.assert_array_equal(reads[0], reads[1])


def test_a_near_planes_defocus_keeps_its_lowest_ring_however_faint_its_texture_reads():
    """A near surface's defocus takes its 3–6 cycle band down with its texture (a 1/f² plane at 0.7 m on the axis
    reads contrast about 0.1 there) and empties the band above (sharpness about 0.01): its lowest ring is the
    evidence of its depth, so no gate puts its windows in the weak group. The same texture at 6 m keeps its upper
    band (sharpness about 0.17): under a gate above its contrast every window is weak."""
    from bmi_sdk.decode.classical import WEAK_TEXTURE_LOW_CYCLES, window_groups
    from bmi_sdk.decode.evidence import hann_taper, window_spectra

    taper = hann_taper(32)
    energy = float((taper ** 2).sum())
    for depth_m, weak_share in ((0.7, 0.0), (6.0, 1.0)):
        raw, row0, col0, _, _ = _plane_frame(depth_m, 0.0, texture="pink", size=256)
        windows = [window_spectra(p, 32, 8, taper) for p in normalised_planes(raw, BLACK, WHITE, row0, col0)]
        noise_vars = [np.full(len(w[1]), 0.005 ** 2) for w in windows]
        groups = window_groups(windows, noise_vars, energy, ClassicalConfig(weak_texture_below=1.0))
        weak = np.logical_or.reduce([mask for mask, _, low in groups if low == WEAK_TEXTURE_LOW_CYCLES])
        assert weak.mean() == weak_share, (depth_m, weak.mean())
        assert np.array_equal(np.logical_or.reduce([mask for mask, _, _ in groups]), np.ones_like(weak))


@pytest.mark.parametrize("gate", [-0.01, 1.5, float("nan"), float("inf")])
def test_a_weak_texture_gate_outside_zero_to_one_is_refused(gate):
    with pytest.raises(ValueError, match="weak_texture_below must lie in \\[0, 1\\]"):
        ClassicalConfig(weak_texture_below=gate)


def test_a_lens_s_far_plane_is_read_with_the_camera_s_exact_kernels(nominal_decoder):
    """A lens's frames hold exact kernels (the simulated device renders them). The camera's decoder
    (``runtime.classical_decoder``) reads them with exact kernels too: a 6 m plane at 50°, φ 30°, reads within
    12 %. The tensor's kernels, rotated to φ by bilinear interpolation, are smoothed where a far kernel is sharp,
    and read the same frame ~3× worse."""
    from bmi_sdk.runtime.classical import classical_decoder

    raw, row0, col0, _, _ = _plane_frame(6.0, 50.0, texture="pink", psf_mode="exact")
    absrel = {}
    for name, decoder in (("exact", classical_decoder(BuiltCamera())), ("tensor", nominal_decoder)):
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
        absrel[name] = float(np.mean(np.abs(out.depth_m[out.valid] - 6.0) / 6.0))
    assert absrel["exact"] < 0.12 and absrel["tensor"] > 2 * absrel["exact"]


def test_a_noiseless_frames_aif_is_not_inverse_filtered(nominal_decoder):
    """σ 0 (only the ADC's rounding): with the sensor's noise alone the Wiener filter becomes an inverse filter and
    the kernel's small errors (depth, blend between candidates) ring: AiF PSNR 13 dB on this plane; the kernel-error
    term (``aif_model_error``) keeps it above 20 dB."""
    from bmi_sdk.metrics import image_metrics

    raw, row0, col0, psf_map, rgb = _plane_frame(2.0, 10.0, sigma=0.0, texture="pink")
    truth = rgb[24:-24, 24:-24]
    psnr = {}
    for eps in (0.0, ClassicalConfig().aif_model_error):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(aif_model_error=eps))
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.0))
        psnr[eps] = image_metrics(out.aif, truth, out.valid)["psnr_db"]
    assert psnr[0.0] < 15 and psnr[ClassicalConfig().aif_model_error] > 20
    with pytest.raises(ValueError, match="aif_model_error"):
        ClassicalConfig(aif_model_error=-0.1)


@pytest.mark.parametrize("texture", ["pink", "scene"])
def test_another_decoders_aif_is_pulled_to_the_frame_through_the_kernels(nominal_decoder, texture):
    """The Wiener step with a prior mean (``ClassicalDecoder.restore_aif``, the learned decoder's AiF step): the true
    image as the prior explains the frame up to its noise and is kept; the same image drawn 3 px off (a network
    that draws a built camera's image where the nominal camera would put it) is pulled back towards the frame; a
    zero prior is the plain Wiener AiF."""
    from bmi_sdk.metrics import image_metrics

    raw, row0, col0, _, rgb = _plane_frame(2.0, 10.0, texture=texture)
    truth = rgb[24:-24, 24:-24]
    noise = NoiseProfile.additive(0.005)
    depth = np.full(raw.shape, 2.0, np.float32)
    kept = nominal_decoder.restore_aif(raw, BLACK, WHITE, GEOMETRY, depth, truth.astype(np.float32), noise, row0, col0)
    assert np.sqrt(np.mean((kept - truth) ** 2)) < 1e-3
    shifted = np.roll(rgb, (3, 3), axis=(0, 1))[24:-24, 24:-24].astype(np.float32)
    pulled = nominal_decoder.restore_aif(raw, BLACK, WHITE, GEOMETRY, depth, shifted, noise, row0, col0)
    assert image_metrics(pulled, truth)["psnr_db"] > image_metrics(shifted, truth)["psnr_db"] + 1.5
    out = nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=noise)
    plain = nominal_decoder.restore_aif(raw, BLACK, WHITE, GEOMETRY, out.depth_m, np.zeros_like(out.aif), noise,
                                        row0, col0)
    assert np.allclose(plain, out.aif, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="prior AiF"):
        nominal_decoder.restore_aif(raw, BLACK, WHITE, GEOMETRY, depth, shifted[:-2], noise, row0, col0)


def test_without_a_profile_the_noise_is_estimated_from_the_frame(nominal_decoder):
    raw, row0, col0, _, _ = _plane_frame(2.0, 10.0)
    out = nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0)
    assert out.stats["noise_source"] == "estimated" and 0.004 < out.stats["noise_sigma"] < 0.01  # texture adds


def test_nearest_depth_reads_nearer_than_the_far_end(nominal_decoder):
    medians = []
    for depth_m in (0.7, 8.0):
        raw, row0, col0, _, _ = _plane_frame(depth_m, 50.0)
        medians.append(np.nanmedian(nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0).depth_m))
    assert medians[0] < 1.0 and medians[1] > 4.0


@pytest.mark.parametrize("level", ["black", "saturated"])
def test_black_and_saturated_frames_decode_to_finite_maps_with_large_sigma(nominal_decoder, level):
    raw = np.full((128, 128), BLACK if level == "black" else WHITE, np.uint16)
    r, c = GEOMETRY.pixel_of_field(20.0, 0.0)
    out = nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, int(r) // 2 * 2, int(c) // 2 * 2)
    assert np.isfinite(out.depth_m).all() and np.isfinite(out.aif).all()
    assert np.all(out.depth_sigma_m / out.depth_m >= 0.1)  # no evidence: never a confident depth


def test_windows_touching_marks_the_windows_of_the_spectra_grid():
    """Which windows hold a set sample, against each window cut out the way ``window_spectra`` cuts it."""
    from bmi_sdk.decode.evidence import windows_touching

    rng = np.random.default_rng(5)
    mask = rng.random((70, 90)) > 0.999
    got = windows_touching(mask, 16, 8)
    rows, cols = (70 - 16) // 8 + 1, (90 - 16) // 8 + 1
    brute = [mask[r * 8:r * 8 + 16, c * 8:c * 8 + 16].any() for r in range(rows) for c in range(cols)]
    assert got.tolist() == brute and 0 < got.sum() < got.size
    assert not windows_touching(np.zeros((70, 90), bool), 16, 8).any() and windows_touching(mask, 16, 8).size == got.size


def test_windows_holding_clipped_samples_read_the_plane_around_a_lamp(nominal_decoder):
    """A 2 m textured plane with a blown-out lamp (a clipped disc): windows that touch clipped samples read the plane
    from their other samples, those clipped in every plane take their neighbours' depth (2 m within 5 %); the rest of
    the plane still reads within 5 %, and the report counts the windows. Scored with their clipped samples, the
    lamp read 4.2 m: a clipped plateau's sharp rim fits no kernel of the plane's depth."""
    raw, row0, col0, _, _ = _plane_frame(2.0, 10.0, size=256, texture="pink")
    yy, xx = np.mgrid[:256, :256]
    lamp = (yy - 128) ** 2 + (xx - 128) ** 2 < 20 ** 2
    raw = np.where(lamp, WHITE, raw).astype(raw.dtype)
    out = nominal_decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
    stats = out.stats
    assert stats["windows_with_clipped_samples"] >= stats["windows_scored_without_clipped_samples"] > 0
    assert stats["windows_with_clipped_samples"] >= stats["windows_without_evidence"]
    near_lamp = np.hypot(yy - 128, xx - 128) < 20 + 32
    far_from_lamp = np.hypot(yy - 128, xx - 128) > 20 + 64 + 16  # no window holding the lamp reaches here
    assert out.valid[near_lamp].all()
    assert np.mean(np.abs(out.depth_m[near_lamp] - 2.0)) / 2.0 < 0.05
    assert np.mean(np.abs(out.depth_m[far_from_lamp] - 2.0)) / 2.0 < 0.05


@pytest.fixture(scope="module")
def highlight_frame(nominal_decoder):
    """``bench.clipped.highlight_scene`` 3: a dark 1/f-textured disc at 1.5 m (radius 70 px) holding a highlight 20×
    white (radius 10 px), before a brighter 1/f-textured wall at 5 m, at 15° of field, σ 0.005. The near kernel
    spreads the highlight over most of the disc: the case of a specular lamp or a sunlit glint on a near object."""
    from bmi_sdk.bench.clipped import HIGHLIGHT_SCENES, highlight_scene

    psf_map = nominal_decoder.zones.psf_map
    return highlight_scene(*HIGHLIGHT_SCENES[2], psf_map.tensor, GEOMETRY, psf_map)


def test_a_near_object_with_a_blown_out_highlight_reads_its_own_depth(nominal_decoder, highlight_frame):
    """The highlight_frame: every window on the near disc holds clipped samples. Scored from their other samples
    under a taper ramped to zero around the clipped ones (``decode.clipped``), the disc reads AbsRel 0.30 inside its
    rim and the wall 0.12. Given no evidence by them (``clipped_planes_per_frame`` 0), the disc's windows are blind
    and take the wall's depth (AbsRel 1.52; the wall 0.11)."""
    from dataclasses import replace

    raw, row0, col0 = (highlight_frame[k] for k in ("raw", "row0", "col0"))
    range_m, radius = highlight_frame["range_m"], highlight_frame["radius_px"]
    assert 0.005 < np.mean(raw >= WHITE) < 0.05
    inside, wall = radius < 54, radius > 110
    reads = {}
    for per_frame in (ClassicalConfig().clipped_planes_per_frame, 0):
        decoder = ClassicalDecoder(nominal_decoder.zones.psf_map, nominal_decoder.candidates,
                                   replace(nominal_decoder.config, clipped_planes_per_frame=per_frame))
        decoder.zones = nominal_decoder.zones
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005))
        error = np.abs(out.depth_m - range_m) / range_m
        reads[per_frame] = (np.mean(error[inside]), np.mean(error[wall]), out.stats)
    (disc, wall_error, stats), (disc_dropped, _, dropped) = reads.values()
    assert disc < 0.4 < 1.0 < disc_dropped and wall_error < 0.15
    assert stats["windows_scored_without_clipped_samples"] > 0.8 * stats["windows_with_clipped_samples"]
    assert stats["windows_without_evidence"] < 0.1 * dropped["windows_without_evidence"]
    assert dropped["windows_scored_without_clipped_samples"] == 0


def test_the_clipped_pairs_a_frame_scores_are_capped_and_do_not_depend_on_threads(nominal_decoder, highlight_frame):
    """``clipped_planes_per_frame`` caps the (window, plane) pairs scored without their clipped samples, choosing the
    pairs for the whole frame before its blocks run, so one thread and two read the same depths."""
    from dataclasses import replace

    raw, row0, col0 = (highlight_frame[k] for k in ("raw", "row0", "col0"))
    depths = []
    for threads in (1, 2):
        decoder = ClassicalDecoder(nominal_decoder.zones.psf_map, nominal_decoder.candidates,
                                   replace(nominal_decoder.config, clipped_planes_per_frame=40, threads=threads))
        decoder.zones = nominal_decoder.zones
        out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005),
                             aif=False)
        assert 10 <= out.stats["windows_scored_without_clipped_samples"] <= 40
        depths.append(out.depth_m)
    assert np.array_equal(depths[0], depths[1], equal_nan=True)
    with pytest.raises(ValueError, match="clipped_planes_per_frame"):
        ClassicalConfig(clipped_planes_per_frame=-1)


def test_blocks_outside_the_image_circle_are_skipped(nominal_decoder):
    """A 40° image circle: the sensor's corner lies outside it, so no evidence is computed there."""
    from dataclasses import replace

    small_circle = replace(GEOMETRY, max_field_deg=40.0)
    raw = np.full((256, 256), 1000, np.uint16)
    kernels_before = nominal_decoder.zones.kernel_sets_computed
    out = nominal_decoder.decode(raw, BLACK, WHITE, small_circle, 0, 0)
    assert out.stats["blocks_skipped"] == out.stats["blocks_skipped"] + out.stats["blocks_run"] >= 1
    assert out.stats["candidate_evaluations"] == 0 and out.stats["kernel_sets_computed"] == kernels_before
    assert not out.valid.any() and np.isnan(out.depth_m).all() and not out.aif.any()


def test_the_aif_blocks_read_the_zones_the_evidence_blocks_traced():
    """The AiF's blocks cover the evidence blocks' pixels and take their zones: across the whole sensor (the
    partial blocks at its bottom and right edges included) every AiF block's zone is an evidence block's, and at the
    defaults its candidates are the coarse pass's, so a camera's first frame traces no zone for the AiF alone."""
    from bmi_sdk.decode.classical import (
        aif_block_centre,
        aif_blocks,
        coarse_indices,
        evidence_block_centre,
        evidence_blocks,
    )
    from bmi_sdk.decode.kernels import ZoneKernels

    cfg = ClassicalConfig()
    height, width = GEOMETRY.height_px, GEOMETRY.width_px
    evidence_zones = {ZoneKernels.zone_at(GEOMETRY, *evidence_block_centre(cfg, block))
                      for block in evidence_blocks(cfg, height, width)}
    blocks = aif_blocks(cfg, height, width)
    aif_zones = {ZoneKernels.zone_at(GEOMETRY, *aif_block_centre(cfg, block, height, width)) for block in blocks}
    assert aif_zones <= evidence_zones and len(aif_zones) > 300
    assert np.array_equal(coarse_indices(cfg.candidates, cfg.aif_step), coarse_indices(cfg.candidates, cfg.coarse_step))
    for r, r1, c, c1 in blocks:  # each zone's field position lies inside the block it serves
        row, col = aif_block_centre(cfg, (r, r1, c, c1), height, width)
        assert r <= row < r1 and c <= col < c1


def _scene_window():
    """(raw, row0, col0, psf_map, noise) of a 320² procedural scene from 0.7 to 10 m at θ ≈ 10° (four evidence
    blocks), rendered and decoded with the nominal tensor kernels at σ 0.005."""
    scene = generate_scene(320, 320, np.random.default_rng(11))
    tensor = lens_tensor("bmi_monocentric")
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    row0, col0 = 1200, 1600
    optical = render_coded(scene.rgb, scene.range_m, tensor, GEOMETRY, row0, col0, psf_map=psf_map)
    return simulate_raw(optical, 0.005, np.random.default_rng(2), row0, col0), row0, col0, psf_map, \
        NoiseProfile.additive(0.005)


@pytest.mark.slow  # the exhaustive decode is the reference; the default decoder's accuracy is tested on its own
def test_the_coarse_to_fine_pass_reads_what_scoring_every_candidate_reads_with_fewer_evaluations():
    """A procedural scene from 0.7 to 10 m: the coarse pass (every 4th candidate) and a fine pass over each window's
    coarse best ± 4 that reuses the coarse scores read the windows' depths as scoring every candidate does (the
    β grids differ, so not bit for bit: 95 % of windows within 1 %), and never score more than that."""
    raw, row0, col0, psf_map, noise = _scene_window()
    coarse_fine = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig()).decode(
        raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=noise)
    every = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(coarse_step=1)).decode(
        raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=noise)
    stats = coarse_fine.stats
    assert stats["candidate_evaluations"] < stats["candidate_evaluations_exhaustive"]
    assert every.stats["candidate_evaluations"] == every.stats["candidate_evaluations_exhaustive"]
    a, b = coarse_fine.grid_inv_depth, every.grid_inv_depth
    assert np.isfinite(a).all() and np.isfinite(b).all()
    assert np.ptp(1.0 / b) > 3.0  # the scene spans near and far windows
    assert np.mean(np.abs(a - b) / b < 0.01) > 0.95


def test_blocks_read_on_two_threads_give_the_one_thread_decode_bit_for_bit():
    """The decoder reads a frame's evidence and AiF blocks on ``threads`` threads (each block's FFTs on one) and
    makes each zone's models once under a lock: a 320² scene of four blocks, decoded by fresh decoders on one and on
    two threads, gives the same depth, 1σ, AiF, evidence and counts to the last bit."""
    raw, row0, col0, psf_map, noise = _scene_window()
    fresh = [PsfMap(psf_map.tensor, GEOMETRY, mode="tensor") for _ in range(2)]  # nothing memoised by the other
    one, two = (ClassicalDecoder.for_psf_map(kernels, ClassicalConfig(threads=n)).decode(
        raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=noise) for kernels, n in zip(fresh, (1, 2)))
    assert one.stats["blocks_run"] == two.stats["blocks_run"] == 4
    for name in ("depth_m", "depth_sigma_m", "aif", "valid", "grid_inv_depth", "grid_sigma_inv", "grid_evidence"):
        assert np.array_equal(getattr(one, name), getattr(two, name), equal_nan=True), name
    for key in ("candidate_evaluations", "kernel_sets_computed", "windows_with_clipped_samples"):
        assert one.stats[key] == two.stats[key], key


def test_window_must_hold_the_kernel():
    psf_map = PsfMap(lens_tensor("fisheye"), lens_geometry("fisheye"), mode="tensor")
    with pytest.raises(ValueError, match="do not fit"):
        ClassicalDecoder(psf_map, inverse_depth_candidates(psf_map.tensor.depth_m, 8), ClassicalConfig())
    with pytest.raises(ValueError, match="multiple of 4"):
        ClassicalConfig(window_px=30)


def test_a_built_camera_is_hashed_by_everything_that_makes_its_kernels():
    nominal = BuiltCamera()
    built = BuiltCamera(perturbation=Perturbation(decenter_um=(10.0, 0.0)))
    assert nominal.is_nominal and not built.is_nominal and nominal.sha256() != built.sha256()
    assert nominal.psf_map().mode == "exact" and built.psf_map().mode == "exact"
    assert built.psf_map().perturbation == built.perturbation


def test_infer_classical_writes_depth_sigma_confidence_and_ply_sigma(tmp_path, bmi):
    bmi("simulate", "--procedural", 5, "--size", 128, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    out = bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--decoder", "classical", "--quiet").stdout
    assert "classical decoder" in out
    depth = np.load(tmp_path / "o" / "depth.npy")
    sigma = np.load(tmp_path / "o" / "depth_sigma.npy")
    assert depth.shape == sigma.shape == (128, 128)
    assert np.array_equal(np.isnan(depth), np.isnan(sigma)) and np.all(sigma[np.isfinite(sigma)] > 0)
    assert (tmp_path / "o" / "confidence.png").stat().st_size > 0
    header = (tmp_path / "o" / "points.ply").read_bytes()[:400]
    assert b"property float sigma" in header
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["decoder"] == "classical" and report["calibration_id"] is None
    assert report["decoder_stats"]["candidate_evaluations"] > 0
    # the evidence used the camera's own noise, as the DNG's NoiseProfile tag carries it, not a guess
    from devices import load_raw

    profile = load_raw(tmp_path / "f.dng").noise_profile
    assert report["decoder_stats"]["noise_source"] == "profile"
    assert report["decoder_stats"]["noise_profile"] == profile.to_dict()
    assert report["decoder_stats"]["noise_sigma"] == pytest.approx(0.005, rel=0.05)


def test_simulate_calibrate_infer_loop_uses_the_calibrated_kernels(tmp_path, bmi):
    """A built camera (decenter 8 µm) → calibrated from its own point-source captures → its frames decoded
    with the calibrated kernels, by the classical and the learned decoder, whose AiF then goes through
    those kernels too; the report carries the fitted errors and the camera's hash."""
    from calibration import CapturePlan, PointSource, Target, extract_spots, fit_calibration, simulate_captures
    from calibration.io import write_calibration

    diag = np.degrees(np.arctan2(2250, 3000))
    sources = [(0.0, 0.0, 4.0), (55.0, diag, 10.0), (55.0, 180 - diag, 2.5), (55.0, 180 + diag, 4.0),
               (44.0, 0.0, 2.5), (32.0, 90.0, 10.0), (44.0, 180.0, 4.0)]
    target = Target(tuple(PointSource(t, a, d) for t, a, d in sources))
    truth = Perturbation(decenter_um=(8.0, 0.0))
    captures = simulate_captures(target, CapturePlan(kernel_px=21, roi_margin_px=10), truth, seed=11)
    extraction = extract_spots(captures)
    result = fit_calibration(extraction)
    calib = write_calibration(tmp_path / "calib.json", result, captures, extraction, tensor_fields_deg=(0.0,),
                              tensor_depths_m=(4.0,))
    bmi("simulate", "--procedural", 5, "--size", 96, "--field-deg", 20, "--noise", 0.005,
        "--perturb", "decenter_um=8,0", "--out", tmp_path / "f.dng")
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--decoder", "classical", "--calibration",
        tmp_path / "calib.json", "--candidates", 12, "--quiet")
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["calibration_id"] == calib.id
    fitted = report["camera"]["perturbation"]["decenter_um"][0]
    assert fitted == pytest.approx(result.estimate.decenter_um[0]) and abs(fitted - 8.0) < 2.0
    assert report["camera"]["sha256"] != BuiltCamera(geometry=GEOMETRY).sha256()
    rays = report["rays"]  # the point cloud follows the calibrated camera's rays: its image moved with the lens
    assert rays["source"] == "traced through the calibrated camera"
    assert rays["centre_px"][1] - rays["nominal_centre_px"][1] == pytest.approx(fitted / 2.0, abs=0.1)
    sidecar = json.loads((tmp_path / "f.json").read_text())
    assert sidecar["source"]["injected_perturbation"]["decenter_um"] == [8.0, 0.0]
    assert np.isfinite(np.load(tmp_path / "o" / "depth.npy")).any()
    # the learned decoder on the calibrated camera: its AiF goes through the camera's kernels
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "l", "--decoder", "learned", "--calibration",
        tmp_path / "calib.json", "--quiet")
    report = json.loads((tmp_path / "l" / "report.json").read_text())
    assert report["decoder"] == "learned" and report["calibration_id"] == calib.id
    assert report["aif_consistency_step"] is True
    assert np.isfinite(np.load(tmp_path / "l" / "aif.npy")).all()


def test_overwriting_a_classical_run_with_the_network_leaves_no_stale_sigma(tmp_path, passthrough_model, bmi):
    """--overwrite replaces the whole set: the network writes no depth σ, so the classical run's must go."""
    bmi("simulate", "--procedural", 5, "--size", 96, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--decoder", "classical", "--quiet")
    assert (tmp_path / "o" / "depth_sigma.npy").exists() and (tmp_path / "o" / "confidence.png").exists()
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--model", passthrough_model, "--tile-px", 64,
        "--overwrite", "--quiet")
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["decoder"] == "cnn"
    assert not (tmp_path / "o" / "depth_sigma.npy").exists() and not (tmp_path / "o" / "confidence.png").exists()
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == sorted(report["files"]) + ["report.json"]


def test_a_refused_run_leaves_no_output_folder(tmp_path, bmi):
    bmi("simulate", "--procedural", 5, "--size", 64, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    run = bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "o", "--decoder", "classical", "--candidates", 2,
              check=False)
    assert run.returncode == 2 and "--candidates: 2 is outside [3, 1000]" in run.stderr
    assert not (tmp_path / "o").exists()


def test_aif_windows_have_lengths_the_fft_factors_well():
    """A block's AiF window holds its core and both halos, in whole Bayer quads, at a length scipy's FFT
    factors into small primes (the 256-px block with its 50-px halo was 356 = 4 × 89)."""
    import scipy.fft

    from bmi_sdk.decode.classical import fft_span_px

    for core, halo in ((256, 50), (192, 50), (17, 50), (256, 170), (1, 2)):
        span = fft_span_px(core, halo)
        assert span >= core + 2 * halo and span % 2 == 0
        assert scipy.fft.next_fast_len(span, real=True) == span
        n = span
        for prime in (2, 3, 5, 7, 11):
            while n % prime == 0:
                n //= prime
        assert n == 1, span
    assert fft_span_px(256, 50) == 360


def test_each_window_reads_the_zones_around_its_own_theta_weighted_linearly():
    """A built camera's kernels change with θ within a block, so a window can read the zones of a θ grid around its
    own θ: two zones, weights summing to 1 that interpolate θ exactly, windows in ``window_spectra``'s row-major
    order; θ step off reads the block's centre zone. Near the axis, at the field edge and on a block's grid."""
    from bmi_sdk.decode.kernels import ZoneKernels

    geometry = lens_geometry("bmi_monocentric")
    r, c = geometry.pixel_of_field(55.0, 30.0)
    grids = [([p[0]], [p[1]]) for p in (geometry.pixel_of_field(t, 30.0) for t in (0.3, 54.3, 59.99))]
    grids.append((r + 16.0 * np.arange(3), c + 16.0 * np.arange(4)))
    for rows, cols in grids:
        grid_rows, grid_cols = np.meshgrid(rows, cols, indexing="ij")
        thetas = geometry.field_angles(grid_rows.ravel(), grid_cols.ravel())[0]
        reads = ZoneKernels.field_reads(geometry, rows, cols, (55.0, 30.0), 1.0)
        weight = np.zeros(len(thetas))
        theta_read = np.zeros(len(thetas))
        for (zone_theta, zone_phi), idx, w in reads:
            assert zone_theta == round(zone_theta) and zone_phi == (0.0 if zone_theta == 0 else 30.0)
            np.add.at(weight, idx, w)
            np.add.at(theta_read, idx, w * zone_theta)
        np.testing.assert_allclose(weight, 1.0, atol=1e-12)
        np.testing.assert_allclose(theta_read, thetas, atol=1e-6)
        assert sum(len(idx) for _, idx, _ in reads) <= 2 * len(thetas)
        (only,) = ZoneKernels.field_reads(geometry, rows, cols, (55.0, 30.0), None)
        assert only[0] == (55.0, 30.0) and np.array_equal(only[1], np.arange(len(thetas))) and np.all(only[2] == 1)
    with pytest.raises(ValueError, match="theta_step_deg"):
        ClassicalConfig(theta_step_deg=0.3)


def test_windows_read_at_their_own_theta_agree_with_the_block_zone_on_the_field_invariant_design():
    """The design's kernels hardly change over a block's 2° of field (the paper's premise), so reading each window
    with the zones around its own θ (two zones per window here) must give the block zone's depth to ~1 %."""
    raw, row0, col0, psf_map, _ = _plane_frame(4.0, 50.0, texture="pink")
    per_window = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(theta_step_deg=1.0))
    noise = NoiseProfile.additive(0.005)
    block = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig()).decode(raw, BLACK, WHITE, GEOMETRY, row0, col0,
                                                                            noise_profile=noise)
    own = per_window.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=noise)
    assert own.valid.all() and np.mean(np.abs(own.depth_m - 4.0) / 4.0) < 0.05
    assert np.median(np.abs(own.depth_m / block.depth_m - 1.0)) < 0.01
    assert own.stats["kernel_sets_computed"] > block.stats["kernel_sets_computed"] > 0


def test_a_warmed_cache_serves_a_frames_decode_without_tracing(tmp_path, monkeypatch):
    """``warm_kernels`` traces every zone kernel a window's decode reads (evidence and AiF blocks) into the disk
    cache, and makes their evidence models: a second warm-up traces and makes nothing, and a fresh decoder (a new
    process's) decodes the window reading every kernel and evidence model from disk, with the prior's texture exponent
    or the profiled one. A region off the sensor is refused before any work."""
    from bmi_sdk.decode.classical import with_texture_exponent
    from bmi_sdk.runtime.classical import classical_decoder, warm_kernels

    monkeypatch.setenv("BMI_CACHE_DIR", str(tmp_path / "cache"))
    camera = BuiltCamera()
    config = ClassicalConfig(candidates=12)
    roi = (1504, 2304, 288, 288)  # two evidence blocks and two AiF blocks a side, at zones of their own
    first = warm_kernels(camera, config, roi=roi)
    assert first["zones"] >= 2 and first["kernel_sets_traced"] == first["kernel_sets"] > 0
    assert first["evidence_models_made"] == first["kernel_sets"]
    again = warm_kernels(camera, config, roi=roi)
    assert again["kernel_sets_traced"] == 0 and again["evidence_models_made"] == 0 and again["zones"] == first["zones"]
    decoder = classical_decoder(camera, config)
    raw = np.full(roi[2:], 1500, np.uint16) + np.random.default_rng(0).integers(0, 200, roi[2:]).astype(np.uint16)
    out = decoder.decode(raw, BLACK, WHITE, camera.sensor(), roi[0], roi[1], noise_profile=NoiseProfile.additive(0.005))
    assert out.valid.any() and decoder.zones.kernel_sets_computed > 0
    assert decoder.zones.psf_map.kernels_traced == 0 and out.stats["kernel_sets_traced"] == 0
    assert out.stats["models_computed"] == 0  # and every evidence model from the shards the warm-up wrote
    # the profiled texture exponent reads every window with the exact model of three slopes: the warm-up makes those
    profiled = with_texture_exponent(config, "profiled")
    made = warm_kernels(camera, profiled, roi=roi)
    assert made["kernel_sets_traced"] == 0 and made["evidence_models_made"] == first["kernel_sets"]
    out = classical_decoder(camera, profiled).decode(raw, BLACK, WHITE, camera.sensor(), roi[0], roi[1],
                                                     noise_profile=NoiseProfile.additive(0.005))
    assert out.valid.any() and out.stats["models_computed"] == 0
    with pytest.raises(ValueError, match="not inside the"):
        warm_kernels(camera, config, roi=(4400, 0, 200, 200))
    with pytest.raises(ValueError, match="workers must be >= 1"):
        warm_kernels(camera, config, roi=roi, workers=0)


def test_profile_exponent_is_the_brute_force_minimum_over_a_fine_exponent_grid():
    """A window's NLL that is a parabola in α about its own best exponent: profiled from five slopes it is the exact
    minimum of NLL + the natural-image prior over a fine α grid (a parabola plus a parabola is one), and one slope
    returns its NLL unchanged."""
    from bmi_sdk.decode.evidence import EXPONENT_PRIOR, profile_exponent

    slopes = np.array([1.5, 1.75, 2.0, 2.25, 2.5])
    best_alpha = np.array([1.6, 2.0, 2.37, 2.45])
    curvature = np.array([40.0, 5.0, 120.0, 0.5])
    nll = lambda a: 7.0 + 0.5 * curvature * (a - best_alpha) ** 2  # noqa: E731
    fine = np.linspace(1.5, 2.5, 20001)
    mean, spread = EXPONENT_PRIOR
    brute = np.min([nll(a) + (a - mean) ** 2 / (2 * spread ** 2) for a in fine], axis=0)
    assert profile_exponent(np.stack([nll(a) for a in slopes]), slopes) == pytest.approx(brute, abs=1e-6)
    assert np.array_equal(profile_exponent(nll(2.0)[None], (2.0,)), nll(2.0))
    with pytest.raises(ValueError, match="one NLL per slope"):
        profile_exponent(np.zeros((3, 4)), slopes)


@pytest.mark.parametrize("power_slope", [1.6, 2.0, 2.4])
def test_a_far_plane_of_a_steeper_or_flatter_texture_reads_its_range_with_the_exponent_profiled(power_slope):
    """A plane at 6 m (θ 5°) whose texture's power spectrum falls as 1/f^1.6 or 1/f^2.4, natural images' spread about
    the prior's 1/f²: far away a texture's slope mimics blur, and the 1/f² prior reads such planes 10–45 % off. With
    the exponent profiled (five slopes 1.5–2.5, every window scored with the exact model) the plane reads within 12 %,
    and a 1/f² plane stays within 8 %. At 1.5 m the kernels' rings pin the depth, and both read it within 1 %.

    ``--texture-exponent profiled`` (α profiled per pool, gated) reads them as well; its likelihood-ratio gate keeps
    the prior's α on (nearly) every window of the 1/f² plane and opens on most windows of the others at 6 m."""
    from bmi_sdk.bench.decoder import power_law_texture
    from bmi_sdk.decode.classical import with_texture_exponent

    tensor, size = lens_tensor("bmi_monocentric"), 192
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    fixed = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig())
    profiled = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig(slopes=(1.5, 1.75, 2.0, 2.25, 2.5),
                                                                     exact_model_below=1.0))
    gated = ClassicalDecoder.for_psf_map(psf_map, with_texture_exponent(ClassicalConfig(), "profiled"))
    for depth_m, tolerance in ((6.0, 0.12), (1.5, 0.01)):
        rgb = power_law_texture(size + 48, power_slope, np.random.default_rng(3))
        r, c = GEOMETRY.pixel_of_field(5.0, 30.0)
        row0, col0 = int(r - size / 2) // 2 * 2, int(c - size / 2) // 2 * 2
        optical = render_coded(rgb, np.full((size + 48, size + 48), depth_m, np.float32), tensor, GEOMETRY,
                               row0 - 24, col0 - 24, psf_map=psf_map)[24:-24, 24:-24]
        optical *= relative_illumination(GEOMETRY, row0, col0, size, size)[..., None]
        raw = simulate_raw(optical, 0.005, np.random.default_rng(4), row0, col0)
        ratio, opened = {}, {}
        for name, decoder in (("fixed", fixed), ("profiled", profiled), ("gated", gated)):
            out = decoder.decode(raw, BLACK, WHITE, GEOMETRY, row0, col0, noise_profile=NoiseProfile.additive(0.005),
                                 aif=False)
            ratio[name] = float(np.median(out.depth_m[out.valid])) / depth_m
            opened[name] = out.stats["windows_exponent_profiled"] / np.isfinite(out.grid_inv_depth).sum()
        assert opened["fixed"] == 0 and opened["profiled"] == 1, opened
        if depth_m == 1.5:
            assert all(abs(r - 1) < tolerance for r in ratio.values()), ratio
        elif power_slope == 2.0:
            assert all(abs(r - 1) < 0.08 for r in ratio.values()), ratio
            assert opened["gated"] < 0.05, opened
        else:
            assert abs(ratio["fixed"] - 1) > 0.1, ratio
            assert abs(ratio["profiled"] - 1) < tolerance and abs(ratio["gated"] - 1) < tolerance, ratio
            assert opened["gated"] > 0.8, opened


def test_a_pooled_exponent_with_no_neighbour_in_reach_is_each_windows_own_profile():
    """Exponent profiled over each window's pooled curves: with a pooling radius so small that every neighbour weighs
    e^-512, each pool is the window alone, and its reads are those of α profiled in the window's own NLL (the
    ``exponent_scope`` "window" path, which never pools by slope), to float32 rounding."""
    from bmi_sdk.bench.decoder import power_law_texture

    tensor, size = lens_tensor("bmi_monocentric"), 128
    psf_map = PsfMap(tensor, GEOMETRY, mode="tensor")
    rgb = power_law_texture(size + 48, 2.3, np.random.default_rng(5))
    r, c = GEOMETRY.pixel_of_field(30.0, 60.0)
    row0, col0 = int(r - size / 2) // 2 * 2, int(c - size / 2) // 2 * 2
    depth = np.where(np.arange(size + 48)[:, None] < (size + 48) // 2, 1.2, 4.0) * np.ones((1, size + 48))
    optical = render_coded(rgb, depth.astype(np.float32), tensor, GEOMETRY, row0 - 24, col0 - 24,
                           psf_map=psf_map)[24:-24, 24:-24]
    raw = simulate_raw(optical, 0.005, np.random.default_rng(6), row0, col0)
    reads = {}
    for scope in ("window", "pooled"):
        config = ClassicalConfig(slopes=(1.6, 2.0, 2.4), pool_sigma_px=0.5, exponent_scope=scope)
        out = ClassicalDecoder.for_psf_map(psf_map, config).decode(raw, BLACK, WHITE, GEOMETRY, row0, col0,
                                                                   noise_profile=NoiseProfile.additive(0.005),
                                                                   aif=False)
        reads[scope] = out.grid_inv_depth
    assert np.isfinite(reads["window"]).all()
    np.testing.assert_allclose(reads["pooled"], reads["window"], rtol=1e-5)


@pytest.mark.parametrize("knobs, message", [({"exponent_scope": "frame"}, "exponent_scope must be one of"),
                                            ({"exponent_scope": "pooled", "pool_sigma_px": 0.0}, "needs pooling")])
def test_an_exponent_scope_it_cannot_profile_is_refused(knobs, message):
    with pytest.raises(ValueError, match=message):
        ClassicalConfig(slopes=(1.5, 2.0, 2.5), **knobs)


def test_the_exponent_gate_keeps_the_priors_slope_unless_profiling_lowers_the_pooled_nll_beyond_it():
    """``evidence.gated_exponent`` on curves built to a known likelihood ratio: pools whose profiled least NLL lies more
    than the gate below the α = 2 curve's take the profile (equal to ``profile_exponent``'s), the others the α = 2
    curve exactly; gate 0 profiles every pool; NaN pools (no decode) stay NaN."""
    from bmi_sdk.decode.evidence import gated_exponent, profile_exponent

    slopes = (1.6, 2.0, 2.4)
    d = np.arange(7.0)
    base = (d - 3.0) ** 2                       # α = 2: least NLL 0 at candidate 3
    gains = np.array([0.0, 5.0, 40.0, 400.0])   # how much lower the α = 1.6 curve lies, per pool
    by_slope = np.stack([base[None, :] - gains[:, None], np.broadcast_to(base, (4, 7)),
                         np.broadcast_to(base + 50.0, (4, 7))]).copy()   # (slopes, pools, D)
    by_slope[:, 0] = np.nan
    reference = profile_exponent(by_slope, slopes)
    drop = by_slope[1, 1:].min(axis=-1) - reference[1:].min(axis=-1)   # the likelihood ratio of pools 1–3
    assert np.all(np.diff(drop) > 0) and drop[0] < 10 < drop[1] < 100 < drop[2]
    for gate in (0.0, 10.0, 100.0):
        pooled, profiled = gated_exponent(by_slope, slopes, gate)
        expected = np.array([gate == 0] + [gate == 0 or g > gate for g in drop])
        np.testing.assert_array_equal(profiled, expected)
        take = expected[1:]
        np.testing.assert_allclose(pooled[1:][take], reference[1:][take], rtol=1e-6)
        np.testing.assert_array_equal(pooled[1:][~take], by_slope[1, 1:][~take].astype(np.float32))
        assert np.isnan(pooled[0]).all()


@pytest.mark.parametrize("knobs, message", [
    ({"exponent_gate_nats": -1.0}, "exponent_gate_nats must lie in"),
    ({"exponent_gate_nats": float("nan")}, "exponent_gate_nats must lie in"),
    ({"exponent_gate_nats": 1e9}, "exponent_gate_nats must lie in"),
    ({"exponent_gate_nats": 30.0}, "needs exponent_scope 'pooled'"),
    ({"exponent_gate_nats": 30.0, "exponent_scope": "pooled", "slopes": (1.5, 2.5)}, "2 among the slopes")])
def test_an_exponent_gate_it_cannot_apply_is_refused(knobs, message):
    with pytest.raises(ValueError, match=message):
        ClassicalConfig(**{"slopes": (1.6, 2.0, 2.4), **knobs})


def test_the_evidence_decoders_volume_skips_weak_windows_lowest_ring_as_its_manifest_says(tmp_path):
    """The shipped evidence network's manifest sets the weak-texture gate its classical stage reads with; a manifest
    without the knob (made before it existed) reads the dataclass's 0: every window on every bin but DC's
    neighbours, as it was made."""
    import shutil

    from bmi_sdk.runtime.evidence import EVIDENCE_MODEL, EvidenceNetwork

    assert EvidenceNetwork(EVIDENCE_MODEL).stage_config().weak_texture_below == pytest.approx(0.07)
    path = tmp_path / EVIDENCE_MODEL.name
    shutil.copy(EVIDENCE_MODEL, path)
    manifest = json.loads(EVIDENCE_MODEL.with_suffix(".manifest.json").read_text())
    knobs = {k: v for k, v in manifest["classical_config"].items() if k != "weak_texture_below"}
    path.with_suffix(".manifest.json").write_text(json.dumps(dict(manifest, classical_config=knobs)))
    assert EvidenceNetwork(path).stage_config().weak_texture_below == 0.0


def test_a_texture_exponent_mode_sets_its_knobs_and_an_unknown_one_is_refused():
    from bmi_sdk.decode.classical import TEXTURE_EXPONENTS, with_texture_exponent

    assert with_texture_exponent(ClassicalConfig(), "prior") == ClassicalConfig()
    profiled = with_texture_exponent(ClassicalConfig(candidates=16), "profiled")
    assert profiled.candidates == 16 and profiled.exponent_scope == "pooled" and profiled.exponent_gate_nats > 0
    assert set(TEXTURE_EXPONENTS) == {"prior", "profiled"}
    with pytest.raises(ValueError, match="one of prior, profiled"):
        with_texture_exponent(ClassicalConfig(), "natural")


@pytest.mark.parametrize("slopes", [(), (2.0, 1.5), (1.5, 1.6, 2.0), (float("nan"),), (-1.0,), (1e9,), ("2",), (True,)])
def test_prior_slopes_must_be_increasing_evenly_spaced_exponents(slopes):
    with pytest.raises(ValueError, match="slopes must"):
        ClassicalConfig(slopes=slopes)
