"""All-in-focus image: Wiener deconvolution with the kernels of each pixel's decoded depth.

For one block of a demosaiced channel with spectrum Y and a candidate kernel with OTF K_d, the
Wiener estimate under the evidence's own prior (power β S(f), S = 1/|f|²) and white noise σ² is

    X̂_d = conj(K_d) Y / (|K_d|² + σ² / (β S))

(the posterior mean of the Gaussian model in ``evidence``). Every pixel's decoded 1/d lies between
two neighbouring candidates; its AiF value is the blend of their two deconvolutions, linear in
1/d. Only the candidates that some pixel of the block needs are deconvolved. β per channel comes
from the block's own power (moment estimate under the block's median-depth kernel).
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


def wiener_blend(rgb: np.ndarray, inv_depth: np.ndarray, candidate_inv: np.ndarray, kernels_of,
                 noise_sigma: float, core: tuple[slice, slice], threads: int = 1) -> np.ndarray:
    """AiF of a block's ``core`` (rows, cols) from its demosaiced ``rgb`` (h × w × 3, with halo).

    ``inv_depth``: the core's per-pixel 1/d; ``kernels_of(indices)`` → (3, n, K, K) kernels of those
    candidates. All candidates' OTFs and deconvolutions go through one batched FFT each, on
    ``threads`` threads. Returns the core's AiF, (core h × core w × 3) float32.
    """
    h, w, _ = rgb.shape
    lo, frac = bracket(inv_depth, candidate_inv)
    needed = np.unique(np.concatenate([lo[frac < 1], lo[frac > 0] + 1]))
    kernels = kernels_of(needed)                                # (3, n, K, K)
    k = kernels.shape[-1]
    spectrum = sfft.rfft2(np.ascontiguousarray(rgb.transpose(2, 0, 1), np.float32), workers=threads)  # (3, h, m)
    s = power_law_prior(sfft.fftfreq(h), sfft.rfftfreq(w), 1.0 / max(h, w)).astype(np.float32)
    padded = np.zeros((len(needed), 3, h, w), np.float32)
    padded[..., :k, :k] = kernels.transpose(1, 0, 2, 3)
    otf = sfft.rfft2(np.roll(padded, (-(k // 2), -(k // 2)), axis=(-2, -1)), workers=threads)  # (n, 3, h, m)
    del padded
    power = otf.real ** 2 + otf.imag ** 2
    beta = _prior_level(spectrum, power, s, noise_sigma, h * w)          # (n, 3)
    gain = np.conj(otf) / (power + (np.float32(noise_sigma ** 2) / beta.astype(np.float32))[..., None, None] / s)
    restored = sfft.irfft2(gain * spectrum[None], s=(h, w), workers=threads)[..., core[0], core[1]]
    out = np.zeros(inv_depth.shape + (3,), np.float32)
    for n, j in enumerate(needed):
        weight = np.where(lo == j, 1.0 - frac, 0.0) + np.where(lo + 1 == j, frac, 0.0)
        out += (weight[..., None] * restored[n].transpose(1, 2, 0)).astype(np.float32)
    return out


def _prior_level(spectrum: np.ndarray, power: np.ndarray, s: np.ndarray, noise_sigma: float,
                 n_px: int) -> np.ndarray:
    """(n, C) β of the prior β S per candidate and channel from the block's power:
    Σ |Y|² ≈ Σ (β |K|² S + σ²) n_px over the non-DC bins (``spectrum`` (C, h, m), ``power`` (n, C, h, m))."""
    p = (spectrum.real ** 2 + spectrum.imag ** 2) / n_px
    p[..., 0, 0] = 0.0
    model = power * s
    model[..., 0, 0] = 0.0
    excess = np.maximum(p.sum(axis=(-2, -1)) - noise_sigma ** 2 * (p[0].size - 1), 1e-12)   # (C,)
    return excess[None, :] / np.maximum(model.sum(axis=(-2, -1)), 1e-30)
