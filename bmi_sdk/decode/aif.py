"""All-in-focus image: Wiener deconvolution with the kernels of each pixel's decoded depth.

For one block of a demosaiced channel with spectrum Y and a candidate kernel with OTF K_d, the
Wiener estimate under the evidence's own prior (power β S(f), S = 1/|f|²) and white noise σ² is

    X̂_d = conj(K_d) Y / (|K_d|² + σ² / (β S))

(the posterior mean of the Gaussian model in ``evidence``). Every pixel's decoded 1/d lies between
two neighbouring candidates; its AiF value is the blend of their two deconvolutions, linear in
1/d. Only the candidates that some pixel of the block needs are deconvolved. β per channel comes
from the block's own power (moment estimate under the block's median-depth kernel).

The same model with a prior mean X₀ other than 0 (a data-consistency step): the posterior mean is

    X̂_d = X₀ + conj(K_d) R / (|K_d|² + σ² / (β S)),   R = Y − B X₀,

B X₀ the prior image blurred by the kernels of each pixel's depth (blended as above) and β now the
level of what R holds beyond the noise. X₀ is another decoder's AiF (the learned refinement's network):
where it already explains the raw frame through the camera's kernels, R is noise and X̂ ≈ X₀; where
it does not (a network trained on the nominal camera decoding a built one, whose kernels are shifted
and reshaped), the calibrated kernels pull it back to what the frame shows (docs/decoder.md).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from .evidence import power_law_prior


def bracket(inv_depth: np.ndarray, candidate_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower candidate index, weight of the next one): each 1/d as a linear blend of two neighbouring
    candidates (candidates ordered by increasing depth, i.e. decreasing 1/d); clamped at both ends."""
    n = len(candidate_inv)
    pos = np.interp(-inv_depth, -candidate_inv, np.arange(n))
    lo = np.minimum(np.floor(pos).astype(int), n - 2)
    return lo, pos - lo


def _needed(lo: np.ndarray, frac: np.ndarray, n_candidates: int) -> np.ndarray:
    """The candidate indices (of ``n_candidates``) a bracketed map blends: those with a non-zero weight somewhere."""
    used = np.zeros(n_candidates, bool)
    used[lo[frac < 1]] = True
    used[lo[frac > 0] + 1] = True
    return np.flatnonzero(used)


def _blend(per_candidate, lo: np.ndarray, frac: np.ndarray, needed: np.ndarray) -> np.ndarray:
    """(h × w × 3) float32: each pixel's blend of ``per_candidate[n]`` (3 × h × w, candidate ``needed[n]``) by its
    bracket (``lo``, ``frac``): (1 − frac) of its lower candidate's value and frac of the next one's, each gathered
    from its own candidate (a candidate of weight 0 is gathered from slot 0 and counts 0)."""
    slot = np.zeros(int(needed[-1]) + 2, np.intp)
    slot[needed] = np.arange(len(needed))
    rows, cols = np.arange(lo.shape[0])[:, None], np.arange(lo.shape[1])[None, :]
    weight = frac.astype(np.float32)[..., None]
    out = per_candidate[slot[lo], :, rows, cols]      # (h, w, 3): the candidate index and the pixel index
    upper = per_candidate[slot[lo + 1], :, rows, cols]  # arrays are advanced, so they lead
    out *= 1 - weight
    upper *= weight
    out += upper
    return out


