"""Depth evidence from the camera's own kernels: the Gaussian-prior marginal likelihood of local spectra.

For one window of one Bayer plane (R, G1, G2 or B: ``bayer``), with taper t,
local spectrum Y(ω) = DFT(t · (y − mean)), a candidate kernel with OTF K_d and
an image prior of power spectrum β S(f), S = 1 / |f|² (natural images), the
negative log-likelihood of the observed window under depth d is

    L(d, β) = ½ Σ_ω≠0 [P(ω) / V_d(ω) + log V_d(ω)],    P = |Y|²,
    V_d(ω) = β Σt² · Σ_aliases |K_d(f)|² S(f)  +  σ² Σt²

(Levin, Fergus, Durand & Freeman, "Image and depth from a conventional camera
with a coded aperture", SIGGRAPH 2007, which writes the sum without the ½). The
½ is exact: a real window's spectrum holds each complex value twice (ω and −ω
are conjugates), so the full-spectrum sum counts every independent bin twice;
the Gaussian log-likelihood of the samples, written in Fourier, is half of it.
The likelihood's curvature gives the Laplace 1σ of 1/d; it is the tapered
estimator's real spread only after the taper's variance inflation
(``taper_variance_inflation``: a Hann window lets neighbouring bins share data,
so the bins are not independent and the estimate scatters 35/18 = 1.94×
further than the curvature says). A Monte Carlo test on fields drawn from the
model itself holds both factors (``tests/test_decode.py``). A Bayer plane is the
full-resolution image sampled every second pixel, so the model power of plane frequency ω is
the sum of the four full-resolution frequencies that fold onto it (the
aliases; the kernel's spectrum reaches well past the plane's Nyquist
frequency). The noise σ is white on the raw samples, which is why the
evidence is computed on the raw planes and not on demosaiced channels (whose
interpolated noise is correlated).

Within one zone the weights 1 / V are fixed, so the data term of every window,
every candidate depth and every prior level β_j is one matrix product
P (windows × frequencies) @ W (frequencies × (depth, β)). β is profiled out
per plane, window and depth on a geometric grid and refined by a parabola in
log β; the planes' profiled NLLs add up (with several prior slopes α, per slope, and α is then profiled out of
the sum: ``profile_exponent``). Depth candidates are spaced evenly in
inverse depth (defocus is nearly linear in 1/d); the best candidate is
refined by a parabola in 1/d, and the parabola's curvature gives the 1σ of
1/d (``Evidence.refine``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy import fft as sfft

BETA_RATIO = 2.0 ** 0.5
"""Spacing of the prior-level grid (factor between neighbours); refined by a parabola in log β."""
BETA_MARGIN = (0.25, 16.0)
"""The β grid spans the windows' moment estimates times these factors: a wrong (too blurred) kernel
explains fine detail only with a much larger β, so the grid reaches further up than down."""
MAX_BETA_LEVELS = 48
REAL_FIELD_WEIGHT = 0.5
"""The likelihood's weight per full-spectrum bin (module doc): a real window holds each complex value twice."""


def hann_taper(n: int) -> np.ndarray:
    """n × n separable Hann window (periodic form: no zero at both ends, all n samples carry data)."""
    w = 0.5 - 0.5 * np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n)
    return np.outer(w, w).astype(np.float32)


def taper_variance_inflation(taper: np.ndarray) -> float:
    """N Σt⁴ / (Σt²)², N the taper's samples: how much further a tapered window's spectral estimate scatters
    than the curvature of its likelihood says (tapered Whittle estimation: R. Dahlhaus, "Spectral analysis with
    tapered data", J. Time Ser. Anal. 4, 1983). 1 for no taper; (35/18)² = 3.78 for the 2-D periodic Hann."""
    t = np.asarray(taper, np.float64)
    return float(t.size * np.sum(t ** 4) / np.sum(t ** 2) ** 2)


def power_law_prior(f_row: np.ndarray, f_col: np.ndarray, floor_cycles: float, slope: float = 2.0) -> np.ndarray:
    """S(f) = (|f|² + f0²)^(−slope/2) on the grid of row × column frequencies (cycles per pixel).

    f0 (``floor_cycles``, one DFT bin in practice) keeps the DC term finite; DC itself never enters the
    likelihood. The evidence uses full-resolution DFT grids, the AiF the rfft grid of a block.
    """
    return (f_row[:, None] ** 2 + f_col[None, :] ** 2 + floor_cycles ** 2) ** (-0.5 * slope)


