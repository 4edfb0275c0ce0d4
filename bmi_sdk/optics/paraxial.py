"""Paraxial (first-order) optics and third-order Seidel sums.

y–nu trace with the refraction equation n'u' = nu − y c (n' − n) and transfer
y₊ = y + t u' (u are slopes, Welford's sign convention). The Seidel sums follow
Welford, *Aberrations of Optical Systems* (1986), §8.3:
A = n(u + y c), S_I = −Σ A² y Δ(u/n), S_II = −Σ A Ā y Δ(u/n),
S_III = −Σ Ā² y Δ(u/n), S_IV = −Σ H² c Δ(1/n), H = n(ū y − u ȳ),
and wavefront coefficients W040 = S_I/8, W131 = S_II/2, W222 = S_III/2,
W220 = (S_III + S_IV)/4. A positive singlet has S_I > 0 (under-corrected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .glass import refractive_index
from .prescription import Lens, PrescriptionError

LAMBDA_D_NM = 587.6


def indices(lens: Lens, wavelength_um: float) -> np.ndarray:
    """Index of every medium: object space, after surface 1, …, image space."""
    return np.array([float(refractive_index(m, wavelength_um)) for m in lens.media()])


def _trace(lens: Lens, n: np.ndarray, y0: float, u0: float, upto: int | None = None):
    """Paraxial ray starting at surface 1 with height y0 and object-space slope u0.

    Returns per-surface heights y, slopes before (u) and after (u') each surface.
    """
    surfaces = lens.surfaces if upto is None else lens.surfaces[:upto]
    ys, us, ups = [], [], []
    y, u = y0, u0
    for j, s in enumerate(surfaces):
        c = s.curvature_per_mm
        up = (n[j] * u - y * c * (n[j + 1] - n[j])) / n[j + 1]
        ys.append(y), us.append(u), ups.append(up)
        y = y + s.thickness_mm * up
        u = up
    return np.array(ys), np.array(us), np.array(ups), y, u


@dataclass(frozen=True)
class FirstOrder:
    wavelength_nm: float
    efl_mm: float
    bfd_mm: float  # last surface vertex -> paraxial focus (object at infinity)
    epd_mm: float
    entrance_pupil_z_mm: float  # from surface 1 vertex
    stop_radius_mm: float  # working aperture radius at the stop for the EPD
    f_number: float
    petzval_radius_mm: float
    image_distance_mm: float  # last surface vertex -> paraxial image of the given object
    seidel: dict


def entrance_pupil(lens: Lens, n: np.ndarray) -> tuple[float, float]:
    """(z of the entrance pupil from surface 1, stop radius per unit EP radius)."""
    k = lens.stop_index
    # Heights at the stop of two unit rays launched at surface 1 (linearity of paraxial optics).
    _, _, _, y_a, _ = _trace(lens, n, 1.0, 0.0, upto=k)
    _, _, _, y_b, _ = _trace(lens, n, 0.0, 1.0, upto=k)
    if abs(y_a) < 1e-15:
        raise PrescriptionError("the stop is at an image of the object: no entrance pupil")
    # A ray crossing the axis at z_ep in object space: y0 = -z_ep u0 ; stop height 0 => z_ep = y_b / y_a
    return y_b / y_a, y_a


def first_order(lens: Lens, wavelength_nm: float = LAMBDA_D_NM, object_distance_mm: float = math.inf) -> FirstOrder:
    """EFL, EPD, F-number, Petzval radius and Seidel sums at one wavelength.

    ``object_distance_mm`` is measured from the stop centre; Seidel sums are for
    that conjugate (infinity by default) and the prescription's EPD.
    """
    lam_um = wavelength_nm * 1e-3
    n = indices(lens, lam_um)
    _, _, _, y_end, u_end = _trace(lens, n, 1.0, 0.0)
    if abs(u_end) < 1e-15:
        raise PrescriptionError("afocal system: no focal length")
    efl = -1.0 / u_end
    # y_end is the height at the image surface vertex: back up by the last thickness
    bfd = lens.surfaces[-1].thickness_mm - y_end / u_end
    z_ep, stop_per_ep = entrance_pupil(lens, n)
    r_ep = lens.entrance_pupil_diameter_mm / 2
    stop_r = abs(stop_per_ep) * r_ep
    stop_sd = lens.surfaces[lens.stop_index].semi_diameter_mm
    if stop_r > stop_sd:
        raise PrescriptionError(
            f"entrance pupil {lens.entrance_pupil_diameter_mm} mm needs a stop radius of {stop_r:.4f} mm, "
            f"larger than the stop surface ({stop_sd} mm): the aperture is larger than a surface"
        )
    # Marginal and chief rays at the requested conjugate.
    z_stop = lens.stop_z_mm
    if math.isinf(object_distance_mm):
        y0, u0 = r_ep, 0.0
        # chief ray: unit field slope through the entrance pupil centre
        ybar0, ubar0 = -z_ep * 0.0175, 0.0175
    else:
        z_obj = z_stop - object_distance_mm  # object z relative to surface 1
        u0 = r_ep / (z_ep - z_obj)
        y0 = u0 * (0.0 - z_obj)
        ubar0 = 0.0175
        ybar0 = ubar0 * (0.0 - z_ep)
    ym, um, ump, y_last, u_last = _trace(lens, n, y0, u0)
    yc, uc, ucp, _, _ = _trace(lens, n, ybar0, ubar0)
    image_distance = lens.surfaces[-1].thickness_mm - y_last / u_last
    c = np.array([s.curvature_per_mm for s in lens.surfaces])
    nb, na = n[:-1], n[1:]
    A = nb * (um + ym * c)
    Abar = nb * (uc + yc * c)
    d_u_n = ump / na - um / nb
    H = nb[0] * (uc[0] * ym[0] - um[0] * yc[0])
    S1 = -np.sum(A * A * ym * d_u_n)
    S2 = -np.sum(A * Abar * ym * d_u_n)
    S3 = -np.sum(Abar * Abar * ym * d_u_n)
    S4 = -np.sum(H * H * c * (1 / na - 1 / nb))
    S5 = -np.sum(Abar / np.where(A == 0, np.inf, A) * (H * H * c * (1 / na - 1 / nb) + Abar * A * ym * d_u_n)) \
        if np.all(A != 0) else float("nan")
    petzval_sum = np.sum(c * (na - nb) / (na * nb))
    petzval_radius = -1.0 / (n[-1] * petzval_sum) if petzval_sum != 0 else math.inf
    lam_mm = lam_um * 1e-3
    seidel = {
        "S_I_mm": float(S1), "S_II_mm": float(S2), "S_III_mm": float(S3), "S_IV_mm": float(S4), "S_V_mm": float(S5),
        "W040_waves": float(S1 / 8 / lam_mm),
        "W131_waves_per_field": float(S2 / 2 / lam_mm),
        "W222_waves_per_field": float(S3 / 2 / lam_mm),
        "W220_waves_per_field": float((S3 + S4) / 4 / lam_mm),
        "field_slope_for_field_terms": ubar0,
    }
    return FirstOrder(
        wavelength_nm=wavelength_nm, efl_mm=float(efl), bfd_mm=float(bfd), epd_mm=lens.entrance_pupil_diameter_mm,
        entrance_pupil_z_mm=float(z_ep), stop_radius_mm=float(stop_r), f_number=float(efl / lens.entrance_pupil_diameter_mm),
        petzval_radius_mm=float(petzval_radius), image_distance_mm=float(image_distance), seidel=seidel,
    )


def epd_for_w040(lens: Lens, w040_waves: float, wavelength_nm: float = LAMBDA_D_NM) -> float:
    """Entrance-pupil diameter giving a Seidel W040 of ``w040_waves`` (object at infinity).

    S_I scales with the fourth power of the marginal height, so one evaluation suffices.
    """
    probe = first_order(lens.with_entrance_pupil(1.0), wavelength_nm)
    w = probe.seidel["W040_waves"]
    if w <= 0:
        raise PrescriptionError(f"Seidel W040 is {w:.3g} waves at EPD 1 mm: cannot scale to {w040_waves} waves")
    return float((w040_waves / w) ** 0.25)
