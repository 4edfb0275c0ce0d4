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
from functools import cached_property
from pathlib import Path

import numpy as np

_CIRCLE_BAND = 1e-9
"""Relative band of squared distances about the image circle's rim inside which ``valid_mask`` evaluates θ itself:
far wider than the float rounding that separates the two tests (~1e-16), and a fraction of a pixel wide."""


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
        """Pixels inside the image circle (θ ≤ max_field_deg).

        θ never falls as a pixel moves away from the optical centre (the chief-ray table rises), so the image circle
        is a disc of radius ``image_circle_radius_px``: a pixel's squared distance from the centre decides it, and θ
        itself is evaluated only for the pixels within a relative ``_CIRCLE_BAND`` of the rim, where rounding could
        tell the two tests apart. The same mask as θ ≤ max_field_deg at every pixel (``valid_mask_by_field``), at a
        tenth of the work: it runs on every network tile and output band of a frame.
        """
        height = self.height_px - row0 if height is None else height
        width = self.width_px - col0 if width is None else width
        rim_px = self.image_circle_radius_px
        if rim_px is None:
            return self.valid_mask_by_field(row0, col0, height, width)
        cy, cx = self.centre_px
        dy2 = ((np.arange(row0, row0 + height, dtype=np.float64) - cy) ** 2)[:, None]
        dx2 = ((np.arange(col0, col0 + width, dtype=np.float64) - cx) ** 2)[None, :]
        dist2 = dy2 + dx2
        inside = dist2 <= rim_px ** 2 * (1.0 - _CIRCLE_BAND)
        rim = (dist2 <= rim_px ** 2 * (1.0 + _CIRCLE_BAND)) & ~inside
        if rim.any():
            rows, cols = np.nonzero(rim)
            theta = self.field_deg_from_radial_mm(self.pixel_polar(rows + row0, cols + col0)[0])
            inside[rim] = np.isfinite(theta) & (theta <= self.max_field_deg)
        return inside

    def valid_mask_by_field(self, row0: int = 0, col0: int = 0, height: int | None = None, width: int | None = None):
        """``valid_mask`` by its definition, θ ≤ max_field_deg evaluated at every pixel: the reference it is tested
        against, and its fallback where θ is not monotone in the distance from the centre."""
        height = self.height_px - row0 if height is None else height
        width = self.width_px - col0 if width is None else width
        radial, _, _ = self.window_polar(row0, col0, height, width)
        theta = self.field_deg_from_radial_mm(radial)
        return np.isfinite(theta) & (theta <= self.max_field_deg)

    @cached_property
    def image_circle_radius_px(self) -> float | None:
        """Distance from the optical centre (px) out to which θ ≤ max_field_deg: the chief-ray table's radial at
        max_field_deg (its last radial when the table stops short of it: θ is undefined beyond), or R·θ_max on a
        sphere without a table. None where that does not describe the circle: a field table that does not rise throughout
        (θ not strictly monotone in the distance), one starting beyond max_field_deg, or a plane sensor with no
        table."""
        pitch_mm = self.pitch_um * 1e-3
        if len(self.radial_table_mm):
            field_deg = np.asarray(self.field_table_deg, np.float64)
            if np.any(np.diff(field_deg) <= 0) or field_deg[0] > self.max_field_deg:
                return None
            if self.max_field_deg >= field_deg[-1]:
                return float(self.radial_table_mm[-1]) / pitch_mm
            return float(np.interp(self.max_field_deg, field_deg, self.radial_table_mm)) / pitch_mm
        if self.radius_mm is None:
            return None
        return float(np.radians(self.max_field_deg) * self.radius_mm) / pitch_mm

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
        """The geometry ``to_dict`` wrote (a ``DisplacedGeometry`` when it holds a displacement table)."""
        cy, cx = d.get("centre_px", (None, None))
        kwargs = dict(width_px=int(d["width_px"]), height_px=int(d["height_px"]), pitch_um=float(d["pitch_um"]),
                      radius_mm=d.get("radius_mm"), cx_px=cx, cy_px=cy, max_field_deg=float(d.get("max_field_deg", 60)),
                      field_table_deg=tuple(d.get("field_table_deg", ())),
                      radial_table_mm=tuple(d.get("radial_table_mm", ())))
        if "displacement" in d:
            disp = d["displacement"]
            return DisplacedGeometry(**kwargs, displacement_step_deg=float(disp["step_deg"]),
                                     displacement_phi_count=int(disp["phi_count"]),
                                     displacement_px=tuple(float(x) for x in disp["px"]))
        return SensorGeometry(**kwargs)