def fold_power(power_full: np.ndarray, n_plane: int) -> np.ndarray:
    """(..., n, n): a 2n × 2n full-resolution power spectrum folded onto a plane's DFT bins.

    A plane samples every second full-resolution pixel, so plane bin (u, v) receives full-resolution
    bins (u + a n, v + b n), a, b ∈ {0, 1} (the aliases), each with weight ¼ in expectation; the
    constant is absorbed into the prior level β.
    """
    folded = power_full[..., :n_plane, :] + power_full[..., n_plane:, :]
    return folded[..., :, :n_plane] + folded[..., :, n_plane:]


EXPONENT_PRIOR = (2.0, 0.4)
"""Mean and spread of natural images' power-spectrum exponent (S ∝ 1/|f|^α): α scatters about 2 by about ±0.4 from one
image to the next (van der Schaaf & van Hateren, Vision Research 36, 1996). ``profile_exponent`` weighs the slopes it
profiles with this Gaussian prior."""


def profile_exponent(nll_by_slope: np.ndarray, slopes) -> np.ndarray:
    """(...) NLL with the texture's power exponent α profiled out of (A, ...) NLLs, one per prior slope of ``slopes``
    (A increasing, evenly spaced values; one slope: its NLL as it is).

    A window's planes see one surface, so they share one α: the NLLs given here are already summed over the planes.
    Each slope's NLL gets the prior's penalty (α − μ)² / 2s² (``EXPONENT_PRIOR``), and the minimum over α is the
    vertex of the parabola through the best slope and its two neighbours, clamped to them (at either end of the
    slopes, the end slope's value). Depth and α trade off only where the kernels change slowly with depth (beyond
    about 3 m), so profiling α costs precision there and removes the bias a texture steeper or flatter than 1/f²
    causes (``bmi bench texture``, ``bmi bench objects``).
    """
    nll_by_slope = np.asarray(nll_by_slope, np.float64)
    slopes = np.asarray(slopes, np.float64)
    if nll_by_slope.shape[0] != len(slopes):
        raise ValueError(f"profile_exponent needs one NLL per slope, got {nll_by_slope.shape[0]} for {len(slopes)}")
    if len(slopes) == 1:
        return nll_by_slope[0]
    mean, spread = EXPONENT_PRIOR
    penalty = (slopes - mean) ** 2 / (2.0 * spread ** 2)
    total = nll_by_slope + penalty.reshape((-1,) + (1,) * (nll_by_slope.ndim - 1))
    if len(slopes) == 2:
        return total.min(axis=0)
    return parabola_minimum(np.moveaxis(total, 0, -1))


def gated_exponent(pooled_by_slope: np.ndarray, slopes, gate_nats: float) -> tuple[np.ndarray, np.ndarray]:
    """((...) pooled NLL, (...[:-1]) bool: α profiled) from (A, ..., D) pooled NLLs, one per slope of ``slopes``, each
    window's pool over D candidates: α profiled out (``profile_exponent``) in the pools where that lowers the least NLL
    over the candidates by more than ``gate_nats`` below the prior's own α (``EXPONENT_PRIOR``, which must be among
    the slopes), that α's NLL elsewhere; ``gate_nats`` 0 profiles every pool.

    A likelihood-ratio test of the texture's exponent: a pool sums many windows' NLLs, so a surface whose spectrum
    falls steeper or flatter than 1/f² moves it by many nats, and one of 1/f² texture rarely does; there the prior's
    α is kept, which reads depth more precisely than α profiled (``bmi bench objects``). The windows of a pool
    overlap, so its NLL differences are not χ²-distributed and the gate is an empirical threshold, not a p-value.
    """
    pooled_by_slope = np.asarray(pooled_by_slope, np.float64)
    profiled = profile_exponent(pooled_by_slope, slopes)
    keep = np.ones(profiled.shape[:-1], bool)
    if gate_nats > 0:
        prior = list(np.asarray(slopes, np.float64)).index(EXPONENT_PRIOR[0])
        fixed = pooled_by_slope[prior]
        with np.errstate(invalid="ignore"):
            keep = np.nan_to_num(fixed.min(axis=-1) - profiled.min(axis=-1)) > gate_nats
        profiled = np.where(keep[..., None], profiled, fixed)
    return profiled.astype(np.float32), keep