def wiener_blend(rgb: np.ndarray, inv_depth: np.ndarray, candidate_inv: np.ndarray, kernels_of,
                 noise_sigma: float, core: tuple[slice, slice], threads: int = 1, prior: np.ndarray | None = None,
                 prior_inv_depth: np.ndarray | None = None) -> np.ndarray:
    """AiF of a block's ``core`` (rows, cols) from its demosaiced ``rgb`` (h × w × 3, with halo).

    ``inv_depth``: the core's per-pixel 1/d; ``kernels_of(indices)`` → (3, n, K, K) kernels of those
    candidates. All candidates' OTFs and deconvolutions go through one batched FFT each, on
    ``threads`` threads. ``prior`` (h × w × 3, the whole block in ``rgb``'s units) is the image model's mean
    (module doc), blurred by the kernels of ``prior_inv_depth`` (h × w 1/d, the whole block); None: mean 0, the
    plain Wiener AiF. Returns the core's AiF, (core h × core w × 3) float32.
    """
    h, w, _ = rgb.shape
    lo, frac = bracket(inv_depth, candidate_inv)
    needed = core_needed = _needed(lo, frac, len(candidate_inv))
    if prior is not None:  # the prior is blurred over the whole block, whose halo may need further candidates
        if prior_inv_depth is None:
            raise ValueError("wiener_blend: a prior needs prior_inv_depth, the 1/d its kernels blur it with")
        prior_lo, prior_frac = bracket(prior_inv_depth, candidate_inv)
        needed = np.union1d(core_needed, _needed(prior_lo, prior_frac, len(candidate_inv)))
    kernels = kernels_of(needed)                                # (3, n, K, K)
    k = kernels.shape[-1]
    padded = np.zeros((len(needed), 3, h, w), np.float32)
    padded[..., :k, :k] = kernels.transpose(1, 0, 2, 3)
    otf = sfft.rfft2(np.roll(padded, (-(k // 2), -(k // 2)), axis=(-2, -1)), workers=threads)  # (n, 3, h, m)
    del padded
    data = np.ascontiguousarray(rgb.transpose(2, 0, 1), np.float32)
    if prior is not None:
        prior_spectrum = sfft.rfft2(np.ascontiguousarray(prior.transpose(2, 0, 1), np.float32), workers=threads)
        blurred = sfft.irfft2(otf * prior_spectrum[None], s=(h, w), workers=threads)  # (n, 3, h, w)
        data = data - _blend(blurred, prior_lo, prior_frac, needed).transpose(2, 0, 1)
        del blurred
    spectrum = sfft.rfft2(data, workers=threads)                # (3, h, m)
    excess = _excess_power(spectrum, noise_sigma, h * w)
    if prior is not None and not (excess > 0).any():  # the prior explains the block within the noise: β = 0
        return prior[core].copy()
    if len(core_needed) < len(needed):  # only the core's candidates are deconvolved
        otf = otf[np.searchsorted(needed, core_needed)]
    s = power_law_prior(sfft.fftfreq(h), sfft.rfftfreq(w), 1.0 / max(h, w)).astype(np.float32)
    power = otf.real ** 2 + otf.imag ** 2
    beta = _prior_level(excess, power, s)                       # (n, 3)
    inverse = power  # 1 / (|K|² + σ² / (β S)), in place of |K|²: real, so the gain needs no complex division
    inverse += (np.float32(noise_sigma ** 2) / beta.astype(np.float32))[..., None, None] / s
    np.reciprocal(inverse, out=inverse)
    restored = np.conj(otf)
    restored *= spectrum[None]
    restored *= inverse
    restored = sfft.irfft2(restored, s=(h, w), workers=threads)[..., core[0], core[1]]
    out = _blend(restored, lo, frac, core_needed)
    if prior is not None:
        out += prior[core]
    return out


def _excess_power(spectrum: np.ndarray, noise_sigma: float, n_px: int) -> np.ndarray:
    """(C,) the block's power beyond the noise, Σ |Y|² / n_px − σ² (n_px − 1) over the non-DC bins
    (``spectrum`` (C, h, m), an rfft2): what the prior β |K|² S has to explain; ≤ 0 when the noise explains it all."""
    p = (spectrum.real ** 2 + spectrum.imag ** 2) / n_px
    p[..., 0, 0] = 0.0
    return p.sum(axis=(-2, -1)) - noise_sigma ** 2 * (p[0].size - 1)


def _prior_level(excess: np.ndarray, power: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(n, C) β of the prior β S per candidate and channel from the block's ``excess`` power (``_excess_power``):
    Σ |Y|² ≈ Σ (β |K|² S + σ²) n_px over the non-DC bins (``power`` |K|², (n, C, h, m))."""
    model = power * s
    model[..., 0, 0] = 0.0
    return np.maximum(excess, 1e-12)[None, :] / np.maximum(model.sum(axis=(-2, -1)), 1e-30)