@dataclass(frozen=True, repr=False)
class DisplacedGeometry(SensorGeometry):
    """A sensor geometry whose chief rays land off its rotationally symmetric mapping by a smooth displacement.

    A built camera with decenter or tilt breaks the rotational symmetry: the chief ray of (θ, φ) lands at
    ``SensorGeometry.pixel_of_field(θ, φ) + D(θ, φ)``. D (row, col) px is tabulated on the regular grid
    θ = i·``displacement_step_deg`` (0 … the table's end), φ = j·360°/n_φ, flattened in
    ``displacement_px`` as (n_θ, n_φ, 2), and interpolated bilinearly (periodic in φ, clamped in θ).
    ``field_angles`` inverts it: on a lattice of sensor pixels every ``INVERSE_LATTICE_PX`` the
    displacement E(pixel) = D(f) of the field f the pixel sees is found by fixed-point iteration
    f ← symmetric field of (pixel − D(f)) (D is a few px and changes by ~1e-3 px per px, so two steps
    leave ~1e-5 px), once; any pixel then sees the symmetric field of (pixel − E(pixel)), E bilinear
    between lattice points (C speed: a full frame costs what the symmetric mapping does, twice).
    """

    INVERSE_LATTICE_PX = 32

    displacement_step_deg: float = 1.0
    displacement_phi_count: int = 1
    displacement_px: tuple = ()

    def __post_init__(self):
        super().__post_init__()
        d = np.asarray(self.displacement_px, dtype=np.float64)
        if not self.displacement_step_deg > 0 or self.displacement_phi_count < 1 or \
                d.size % (2 * self.displacement_phi_count) or not d.size or not np.all(np.isfinite(d)):
            raise ValueError(f"displacement_px must hold finite (n_theta, {self.displacement_phi_count}, 2) values "
                             f"on a {self.displacement_step_deg}° θ grid")
        object.__setattr__(self, "_table", d.reshape(-1, self.displacement_phi_count, 2))

    def displacement(self, theta_deg, phi_deg) -> tuple[np.ndarray, np.ndarray]:
        """(d_row, d_col) px of the chief rays of (θ, φ) from the symmetric mapping (bilinear in the table)."""
        table = self._table
        n_theta, n_phi = table.shape[:2]
        # beyond the image circle (θ NaN or past the table) the edge's displacement continues
        t = np.clip(np.nan_to_num(np.asarray(theta_deg, dtype=np.float64), nan=np.inf) / self.displacement_step_deg,
                    0.0, n_theta - 1.0)
        f = np.mod(np.asarray(phi_deg, dtype=np.float64), 360.0) / (360.0 / n_phi)
        i0 = np.minimum(np.floor(t).astype(int), n_theta - 2) if n_theta > 1 else np.zeros_like(t, dtype=int)
        j0 = np.floor(f).astype(int) % n_phi
        j1 = (j0 + 1) % n_phi
        wt = (t - i0)[..., None]
        wf = (f - np.floor(f))[..., None]
        i1 = np.minimum(i0 + 1, n_theta - 1)
        d = ((1 - wt) * ((1 - wf) * table[i0, j0] + wf * table[i0, j1])
             + wt * ((1 - wf) * table[i1, j0] + wf * table[i1, j1]))
        return d[..., 0], d[..., 1]

    def pixel_of_field(self, theta_deg, phi_deg):
        row, col = super().pixel_of_field(theta_deg, phi_deg)
        d_row, d_col = self.displacement(theta_deg, phi_deg)
        return row + d_row, col + d_col

    def _inverse_lattice(self) -> np.ndarray:
        """(2, n_rows, n_cols) displacement E (row, col) px of the chief rays landing on lattice pixels."""
        lattice = getattr(self, "_lattice", None)
        if lattice is None:
            step = self.INVERSE_LATTICE_PX
            rows = np.arange(0, self.height_px + step, step, dtype=np.float64)[:, None]
            cols = np.arange(0, self.width_px + step, step, dtype=np.float64)[None, :]
            d_row = d_col = np.zeros(np.broadcast_shapes(rows.shape, cols.shape))
            for _ in range(3):
                theta, phi = super().field_angles(rows - d_row, cols - d_col)
                d_row, d_col = self.displacement(theta, phi)
            lattice = np.stack([d_row, d_col])
            object.__setattr__(self, "_lattice", lattice)
        return lattice

    def field_angles(self, rows, cols):
        from scipy.ndimage import map_coordinates  # here: the host API imports this module without scipy

        rows, cols = np.broadcast_arrays(np.asarray(rows, dtype=np.float64), np.asarray(cols, dtype=np.float64))
        at = [rows / self.INVERSE_LATTICE_PX, cols / self.INVERSE_LATTICE_PX]
        d_row, d_col = (map_coordinates(e, at, order=1, mode="nearest") for e in self._inverse_lattice())
        return super().field_angles(rows - d_row, cols - d_col)

    @property
    def max_displacement_px(self) -> float:
        return float(np.hypot(self._table[..., 0], self._table[..., 1]).max())

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["displacement"] = {"step_deg": self.displacement_step_deg, "phi_count": self.displacement_phi_count,
                             "px": [float(x) for x in self.displacement_px]}
        return d


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