def parabola_minimum(values: np.ndarray) -> np.ndarray:
    """(...) the least of (..., L ≥ 3) values on an evenly spaced grid along their last axis: the vertex of the parabola
    through the least value and its two neighbours (the end value's neighbours at either end), clamped to that
    bracket, and never above the least value itself (the β levels of ``plane_nll``, the slopes of
    ``profile_exponent``)."""
    j = np.clip(np.argmin(values, axis=-1), 1, values.shape[-1] - 2)
    take = lambda k: np.take_along_axis(values, k[..., None], axis=-1)[..., 0]  # noqa: E731
    lo, mid, hi = take(j - 1), take(j), take(j + 1)
    curv = lo - 2 * mid + hi
    # the parabola through the three levels, evaluated at its vertex clamped to the bracket
    offset = np.clip(0.5 * (lo - hi) / np.where(curv > 0, curv, np.inf), -1.0, 1.0)
    return np.minimum(mid + 0.5 * offset * (hi - lo) + 0.5 * curv * offset ** 2, values.min(axis=-1))


TAPER_OVERSAMPLE = 2
"""The taper's spectral window is applied on a grid this many times finer than the window's DFT bins."""


def folded_model(kernels: np.ndarray, n_plane: int, slope: float = 2.0) -> np.ndarray:
    """(..., n_plane, n_plane // 2 + 1) model power of a Hann-tapered plane window's rfft bins, per Σt².

    ``kernels`` (..., K, K) are full-resolution, centred, unit-sum kernels (K ≤ 2 n_plane). The plane's
    spectrum is Σ_aliases |K(f)|² S(f) (a plane samples every second full-resolution pixel), and the
    taper t smooths it: the expected periodogram of a tapered window is the spectrum convolved with
    the taper's spectral window, E|Y_t(ω)|² = ∫ |T(ω − ν)|² M(ν) dν (T the taper's DTFT). A near
    kernel's OTF oscillates about once per DFT bin of a 64-px window, so without the smoothing the
    model has zeros the data cannot show, and near candidates are wrongly penalised. The integral is
    evaluated on a grid ``TAPER_OVERSAMPLE`` times finer than the bins.
    """
    k = kernels.shape[-1]
    os_ = TAPER_OVERSAMPLE
    n_os = n_plane * os_
    n_full = 2 * n_os
    if k > 2 * n_plane:
        raise ValueError(f"a {k}-px kernel does not fit a {2 * n_plane}-px window")
    padded = np.zeros(kernels.shape[:-2] + (n_full, n_full), np.float32)
    padded[..., :k, :k] = kernels
    otf = sfft.rfft2(padded)                                               # a shift only changes phase
    f = sfft.fftfreq(n_full)
    power = (otf.real ** 2 + otf.imag ** 2) * power_law_prior(f, f[:n_full // 2 + 1], 1.0 / (2 * n_plane), slope)
    folded = fold_power(_full_from_half(power, n_full), n_os)              # (..., n_os, n_os) the plane's spectrum
    folded[..., 0, 0] = 0.0  # the window's mean is removed
    product = sfft.rfft2(folded) * _hann_window_ft(n_plane)
    # only every os_-th row of the inverse transform is kept: that is the inverse transform of the rows folded onto
    # n_plane (aliasing in reverse), over os_
    product = product.reshape(product.shape[:-2] + (os_, n_plane, product.shape[-1])).sum(axis=-3)
    rows = sfft.ifft(product, axis=-2) * (1.0 / os_)
    smoothed = sfft.irfft(rows, n=n_os, axis=-1)[..., ::os_]
    return np.asarray(smoothed[..., :, :n_plane // 2 + 1], np.float64)


EXACT_OVERSAMPLE = 4
"""``expected_periodogram``'s frequency grid is this many times finer than the window's DFT bins."""


def expected_periodogram(kernels: np.ndarray, n_plane: int, slope: float = 2.0,
                         oversample: int = EXACT_OVERSAMPLE) -> np.ndarray:
    """(..., n_plane, n_plane // 2 + 1) expected periodogram of a Hann-tapered plane window whose taper-weighted
    mean is removed, per Σt², under the plane spectrum M = Σ_aliases |K|² S: ``folded_model`` without its
    approximations at the lowest frequencies (``plane_autocovariance``, then ``tapered_periodogram``). A Monte Carlo
    periodogram matches it bin by bin, DC's neighbours included (``tests/test_decode.py``)."""
    return tapered_periodogram(plane_autocovariance(kernels, n_plane, slope, oversample), _hann_terms(n_plane))


class PlaneCovariance(NamedTuple):
    """A plane's autocovariance r(L) at the lags of an n × n window, on a 2n × 2n grid (lag L at index L mod 2n,
    |L| < n; index n holds 0), and its rfft2: what ``tapered_periodogram`` needs of a kernel."""

    r: np.ndarray      # (..., 2n, 2n)
    r_ft: np.ndarray   # (..., 2n, n + 1)


def plane_autocovariance(kernels: np.ndarray, n_plane: int, slope: float = 2.0,
                         oversample: int = EXACT_OVERSAMPLE) -> PlaneCovariance:
    """``PlaneCovariance`` of a Bayer plane under the plane spectrum M = Σ_aliases |K|² S of ``kernels`` (..., K, K),
    at the lags of an n = ``n_plane`` window: the part of ``tapered_periodogram``'s model that does not depend on
    the taper (a block's clipped windows share it).

    M is sampled on a grid ``oversample`` times finer than the window's bins (r then holds lags to ``oversample`` /
    2 windows before it wraps), and S's floor f0 is one bin of that grid at full resolution, so the prior reaches
    below the window's lowest frequency (``folded_model`` floors at one window bin). DC and the frequencies that
    fold onto it are left out: a constant, which the window's mean removal takes out under any taper.
    """
    k = kernels.shape[-1]
    n_os = n_plane * oversample
    n_full = 2 * n_os
    if k > 2 * n_plane:
        raise ValueError(f"a {k}-px kernel does not fit a {2 * n_plane}-px window")
    if oversample < 2:
        raise ValueError(f"oversample must be >= 2 (the autocovariance's lags reach a window), got {oversample}")
    # the kernel's rfft2 on the n_full grid, its k non-zero rows transformed first (a shift only changes phase);
    # float32 holds |K|² to ~1e-7 of its peak, the precision the sums below need in float64
    otf = sfft.fft(sfft.rfft(np.asarray(kernels, np.float32), n=n_full, axis=-1), n=n_full, axis=-2)
    power = (otf.real.astype(np.float64) ** 2 + otf.imag.astype(np.float64) ** 2) * _prior_half(n_full, slope)
    # the plane samples every second pixel: its autocovariance at lag L is the full field's at 2L (the fold of
    # the aliases in frequency), up to a constant factor that the prior level absorbs; R = F⁻¹[power] is taken
    # at those lags only: rows first, then the columns of the rows kept
    lags = np.r_[0:2 * n_plane:2, n_full - 2 * (n_plane - 1):n_full:2]    # 2L for L = 0 … n−1, −(n−1) … −1
    rows = sfft.ifft(power, axis=-2)[..., lags, :]
    r = sfft.irfft(rows, n=n_full, axis=-1)[..., lags]
    # on a 2n grid, lag L at index L mod 2n (index n, lag ±n, is beyond every window's lags: 0)
    r_circ = np.zeros(r.shape[:-2] + (2 * n_plane, 2 * n_plane))
    circ = np.r_[0:n_plane, n_plane + 1:2 * n_plane]
    r_circ[..., circ[:, None], circ[None, :]] = r
    return PlaneCovariance(r_circ, sfft.rfft2(r_circ))


def tapered_periodogram(covariance: PlaneCovariance, terms: "TaperTerms") -> np.ndarray:
    """(..., n, n // 2 + 1) expected periodogram, per Σt², of an n × n plane window tapered by a taper t (any: the
    Hann taper, or one zeroed at clipped samples, ``masked_window``; ``terms`` = ``taper_terms(t)``) whose
    taper-weighted mean is removed, for a plane of autocovariance r (``plane_autocovariance``).

    ``window_spectra`` computes Y(ω) = X_t(ω) − μ T(ω), X_t the tapered window's DFT, T the taper's and
    μ = Σ t x / T(0). With a_t the taper's autocorrelation and u = t ⊛ r on the window's samples,

        E|X_t(ω)|² = Σ_L a_t(L) r(L) e^(−iωL),   E[X_t(ω) μ] = DFT(t u)(ω) / T(0),   E[μ²] = Σ t u / T(0)²,
        E|Y(ω)|² = E|X_t|² − 2 Re(E[X_t μ] conj T(ω)) + E[μ²] |T(ω)|²:

    the first term the taper's smoothing (all ``folded_model`` holds), the others the mean's removal, which takes
    power from the bins next to DC under the Hann taper and from every bin under a taper with holes (its transform
    is broad). Every lag of a window is shorter than the window, so the sums are transforms of the window's size.
    """
    taper, taper_corr, pad_ft, taper_ft = terms
    n_plane = taper.shape[-1]
    # E|X_t|²: the lags folded onto the window's bins (L and L ± n meet at ω = 2πk/n; on the 2n grid, indices j and
    # j ± n)
    product = covariance.r * taper_corr
    folded = product.reshape(product.shape[:-2] + (2, n_plane, 2, n_plane)).sum(axis=(-4, -2))
    smoothed = sfft.rfft2(folded).real
    # u = t ⊛ r on the window: a circular convolution on the 2n grid holds every lag −(n−1) … n−1 unwrapped
    u = sfft.irfft2(covariance.r_ft * pad_ft, s=(2 * n_plane, 2 * n_plane))[..., :n_plane, :n_plane]
    tu = taper * u
    t0 = float(taper.sum())
    cross = sfft.rfft2(tu) / t0                                            # E[X_t μ]
    mean_power = tu.sum(axis=(-2, -1))[..., None, None] / t0 ** 2            # E[μ²]
    expected = smoothed - 2.0 * (cross * np.conj(taper_ft)).real + mean_power * np.abs(taper_ft) ** 2
    return expected / float((taper ** 2).sum())


@lru_cache(maxsize=8)
def _prior_half(n_full: int, slope: float) -> np.ndarray:
    """S on the rfft half of the n_full grid, floored at one of its bins; zero at DC and at the three
    frequencies that fold onto a plane's DC (a constant field, which the window's mean removal takes out)."""
    f = sfft.fftfreq(n_full)
    prior = power_law_prior(f, f[:n_full // 2 + 1], 1.0 / n_full, slope)
    prior[[0, 0, n_full // 2, n_full // 2], [0, n_full // 2, 0, n_full // 2]] = 0.0
    return prior


TaperTerms = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(t, a_t on the 2n grid, rfft2 of t zero-padded to 2n, rfft2 of t): what ``tapered_periodogram`` needs of an n × n
taper."""


def taper_terms(taper: np.ndarray) -> TaperTerms:
    """``TaperTerms`` of an n × n taper: the taper (float64), its autocorrelation a_t(L) = Σ_j t_j t_(j+L) on the 2n
    grid of ``PlaneCovariance`` (lag L at index L mod 2n; none wraps, and index n is 0) and the transforms
    ``tapered_periodogram`` multiplies by."""
    taper = np.asarray(taper, np.float64)
    n_plane = taper.shape[-1]
    pad = np.zeros((2 * n_plane, 2 * n_plane))
    pad[:n_plane, :n_plane] = taper
    pad_ft = sfft.rfft2(pad)
    corr = sfft.irfft2(np.abs(pad_ft) ** 2, s=pad.shape)
    corr[n_plane, :] = 0.0  # lag ±n: zero up to rounding, and beyond every window's lags
    corr[:, n_plane] = 0.0
    return taper, corr, pad_ft, sfft.rfft2(taper)


@lru_cache(maxsize=8)
def _hann_terms(n_plane: int) -> TaperTerms:
    """``taper_terms`` of the n_plane Hann taper (memoised; callers only read them)."""
    return taper_terms(hann_taper(n_plane))


def _full_from_half(half: np.ndarray, n: int) -> np.ndarray:
    """(..., n, n) the whole 2-D spectrum of a real signal from its rfft half (..., n, n//2+1): P(−f) = P(f)."""
    rest = half[..., :, 1:n - n // 2][..., :, ::-1]                         # columns n//2+1 .. n−1
    rest = np.roll(rest[..., ::-1, :], 1, axis=-2)                          # rows mirrored: −u
    return np.concatenate([half, rest], axis=-1)


@lru_cache(maxsize=8)
def _hann_window_ft(n_plane: int) -> np.ndarray:
    """rfft2 of the n_plane Hann taper's spectral window |DTFT t|² (unit sum) on the grid ``TAPER_OVERSAMPLE`` times
    finer than its bins: multiplying a spectrum's rfft2 by it convolves the spectrum with the window (circularly; the
    window decays as 1/f⁶). Memoised."""
    n_os = n_plane * TAPER_OVERSAMPLE
    pad = np.zeros((n_os, n_os))
    pad[:n_plane, :n_plane] = hann_taper(n_plane)
    window = np.abs(sfft.fft2(pad)) ** 2
    return sfft.rfft2(window / window.sum())


def rfft_multiplicity(n_plane: int, low_cycles_skipped: int = 1) -> np.ndarray:
    """(n, n//2+1) how many full-spectrum bins each rfft bin stands for (1 on the self-conjugate columns), 0 for
    the bins the evidence skips: those within ``low_cycles_skipped`` cycles per window of DC on both axes.

    DC and its eight neighbours are always skipped: the window's mean is removed, and through the taper that removal
    takes about half the expected power of the neighbouring bins (measured against a Monte Carlo periodogram,
    ``tests/test_decode.py``), which no stationary model holds; from two bins out the model matches to 1–2 %.
    Weak, sharp windows skip the next ring as well (``WEAK_TEXTURE_LOW_CYCLES``, ``classical.window_groups``).
    """
    if isinstance(low_cycles_skipped, bool) or not isinstance(low_cycles_skipped, (int, np.integer)) \
            or not 1 <= low_cycles_skipped <= n_plane // 4:
        raise ValueError(f"low_cycles_skipped must be an integer in [1, {n_plane // 4}] for {n_plane}-sample planes, "
                         f"got {low_cycles_skipped!r}")
    m = np.full((n_plane, n_plane // 2 + 1), 2.0)
    m[:, 0] = 1.0
    if n_plane % 2 == 0:
        m[:, -1] = 1.0
    rows = np.r_[0:low_cycles_skipped + 1, n_plane - low_cycles_skipped:n_plane]
    m[rows, :low_cycles_skipped + 1] = 0.0
    return m


WEAK_TEXTURE_LOW_CYCLES = 2
"""Cycles per window about DC that a weakly textured, sharp window's evidence skips (``classical.window_groups``)."""
TEXTURE_BAND_CYCLES = (3.0, 6.0)
"""The radial band (cycles per window, lower bound included) whose power measures a window's texture contrast
(``texture_bands``): above the lowest bins, below where the noise takes over a faint texture."""
SHARPNESS_BAND_CYCLES = (6.0, 12.0)
"""The band above it, whose texture power against the contrast band's says whether the kernel left the window sharp
(``texture_bands``)."""
SHARP_TEXTURE_RATIO = 0.05
"""A window's texture is sharp when its power per bin in ``SHARPNESS_BAND_CYCLES`` is at least this fraction of its
power per bin in ``TEXTURE_BAND_CYCLES``: a 1/f² texture the kernel leaves whole has 0.24 (the bands' mean 1/f²), a
near surface's defocus empties the upper band (about 0)."""


def texture_bands(spectra: list, means: list, noise_vars: list, taper_energy: float) -> tuple[np.ndarray, np.ndarray]:
    """(contrast, sharpness), each (windows,): a window's texture contrast in ``TEXTURE_BAND_CYCLES`` and its texture
    power per bin in ``SHARPNESS_BAND_CYCLES`` over that in ``TEXTURE_BAND_CYCLES``, from the four planes' window
    spectra (``window_spectra``: power, t²-weighted means) and noise variances.

    A tapered periodogram's expected power at a bin is Σt² × (the field's power per bin + the noise variance), so
    mean(P) / Σt² − σ² over a band's bins is the texture's power per bin there (the variance of a white texture of
    that level); its square root over the window's mean signal is the contrast, the same at any exposure. On
    ``bmi bench objects``' 1/f² walls of contrast (std over mean) 0.3 and 0.03, the median 64-px window reads 0.33–0.37
    and 0.034–0.037. The contrast is infinite (never weak) where a window's mean is not positive, the sharpness 0
    where the contrast band holds no texture above the noise."""
    n = spectra[0].shape[1]
    ky = np.fft.fftfreq(n) * n
    kx = np.arange(spectra[0].shape[2])
    radius = np.hypot(ky[:, None], kx[None, :])

    def power(cycles: tuple) -> np.ndarray:  # (windows,) texture power per bin in the band, noise out, over the planes
        band = (radius >= cycles[0]) & (radius < cycles[1])
        return np.mean([np.asarray(s)[:, band].mean(axis=1) / taper_energy - np.asarray(v, np.float64)
                        for s, v in zip(spectra, noise_vars)], axis=0)

    texture, upper = power(TEXTURE_BAND_CYCLES), power(SHARPNESS_BAND_CYCLES)
    mean = np.mean([np.asarray(m, np.float64) for m in means], axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = np.where(mean > 0, np.sqrt(np.maximum(texture, 0.0)) / mean, np.inf)
        sharpness = np.where(texture > 0, upper / texture, 0.0)
    return contrast, sharpness


def window_spectra(plane: np.ndarray, n_plane: int, stride_plane: int, taper: np.ndarray,
                   threads: int = 1) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Power spectra (rows × cols, n, n//2+1) float32 of the tapered, mean-removed n × n windows of a plane.

    Windows start every ``stride_plane`` samples. Returns the spectra, each window's t²-weighted mean
    signal (what its noise variance follows under signal-dependent noise: the noise power a tapered
    window passes is Σ t² Var[x], ``plane_nll``) and the (rows, cols) grid shape.
    """
    view = np.lib.stride_tricks.sliding_window_view(plane, (n_plane, n_plane))[::stride_plane, ::stride_plane]
    rows, cols = view.shape[:2]
    w = view.reshape(rows * cols, n_plane, n_plane).astype(np.float32)
    tsum = float(taper.sum())
    taper_sq = taper * taper
    noise_mean = np.einsum("nij,ij->n", w, taper_sq) / float(taper_sq.sum())
    mean = np.einsum("nij,ij->n", w, taper) / tsum
    w = (w - mean[:, None, None]) * taper
    spec = sfft.rfft2(w, workers=threads)
    return (spec.real ** 2 + spec.imag ** 2).astype(np.float32), noise_mean, (rows, cols)


def inverse_depth_information(model: np.ndarray, inv_depth_per_m: np.ndarray, beta_rel: float) -> np.ndarray:
    """(D,) Fisher information about 1/d (m²) of one plane's window at each candidate depth, β a nuisance.

    ``model`` (D, n, m) is ``folded_model`` × the taper energy and ``beta_rel`` the prior level in units of the
    window's noise power, so V = β' A_d + 1 (``plane_nll``). With g = ∂ log V / ∂(1/d), h = ∂ log V / ∂ log β'
    and the likelihood's ½ count (module doc), I = ½ Σ m g², ½ Σ m g h, ½ Σ m h² form the 2 × 2 information and
    the nuisance is removed by its Schur complement. ∂A / ∂(1/d) is the central difference over the candidates.
    The informations of the planes add; 1 / √I is the Cramér–Rao bound of the estimate from an untapered window,
    which a tapered one exceeds by √``taper_variance_inflation``.
    """
    mult = rfft_multiplicity(model.shape[1]) * REAL_FIELD_WEIGHT
    a = np.asarray(model, np.float64)
    v = beta_rel * a + 1.0
    g = beta_rel * np.gradient(a, np.asarray(inv_depth_per_m, np.float64), axis=0) / v
    h = beta_rel * a / v
    i_uu, i_ub, i_bb = ((mult * x * y).sum(axis=(1, 2)) for x, y in ((g, g), (g, h), (h, h)))
    return i_uu - i_ub ** 2 / i_bb


def windows_touching(mask: np.ndarray, n_plane: int, stride_plane: int) -> np.ndarray:
    """(rows × cols,) bool: which of ``window_spectra``'s windows (same grid) hold at least one set sample."""
    if not mask.any():
        rows = (mask.shape[0] - n_plane) // stride_plane + 1
        cols = (mask.shape[1] - n_plane) // stride_plane + 1
        return np.zeros(rows * cols, bool)
    view = np.lib.stride_tricks.sliding_window_view(mask, (n_plane, n_plane))[::stride_plane, ::stride_plane]
    return view.any(axis=(2, 3)).ravel()


@dataclass
class Evidence:
    """NLL(window, candidate) summed over the planes, and what the refinement needs.

    ``nll``: (rows, cols, D) float64 negative log-likelihood (up to a constant per window);
    ``inv_depth_per_m``: (D,) candidate 1/d in m⁻¹, monotonic.
    """

    nll: np.ndarray
    inv_depth_per_m: np.ndarray

    def refine(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth_m, sigma_inv_depth_per_m, best_index) from a parabola in 1/d through the best candidate.

        The parabola passes through the best candidate and its two neighbours at their own 1/d (the
        candidates need not be evenly spaced). Its vertex, clamped to the neighbours, is the estimate;
        its second derivative h gives the Laplace-approximation 1σ of 1/d, 1 / sqrt(h). At either
        end of the list the end candidate is kept and h is taken from the one-sided difference.
        """
        nll, x = self.nll, np.asarray(self.inv_depth_per_m, dtype=np.float64)
        d = nll.shape[-1]
        best = np.argmin(nll, axis=-1)
        i = np.clip(best, 1, d - 2)
        take = lambda k: np.take_along_axis(nll, k[..., None], axis=-1)[..., 0]  # noqa: E731
        y0, y1, y2 = take(i - 1), take(i), take(i + 1)
        x0, x1, x2 = x[i - 1], x[i], x[i + 1]
        s01, s12 = (y1 - y0) / (x1 - x0), (y2 - y1) / (x2 - x1)
        h = 2.0 * (s12 - s01) / (x2 - x0)
        safe = np.where(h > 0, h, 1.0)
        vertex = 0.5 * (x0 + x1) - s01 / safe  # where the derivative of the parabola vanishes
        vertex = np.where(h > 0, np.clip(vertex, np.minimum(x0, x2), np.maximum(x0, x2)), x1)
        edge = (best == 0) | (best == d - 1)
        j = np.where(best == 0, 1, d - 2)
        gap = np.abs(x[j] - x[best])
        with np.errstate(invalid="ignore", divide="ignore"):  # only read where best is an end (gap > 0)
            h_edge = 2.0 * np.maximum(take(j) - take(best), 0.0) / gap ** 2
        inv = np.where(edge, x[best], vertex)
        h = np.where(edge, h_edge, h)
        sigma_inv = 1.0 / np.sqrt(np.maximum(h, 1e-12))
        return 1.0 / np.maximum(inv, 1e-6), sigma_inv, best


def plane_nll(power: np.ndarray, model: np.ndarray, noise_var, taper_energy: float,
              grid_model: np.ndarray | None = None, low_cycles_skipped: int = 1) -> np.ndarray:
    """(windows, D) NLL of one plane's window spectra, β profiled out (module doc).

    ``power`` (windows, n, m) float32; ``model`` (D, n, m) = Σ_aliases |K_d|² S per candidate;
    ``noise_var``: the raw noise variance, one value or one per window (signal-dependent noise,
    ``sensor.NoiseProfile``). Each window is measured in units of its own noise power s: with
    P' = P / s and β' = β / s, P / V + log V = P' / (β' A + 1) + log(β' A + 1) + log s, so one grid of
    β' and one matrix product serve windows of every noise level, exactly; the log s term is the
    same for every candidate of a window and is kept, so the NLL is the true one; the bins are those
    ``rfft_multiplicity`` keeps (``low_cycles_skipped``), each counted with the ½ of the module doc.
    ``grid_model``: the candidates whose gains place the β grid (default ``model``'s own). The grid's
    levels change the profiled NLL by up to a few tenths of a nat, so NLLs that are compared with each
    other (a coarse pass's and the fine pass that completes it) must share one grid.
    """
    nw = power.shape[0]
    n_cand = model.shape[0]
    mult = rfft_multiplicity(model.shape[1], low_cycles_skipped)
    keep = mult > 0

    def bins(m: np.ndarray) -> np.ndarray:  # (candidates, F): the kept bins of models, in units of the taper's energy
        return m.reshape(m.shape[0], -1)[:, keep.ravel()] * taper_energy

    a = bins(model)                                                       # (D, F)
    mult = mult[keep] * REAL_FIELD_WEIGHT
    s = np.maximum(np.broadcast_to(np.asarray(noise_var, np.float64), (nw,)), 1e-12) * taper_energy  # (W,)
    p = power.reshape(nw, -1)[:, keep.ravel()] * (1.0 / s)[:, None].astype(np.float32)  # P' (W, F)
    # moment estimate of β' per window and candidate: Σ m P' ≈ β' Σ m A + Σ m
    total = p @ mult                                                      # (W,)
    gain = (a if grid_model is None else bins(grid_model)) @ mult          # (D,) of the grid's candidates
    excess = np.maximum(total - mult.sum(), 1e-3 * total + 1e-30)
    lo = np.log(max(float(excess.min() / gain.max()), 1e-30) * BETA_MARGIN[0])
    hi = np.log(float(excess.max() / gain.min()) * BETA_MARGIN[1])
    n_beta = int(np.clip(np.ceil((hi - lo) / np.log(BETA_RATIO)) + 1, 3, MAX_BETA_LEVELS))
    # float32 (a few 1e-3 nats on NLLs of ~1e3), and C-contiguous weights: a transposed operand makes the
    # product ~10x slower (docs/benchmarks.md, "The camera's noise, the tapered window model, …")
    beta = np.exp(np.linspace(lo, hi, n_beta)).astype(np.float32)
    v = (beta[None, :, None] * a.astype(np.float32)[:, None, :] + np.float32(1.0)).reshape(n_cand * n_beta, -1)
    mult32 = mult.astype(np.float32)
    weights = np.ascontiguousarray((mult32 / v).T)                          # (F, D·J)
    log_term = (np.log(v) @ mult32).astype(np.float64)                       # (D·J,)
    nll = (p @ weights).astype(np.float64) + log_term                        # (W, D·J)
    nll = nll.reshape(nw, n_cand, n_beta) + (mult.sum() * np.log(s))[:, None, None]
    return parabola_minimum(nll)
