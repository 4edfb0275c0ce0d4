"""Wavelength samples per colour channel.

The paper's baseline model uses one representative wavelength per channel
(R 656.3, G 587.6, B 486.1 nm: the C, d and F lines). Its spectral option
integrates each channel over 13 wavelengths weighted by an RGB response;
``bmi_sdk/data/spectral/rgb_response.json`` holds the response model used
(Gaussian stand-ins, documented as such). A channel is a list of
(wavelength_nm, weight) pairs with weights summing to 1.
"""

from __future__ import annotations

import json
from importlib import resources

import numpy as np

CHANNELS = ("R", "G", "B")
REPRESENTATIVE_NM = {"R": 656.3, "G": 587.6, "B": 486.1}


def wavelengths_nm(channels) -> list[float]:
    """Every wavelength the channels sample, sorted and each once (so each is traced once)."""
    return sorted({lam for ch in channels for lam, _ in ch})


def channel_kernels(mono_by_nm, channels, clip_negative: bool = False) -> np.ndarray:
    """(C, ..., K, K) float64 unit-sum kernels of each colour channel from its monochromatic kernels.

    The one place where monochromatic PSFs become a channel's PSF: ``mono_by_nm`` maps a
    wavelength (nm) to kernels (..., K, K); channel c's kernel is Σ w_λ k_λ over its
    (wavelength, weight) pairs, renormalised to unit sum per kernel (the pixel-integrated
    PSF of a channel whose spectral response is those weights). ``clip_negative`` clips
    below 0 before normalising: a fitted glare fraction slightly below 0 (an honest
    estimate, ``optics.perturb``) must not make negative wings.
    """
    out = np.stack([sum(w * np.asarray(mono_by_nm[lam], dtype=np.float64) for lam, w in ch) for ch in channels])
    if clip_negative:
        out = np.maximum(out, 0.0)
    return out / out.sum(axis=(-2, -1), keepdims=True)


def representative() -> list[list[tuple[float, float]]]:
    return [[(REPRESENTATIVE_NM[c], 1.0)] for c in CHANNELS]


def response_model() -> dict:
    item = resources.files("bmi_sdk") / "data" / "spectral" / "rgb_response.json"
    return json.loads(item.read_text())


def integrated(samples: int | None = None) -> list[list[tuple[float, float]]]:
    """Per channel, ``samples`` wavelengths across ±2σ of its response (inside the band)."""
    model = response_model()
    n = samples or model["samples_per_channel"]
    lo, hi = model["band_nm"]
    out = []
    for c in CHANNELS:
        ch = model["channels"][c]
        lam = np.linspace(max(lo, ch["peak_nm"] - 2 * ch["sigma_nm"]), min(hi, ch["peak_nm"] + 2 * ch["sigma_nm"]), n)
        w = np.exp(-0.5 * ((lam - ch["peak_nm"]) / ch["sigma_nm"]) ** 2)
        w /= w.sum()
        out.append([(float(a), float(b)) for a, b in zip(lam, w)])
    return out
