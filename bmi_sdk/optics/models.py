"""The paper's fast approximations, kept to measure how far they are from the trace.

* ``ellipse_fit``: the on-axis traced pupil with its aperture compressed by
  cos θ along the radial direction (paper Eq. 2: for an exactly concentric
  lens the aberration relative to the chief ray does not change with field,
  only the stop is seen obliquely). One trace per (d, λ) serves every field.
* ``two_term_fit``: the wavefront replaced by the paper's Eq. 1,
  W = W020 ρ² + W040 ρ⁴, with ρ the normalised stop radius (ρ² is the fitted
  stop aperture function) and the coefficients given.
Both return a :class:`PupilFit` that ``psf_from_pupil`` accepts; the ellipse
model also needs ``aperture_l_scale=cos θ`` (see :func:`ellipse_psf`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.signal import convolve2d

from .psf import Psf, psf_from_pupil
from .pupil import PupilFit


def ellipse_psf(on_axis: PupilFit, field_deg: float, kernel_px: int, **kwargs) -> Psf:
    """PSF at ``field_deg`` from the on-axis pupil and a cos θ-compressed aperture."""
    if on_axis.field_deg != 0.0:
        raise ValueError("the ellipse model starts from the on-axis pupil (field 0°)")
    return psf_from_pupil(on_axis, kernel_px, aperture_l_scale=math.cos(math.radians(field_deg)), **kwargs)


def _pad(c: np.ndarray, size: int) -> np.ndarray:
    out = np.zeros((size, size))
    out[: c.shape[0], : c.shape[1]] = c
    return out


def two_term_fit(fit: PupilFit, w020_waves: float, w040_waves: float) -> PupilFit:
    """``fit`` with its wavefront replaced by W020 ρ² + W040 ρ⁴ (ρ² = the stop function)."""
    rho2 = fit.coeffs["stop"]
    rho4 = convolve2d(rho2, rho2)  # product of two polynomials = convolution of coefficient arrays
    size = rho4.shape[0]
    coeffs = {k: _pad(v, size) for k, v in fit.coeffs.items()}
    coeffs["w_waves"] = w020_waves * _pad(rho2, size) + w040_waves * rho4
    return replace(fit, coeffs=coeffs, degree=size - 1)
