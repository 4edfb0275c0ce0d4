"""Sensor geometry: the one object that maps pixels to field angles and rays.

The BMI sensor is a spherical cap (radius 7.199 mm, concave towards the lens)
sampled on a 6000×4500 grid at 2 µm *arc-length* pitch: a pixel's distance
from the optical centre, measured along the sphere, is ``pitch × radial index``
(an azimuthal-equidistant layout: the corners lie 3750 px × 2 µm / 7.199 mm
= 59.7° round the sphere, which the design lens's traced mapping makes a
60.06° field, just outside the image circle). A plane sensor (the fisheye
baseline) uses the same object with ``radius_mm=None`` and planar distances.

Which *object-space* field angle θ lands at a given sensor position is a
property of the lens, not of the sensor: it comes from the real chief-ray
trace, as a monotone table ``(field_deg, sensor_radial_mm)``. For the ideal
concentric lens the table is θ_sensor = θ_field (the chief ray passes the
common centre undeviated; ``IDEAL_BMI_SENSOR``); ``SensorGeometry.for_lens``
builds the exact table, and ``BMI_SENSOR``, the SDK's default, carries the
design lens's traced table (``data/bmi_sensor_mapping.json``).

Conventions: pixel (row, col) has its centre at index coordinates
(row, col); the optical centre sits at (cy_px, cx_px), by default the centre
of the array. x grows with col, y with row; the azimuth φ = atan2(y, x).
Raw frames are read out upright (as every camera does, the readout order
undoes the lens's inversion), so pixel (row, col) sees the object-space ray
(sin θ cos φ, sin θ sin φ, cos θ) in a camera frame with x right, y down,
z forward (OpenCV's).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class SensorGeometry:
    width_px: int = 6000
    height_px: int = 4500
    pitch_um: float = 2.0
    radius_mm: float | None = 7.199  # None: plane sensor
    cx_px: float | None = None
    cy_px: float | None = None
    max_field_deg: float = 60.0
    # chief-ray table: object field angle (deg) -> radial position on the sensor (mm, arc length or planar)
    field_table_deg: tuple = field(default=())
    radial_table_mm: tuple = field(default=())

    def __post_init__(self):
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"sensor size must be positive, got {self.width_px}×{self.height_px}")
        if not self.pitch_um > 0:
            raise ValueError(f"pitch_um must be > 0, got {self.pitch_um}")
        if self.radius_mm is not None and not self.radius_mm > 0:
            raise ValueError(f"radius_mm must be > 0 (or None for a plane sensor), got {self.radius_mm}")
        if len(self.field_table_deg) != len(self.radial_table_mm):
            raise ValueError("field_table_deg and radial_table_mm differ in length")
        if len(self.radial_table_mm) and np.any(np.diff(self.radial_table_mm) <= 0):
            raise ValueError("chief-ray table must be strictly increasing (the lens folds the field)")

    def __repr__(self) -> str:
        """The scalar fields, and the chief-ray table as its length and range: its ~240 floats
        would otherwise fill every signature that has a geometry default (``help(FirmwareDevice)``)."""
        scalars = ", ".join(f"{f}={getattr(self, f)!r}" for f in ("width_px", "height_px", "pitch_um", "radius_mm",
                                                                    "cx_px", "cy_px", "max_field_deg"))
        if not self.field_table_deg:
            return f"SensorGeometry({scalars})"
        table = (f"<{len(self.field_table_deg)} points, {self.field_table_deg[0] + 0.0:g}–{self.field_table_deg[-1]:g}° → "
                 f"{self.radial_table_mm[0] + 0.0:g}–{self.radial_table_mm[-1]:g} mm>")
        return f"SensorGeometry({scalars}, chief_ray_table={table})"

    @classmethod
    def for_lens(cls, lens, max_field_deg: float = 60.0, **kwargs) -> "SensorGeometry":
        """The sensor behind ``lens``: its image surface's radius and the real chief-ray table.

        ``lens`` is a :class:`bmi_sdk.optics.Lens` (imported lazily: geometry sits below optics).
        """
        import math

        from .optics.report import chief_ray_table

        field, radial = chief_ray_table(lens, np.linspace(0.0, max_field_deg, 121))
        radius = None if math.isinf(lens.image.radius_mm) else abs(lens.image.radius_mm)
        return cls(radius_mm=radius, max_field_deg=max_field_deg, field_table_deg=tuple(field.tolist()),
                   radial_table_mm=tuple(radial.tolist()), **kwargs)

    # -- centre -------------------------------------------------------------
    @property
    def centre_px(self) -> tuple[float, float]:
        cy = (self.height_px - 1) / 2 if self.cy_px is None else self.cy_px
        cx = (self.width_px - 1) / 2 if self.cx_px is None else self.cx_px
        return cy, cx

    # -- sensor position <-> field ------------------------------------------
    def sensor_angle_rad(self, radial_mm):
        """Angle on the sensor sphere seen from its centre of curvature (0 for a plane)."""
        if self.radius_mm is None:
            return np.zeros_like(np.asarray(radial_mm, dtype=np.float64))
        return np.asarray(radial_mm, dtype=np.float64) / self.radius_mm

    def field_deg_from_radial_mm(self, radial_mm):
        r = np.asarray(radial_mm, dtype=np.float64)
        if len(self.radial_table_mm):
            return np.interp(r, self.radial_table_mm, self.field_table_deg, right=np.nan)
        if self.radius_mm is None:
            raise ValueError("a plane sensor needs the lens's chief-ray table (SensorGeometry.for_lens)")
        return np.degrees(r / self.radius_mm)

    def radial_mm_from_field_deg(self, field_deg):
        t = np.asarray(field_deg, dtype=np.float64)
        if len(self.radial_table_mm):
            return np.interp(t, self.field_table_deg, self.radial_table_mm, right=np.nan)
        if self.radius_mm is None:
            raise ValueError("a plane sensor needs the lens's chief-ray table (SensorGeometry.for_lens)")
        return np.radians(t) * self.radius_mm

    # -- pixels -------------------------------------------------------------
    def pixel_polar(self, rows, cols):
        """(radial_mm, phi_rad) of pixel centres; radial is arc length on a sphere."""
        cy, cx = self.centre_px
        dy = (np.asarray(rows, dtype=np.float64) - cy) * self.pitch_um * 1e-3
        dx = (np.asarray(cols, dtype=np.float64) - cx) * self.pitch_um * 1e-3
        return np.hypot(dx, dy), np.arctan2(dy, dx)

    def field_angles(self, rows, cols):
        """(theta_deg, phi_deg) of the object-space chief ray landing on each pixel."""
        radial, phi = self.pixel_polar(rows, cols)
        return self.field_deg_from_radial_mm(radial), np.degrees(phi)

    def pixel_of_field(self, theta_deg, phi_deg):
        """(row, col) (fractional) where a field direction (θ, φ) lands."""
        r_px = self.radial_mm_from_field_deg(theta_deg) * 1e3 / self.pitch_um
        phi = np.radians(np.asarray(phi_deg, dtype=np.float64))
        cy, cx = self.centre_px
        return cy + r_px * np.sin(phi), cx + r_px * np.cos(phi)

    def grid(self, row0: int = 0, col0: int = 0, height: int | None = None, width: int | None = None):
        """(theta_deg, phi_deg) maps for a window (the whole sensor by default)."""
        height = self.height_px - row0 if height is None else height
        width = self.width_px - col0 if width is None else width
        rows = np.arange(row0, row0 + height, dtype=np.float64)[:, None]
        cols = np.arange(col0, col0 + width, dtype=np.float64)[None, :]
        return self.field_angles(rows, cols)

    def window_polar(self, row0: int, col0: int, height: int, width: int):
        """(radial_mm, cos φ, sin φ) maps of a window, without trigonometry (per-tile hot path).

        cos φ = dx / r and sin φ = dy / r equal cos/sin of ``pixel_polar``'s
        φ to rounding; at the optical centre (r = 0) they are (1, 0), as
        arctan2(0, 0) = 0 gives.
        """
        cy, cx = self.centre_px
        pitch_mm = self.pitch_um * 1e-3
        dy = ((np.arange(row0, row0 + height, dtype=np.float64) - cy) * pitch_mm)[:, None]
        dx = ((np.arange(col0, col0 + width, dtype=np.float64) - cx) * pitch_mm)[None, :]
        radial = np.hypot(dx, dy)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = np.where(radial > 0, 1.0 / radial, 0.0)
        cos_phi = np.where(radial > 0, dx * inv, 1.0)
        return radial, cos_phi, dy * inv

    def valid_mask(self, row0: int = 0, col0: int = 0, height: int | None = None, width: int | None = None):
        """Pixels inside the image circle (θ ≤ max_field_deg)."""
        height = self.height_px - row0 if height is None else height
        width = self.width_px - col0 if width is None else width
        radial, _, _ = self.window_polar(row0, col0, height, width)
        theta = self.field_deg_from_radial_mm(radial)
        return np.isfinite(theta) & (theta <= self.max_field_deg)

    def ray_directions(self, rows, cols):
        """Unit object-space chief-ray directions (…, 3), camera frame x right, y down, z forward."""
        theta, phi = self.field_angles(rows, cols)
        t, p = np.radians(theta), np.radians(phi)
        return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)

    # -- depth conventions --------------------------------------------------
    @staticmethod
    def range_to_z(range_m, theta_deg):
        """Planar z-depth (along the optical axis) of a point at ``range_m`` along a ray at θ."""
        return np.asarray(range_m) * np.cos(np.radians(theta_deg))

    @staticmethod
    def z_to_range(z_m, theta_deg):
        return np.asarray(z_m) / np.cos(np.radians(theta_deg))

    @staticmethod
    def range_to_local_z(range_m, alpha_deg):
        """z-depth in a local tangent patch whose axis is a chief ray; α is the angle from that axis.

        The paper's patches (12° wide) treat a dataset image as a pinhole view along
        the patch's central ray: a pixel at angle α from it has local z = range × cos α.
        """
        return np.asarray(range_m) * np.cos(np.radians(alpha_deg))

    def to_dict(self) -> dict:
        return {
            "width_px": self.width_px, "height_px": self.height_px, "pitch_um": self.pitch_um,
            "radius_mm": self.radius_mm, "centre_px": list(self.centre_px), "max_field_deg": self.max_field_deg,
            "field_table_deg": list(map(float, self.field_table_deg)),
            "radial_table_mm": list(map(float, self.radial_table_mm)),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "SensorGeometry":
        cy, cx = d.get("centre_px", (None, None))
        return cls(width_px=int(d["width_px"]), height_px=int(d["height_px"]), pitch_um=float(d["pitch_um"]),
                   radius_mm=d.get("radius_mm"), cx_px=cx, cy_px=cy, max_field_deg=float(d.get("max_field_deg", 60)),
                   field_table_deg=tuple(d.get("field_table_deg", ())),
                   radial_table_mm=tuple(d.get("radial_table_mm", ())))


IDEAL_BMI_SENSOR = SensorGeometry()
"""The BMI sensor with the ideal concentric mapping θ_field = θ_sensor (a lens whose surfaces share one centre)."""

SENSOR_MAPPING_FILE = Path(__file__).resolve().parent / "data" / "bmi_sensor_mapping.json"


def _traced_bmi_sensor() -> SensorGeometry:
    """The BMI sensor behind the design lens: its traced chief-ray table, read from the package.

    The table is ``SensorGeometry.for_lens(bmi_monocentric)``'s, stored by
    ``bmi lens --write-sensor-mapping`` so that importing the geometry traces
    nothing (a test re-traces it and compares).
    """
    doc = json.loads(SENSOR_MAPPING_FILE.read_text())
    return SensorGeometry(radius_mm=doc["radius_mm"], field_table_deg=tuple(doc["field_deg"]),
                          radial_table_mm=tuple(doc["radial_mm"]))


BMI_SENSOR = _traced_bmi_sensor()
"""The nominal BMI sensor with the design lens's traced mapping: the printed lens is not exactly concentric,
and its chief rays land 0.6–0.8 % inside R·θ (14 px at 30°, 24 px at 60°) — docs/optics.md."""
