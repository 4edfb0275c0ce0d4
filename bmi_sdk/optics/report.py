"""The lens report behind ``bmi lens --json``: first order, Seidel, traced wavefronts.

Everything at 587.6 nm unless a row names its wavelength; object distances
from the lens centre (the stop). The wavefront rows come from the exact trace
(see ``wavefront``), referred to where the chief ray meets the sensor.
"""

from __future__ import annotations

import math

import numpy as np

from .paraxial import LAMBDA_D_NM, first_order
from .prescription import Lens
from .pupil import fit_pupils, stop_radius_mm
from .wavefront import axial_wavefront

REPORT_DEPTHS_M = (0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, math.inf)
REPORT_WAVELENGTHS_NM = (656.3, 587.6, 486.1)


def chief_ray_table(lens: Lens, field_deg=None, wavelength_nm: float = LAMBDA_D_NM, depth_m: float = math.inf):
    """(field_deg, radial position on the image surface in mm) of the real chief ray.

    On a sphere the radial position is the arc length from the image vertex;
    on a plane it is the distance from the axis. This is the lens's mapping
    that ``SensorGeometry`` needs (θ_field ↔ sensor position).
    """
    field_deg = np.linspace(0.0, 60.0, 61) if field_deg is None else np.asarray(field_deg, dtype=np.float64)
    fits = fit_pupils(lens, field_deg, depth_m, wavelength_nm * 1e-3, grid=8, degree=2)
    y = np.array([-f.chief_point_mm[1] for f in fits])
    if math.isinf(lens.image.radius_mm):
        return field_deg, y
    r = abs(lens.image.radius_mm)
    z_vertex = lens.vertex_z_mm[-1]
    centre_z = z_vertex + lens.image.radius_mm
    z = np.array([f.chief_point_mm[2] for f in fits])
    angle = np.arctan2(y, np.sign(lens.image.radius_mm) * (centre_z - z))
    return field_deg, r * angle


SENSOR_MAPPING_SCHEMA = "bmi-sensor-mapping/1"


def sensor_mapping(lens: Lens, max_field_deg: float = 80.0, step_deg: float = 0.25) -> dict:
    """The lens's traced chief-ray table as a document (``SensorGeometry``'s pixel ↔ field mapping).

    At 587.6 nm and infinity; the landing moves < 0.02 px between infinity and
    0.7 m, and 0.5 px between 450 and 650 nm at 60° (lateral colour, left in
    the PSFs). The table runs past the 60° image circle (to 80°) so that render
    margins and 12° patches placed near the circle still have a field angle.
    """
    field_deg, radial_mm = chief_ray_table(lens, np.arange(0.0, max_field_deg + step_deg / 2, step_deg))
    return {"schema": SENSOR_MAPPING_SCHEMA, "lens": lens.name, "lens_sha256": lens.sha256(),
            "wavelength_nm": LAMBDA_D_NM, "object_distance": "infinity",
            "radius_mm": None if math.isinf(lens.image.radius_mm) else abs(lens.image.radius_mm),
            "field_deg": [round(float(v), 6) for v in field_deg], "radial_mm": [float(v) for v in radial_mm]}


def lens_report(lens: Lens, depths_m=REPORT_DEPTHS_M, wavelengths_nm=REPORT_WAVELENGTHS_NM) -> dict:
    fo = first_order(lens, LAMBDA_D_NM)
    field, radial = chief_ray_table(lens, [0.0, 20.0, 40.0, 60.0])
    rows = [axial_wavefront(lens, lam, d).row() for lam in wavelengths_nm for d in depths_m]
    defocus_um = (lens.surfaces[-1].thickness_mm - fo.bfd_mm) * 1e3
    return {
        "lens": lens.name,
        "lens_sha256": lens.sha256(),
        "wavelength_nm": LAMBDA_D_NM,
        "efl_mm": fo.efl_mm,
        "epd_mm": fo.epd_mm,
        "f_number": fo.f_number,
        "petzval_radius_mm": fo.petzval_radius_mm,
        "seidel_w040_waves": fo.seidel["W040_waves"],
        "seidel": fo.seidel,
        "entrance_pupil_z_mm": fo.entrance_pupil_z_mm,
        "stop_radius_mm": stop_radius_mm(lens),
        "paraxial_bfd_mm": fo.bfd_mm,
        "sensor_from_paraxial_focus_um": defocus_um,
        "image_radius_mm": None if math.isinf(lens.image.radius_mm) else lens.image.radius_mm,
        "chief_ray": [{"field_deg": float(t), "image_radial_mm": float(r)} for t, r in zip(field, radial)],
        "wavefront": rows,
    }
