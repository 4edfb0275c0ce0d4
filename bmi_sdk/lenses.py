"""Lens profiles: each lens's sensor geometry, PSF kernel size and nominal PSF tensor, in one place.

numpy only at import (the optics engine is imported when a profile is built), so the runtime and
the classical decoder can ask for a lens's sensor and kernels without loading the training stack.
"""

from __future__ import annotations

import numpy as np

from .geometry import BMI_SENSOR, SensorGeometry

DEFAULT_LENS = "bmi_monocentric"
"""The lens of a camera that names none: the BMI monocentric design."""

LENS_KERNEL_PX = {DEFAULT_LENS: 41, "fisheye": 161}
"""PSF kernel size per lens: the fisheye's near-range blur spreads ~15 % of its energy beyond 41 px."""


def lens_geometry(lens_name: str) -> SensorGeometry:
    """The sensor a lens images on: the BMI curved sensor, or for the fisheye a plane 6000×4500 sensor
    at 2 µm whose pixel → field mapping is the fisheye's traced chief-ray table (0–60°)."""
    if lens_name == DEFAULT_LENS:
        return BMI_SENSOR
    if lens_name == "fisheye":
        from .optics import chief_ray_table, get_lens

        field, radial = chief_ray_table(get_lens("fisheye"), np.linspace(0.0, 60.0, 121))
        return SensorGeometry(radius_mm=None, field_table_deg=tuple(np.abs(field)),
                              radial_table_mm=tuple(np.abs(radial)))
    raise ValueError(f"unknown lens {lens_name!r}; one of {sorted(LENS_KERNEL_PX)}")


def lens_tensor(lens_name: str):
    """The lazily filled nominal PSF tensor of a lens (shared disk cache)."""
    from .optics import PsfTensor, TensorSpec, get_lens

    if lens_name not in LENS_KERNEL_PX:
        raise ValueError(f"unknown lens {lens_name!r}; one of {sorted(LENS_KERNEL_PX)}")
    return PsfTensor(get_lens(lens_name), TensorSpec(kernel_px=LENS_KERNEL_PX[lens_name]))
