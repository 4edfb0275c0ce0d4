"""The traced axial wavefront and the paper's two-term model.

On axis the exact wavefront is W(ρ) with ρ the normalised stop height. It is
traced directly (a meridional fan aimed at the real stop) and referred to the
point where the chief ray meets the sensor, so W020 is the defocus the sensor
actually sees. The fit W(ρ) = Σ_{k=1..5} c_k ρ^{2k} (area-weighted least
squares) gives the reported W020, W040, W060; ``rms_waves`` is the RMS of the
traced W over the pupil area with piston removed. The paper's Eq. (1) keeps
only W020 ρ² + W040 ρ⁴; ``two_term_rms_error_waves`` is how far its best fit
is from the traced wavefront.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .paraxial import entrance_pupil, indices
from .prescription import Lens
from .pupil import _aim, _chief, _launch, stop_radius_mm
from .raytrace import trace

N_TERMS = 5


@dataclass
class AxialWavefront:
    wavelength_nm: float
    depth_m: float
    w020_waves: float
    w040_waves: float
    w060_waves: float
    rms_waves: float
    two_term_w020_waves: float
    two_term_w040_waves: float
    two_term_rms_error_waves: float

    def row(self) -> dict:
        d = asdict(self)
        d["depth_m"] = None if math.isinf(self.depth_m) else self.depth_m
        return d


def traced_axial_wavefront(lens: Lens, wavelength_nm: float, depth_m: float, n_rays: int = 401):
    """(ρ, W in waves) along the meridian, ρ ∈ [0, 1] normalised stop height."""
    lam_um = wavelength_nm * 1e-3
    n = indices(lens, lam_um)
    z_ep, per_ep = entrance_pupil(lens, n)
    r_stop = stop_radius_mm(lens)
    one = lambda x: np.array([x], dtype=np.float64)  # noqa: E731  (batch of one entry)
    b_c, b_lo, b_hi, _ = _aim(lens, one(0.0), one(depth_m), one(lam_um), one(z_ep), one(r_stop / abs(per_ep)), r_stop)
    _, chief_p, _, chief_opl = _chief(lens, one(0.0), one(depth_m), one(lam_um), one(z_ep), b_c, r_stop)
    b = np.linspace(0.0, max(abs(b_lo[0]), abs(b_hi[0])) * 1.02, n_rays)
    o, d, opl = _launch(lens, one(0.0), one(depth_m), one(z_ep), np.zeros((1, n_rays)), b[None, :])
    rays = trace(lens, lam_um, o, d, opl)
    rho = np.abs(rays.stop_xy_mm[0, :, 1]) / r_stop
    s = rays.direction[0]
    v = rays.opl_mm[0] + n[-1] * np.einsum("ij,ij->i", s, chief_p[0][None, :] - rays.position[0])
    w = (chief_opl[0] - v) / (lam_um * 1e-3)  # Welford's sign, as in pupil.py
    keep = rays.alive[0] & (rho <= 1.0)
    order = np.argsort(rho[keep])
    return rho[keep][order], w[keep][order]


def _area_fit(rho, w, powers):
    """Least squares of w on ρ^powers with the pupil-area weight 2ρ dρ (trapezoid rule)."""
    weights = np.gradient(rho) * 2 * rho
    basis = np.stack([rho**p for p in powers], axis=1)
    sw = np.sqrt(weights)
    coef, *_ = np.linalg.lstsq(basis * sw[:, None], w * sw, rcond=None)
    return coef, basis @ coef, weights


def axial_wavefront(lens: Lens, wavelength_nm: float, depth_m: float) -> AxialWavefront:
    rho, w = traced_axial_wavefront(lens, wavelength_nm, depth_m)
    coef, _, weights = _area_fit(rho, w, [0] + [2 * k for k in range(1, N_TERMS + 1)])
    mean = np.sum(w * weights) / weights.sum()
    rms = math.sqrt(np.sum((w - mean) ** 2 * weights) / weights.sum())
    coef2, fit2, _ = _area_fit(rho, w, [0, 2, 4])
    err2 = math.sqrt(np.sum((w - fit2) ** 2 * weights) / weights.sum())
    return AxialWavefront(
        wavelength_nm=wavelength_nm, depth_m=float(depth_m), w020_waves=float(coef[1]), w040_waves=float(coef[2]),
        w060_waves=float(coef[3]), rms_waves=rms, two_term_w020_waves=float(coef2[1]),
        two_term_w040_waves=float(coef2[2]), two_term_rms_error_waves=err2,
    )
