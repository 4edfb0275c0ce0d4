"""The inputs for which one exported PSF is right, measured (docs/reliability.md), and the checks on its output.

``bmi psf export`` used to write an all-NaN kernel at 82–87° of field and a
wrong one (63 % of the energy, fit residual 115 waves) at 1e12 m, with exit
status 0. The engine now traces depths ≥ ``FAR_AS_INFINITY_M`` as infinity and
refuses non-finite kernels; these checks bound the rest before any work and
refuse a kernel too small to hold the PSF or sampled too coarsely to hold it without aliasing.
"""

from __future__ import annotations

import math

MAX_FIELD_DEG = 80.0
"""Measured on bmi_monocentric at 587.6 nm, 41 px: energy ≥ 0.99 to 80.0°, 0.80 at 80.8°, NaN from 81°;
the fisheye traces to 80° and has no real ray at 85°."""
MIN_PITCH_UM, MAX_PITCH_UM = 0.5, 5.0
"""Pixel pitches the exported kernel is right for (bmi_monocentric, 550 nm, 2 m, 41 px): energy 0.95 at 0.5 µm,
0.99 at 1 µm, 0.98 at 5 µm, 1.03 at 10 µm (the pupil undersampled), 0.36 at 20 µm; 1e6 µm asks for 10¹⁵ pupil
samples."""
MIN_ENERGY_CAPTURED = 0.9
"""A kernel holding less of the PSF's energy is a truncated PSF renormalised to sum 1: its shape is wrong."""
MAX_ENERGY_CAPTURED = 1.01
"""More than the pupil's power in the kernel is aliased power: the intensity sampled below its Nyquist rate
(2 NA/λ ≈ 0.95 cycles/µm at 587.6 nm), or a kernel smaller than the PSF, whose transform's replicas then fold
onto it. Measured (bmi_monocentric, 41 px, fields 0/40/80°, 0.05 m–∞, 365–1014 nm): at most 1.0029 at 2 µm with
3 samples per pixel side (the export's default), 0.9993 with 5; at 5 µm 2.08 with 3, 1.018 with 5, 0.9998 with 9;
a 1-px kernel 1.24."""


def min_depth_m(lens) -> float:
    """The nearest object distance: the lens's front vertex, measured from the stop like ``depth_m``."""
    return float(lens.stop_z_mm - lens.vertex_z_mm[0]) * 1e-3


def check_export_request(lens, field_deg: float, depth_m: float, wavelength_nm: float, pitch_um: float) -> None:
    """``ValueError`` naming the input when one lies outside the range the engine is valid for."""
    if not 0.0 <= field_deg <= MAX_FIELD_DEG:
        raise ValueError(f"--field-deg must lie in [0, {MAX_FIELD_DEG:g}]° (beyond, the traced PSF is not valid), "
                         f"got {field_deg}")
    nearest = min_depth_m(lens)
    if not depth_m > nearest:
        raise ValueError(f"--depth-m must lie beyond the lens's front surface ({nearest * 1e3:.1f} mm from the "
                         f"stop), got {depth_m} m")
    if not (math.isfinite(wavelength_nm) and wavelength_nm > 0):
        raise ValueError(f"--wavelength-nm must be a positive number, got {wavelength_nm}")
    if not MIN_PITCH_UM <= pitch_um <= MAX_PITCH_UM:
        raise ValueError(f"--pitch-um must lie in [{MIN_PITCH_UM:g}, {MAX_PITCH_UM:g}] µm (the pupil sampling is "
                         f"valid there; the sensor's pixels are 2 µm), got {pitch_um}")


def check_kernel(psf, kernel_px: int) -> None:
    """Refuse a kernel that is not finite or holds too little of the PSF (``ValueError`` with the remedy)."""
    import numpy as np

    if not np.isfinite(psf.kernel).all():
        raise ValueError("the PSF is not finite; nothing written")
    if psf.energy_captured < MIN_ENERGY_CAPTURED:
        raise ValueError(f"a {kernel_px}×{kernel_px} px kernel holds only {psf.energy_captured:.1%} of this PSF "
                         f"(at least {MIN_ENERGY_CAPTURED:.0%} needed): raise --kernel-px; nothing written")
    if psf.energy_captured > MAX_ENERGY_CAPTURED:
        raise ValueError(f"the {kernel_px}×{kernel_px} px kernel adds up to {psf.energy_captured:.1%} of the PSF's "
                         f"power (at most {MAX_ENERGY_CAPTURED:.0%} is right): the intensity is sampled too coarsely "
                         f"at {psf.pitch_um:g} µm per pixel, so aliased power folds in; raise --oversample (or "
                         f"--kernel-px, for a kernel narrower than the PSF); nothing written")
