"""Optics engine: prescriptions, exact ray tracing, traced pupils, PSFs, the PSF tensor.

Public API below; everything else in the package is private. ``get_lens("fisheye")``
is the published fisheye design matched to the monocentric lens (``baseline``).
"""

from .baseline import matched_fisheye
from .glass import get_glass, refractive_index, register_glass
from .paraxial import epd_for_w040, first_order
from .prescription import Lens, PrescriptionError, load_lens
from .psf import Psf, psf_from_pupil
from .pupil import PupilFit, fit_pupil, fit_pupils
from .raytrace import RayTraceError, trace
from .report import chief_ray_table, lens_report
from .tensor import PsfTensor, TensorSpec, compute_kernels
from .wavefront import axial_wavefront


def spectral_channels(integrated: bool = False):
    """Channel wavelength lists: one representative line each, or the 13-sample integration."""
    from . import spectral

    return tuple(tuple(c) for c in (spectral.integrated() if integrated else spectral.representative()))


def get_lens(name: str = "bmi_monocentric") -> Lens:
    """A lens by name: a built-in prescription, a JSON path, or ``fisheye`` (the matched baseline)."""
    if name in ("fisheye", "fisheye_matched"):
        return matched_fisheye()
    if name in ("monocentric", "bmi"):
        name = "bmi_monocentric"
    return load_lens(name)


__all__ = [
    "Lens", "PrescriptionError", "RayTraceError", "Psf", "PupilFit", "PsfTensor", "TensorSpec",
    "load_lens", "get_lens", "matched_fisheye", "get_glass", "register_glass", "refractive_index", "first_order",
    "epd_for_w040", "trace", "fit_pupil", "fit_pupils", "psf_from_pupil", "compute_kernels", "axial_wavefront",
    "lens_report", "chief_ray_table", "spectral_channels",
]
