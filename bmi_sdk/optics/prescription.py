"""Lens prescriptions: rotationally symmetric sequential systems of spherical and
plane surfaces, read from JSON data files and validated on load.

Conventions (optics habit): millimetres; the optical axis is +z, light travels
towards +z; a surface's radius is positive when its centre of curvature lies
after its vertex; ``thickness_mm`` is the axial distance to the next surface
and ``material`` the medium after the surface. The first surface's vertex is
at z = 0. Object distances are measured from the stop centre (the paper's
convention: the lens centre of the monocentric design).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from .glass import get_glass


class PrescriptionError(ValueError):
    """A lens prescription that cannot describe a real lens."""


@dataclass(frozen=True)
class Surface:
    radius_mm: float  # math.inf for a plane
    thickness_mm: float
    material: str
    semi_diameter_mm: float
    is_stop: bool = False

    @property
    def curvature_per_mm(self) -> float:
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm

    def sag_mm(self, h_mm):
        """Sag z(h) of the surface relative to its vertex at height ``h_mm``."""
        c = self.curvature_per_mm
        h = np.asarray(h_mm, dtype=np.float64)
        if c == 0.0:
            return np.zeros_like(h)
        return c * h * h / (1.0 + np.sqrt(np.maximum(1.0 - (c * h) ** 2, 0.0)))


@dataclass(frozen=True)
class ImageSurface:
    radius_mm: float  # math.inf for a plane sensor
    semi_diameter_mm: float

    @property
    def curvature_per_mm(self) -> float:
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm


@dataclass(frozen=True)
class Lens:
    """A validated prescription. Build with :func:`load_lens` or :meth:`from_dict`."""

    name: str
    surfaces: tuple[Surface, ...]
    image: ImageSurface
    entrance_pupil_diameter_mm: float
    source: str = ""
    description: str = ""
    raw: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    # -- geometry ---------------------------------------------------------
    @property
    def vertex_z_mm(self) -> np.ndarray:
        """z of each surface vertex, then of the image surface vertex."""
        t = [s.thickness_mm for s in self.surfaces]
        return np.concatenate([[0.0], np.cumsum(t)])

    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.is_stop)

    @property
    def stop_z_mm(self) -> float:
        return float(self.vertex_z_mm[self.stop_index])

    def media(self) -> list[str]:
        """Medium before each surface, then after the last one (object side first)."""
        return ["air"] + [s.material for s in self.surfaces]

    def with_entrance_pupil(self, diameter_mm: float) -> "Lens":
        if not diameter_mm > 0:
            raise PrescriptionError(f"entrance pupil diameter must be > 0 mm, got {diameter_mm}")
        raw = dict(self.raw, entrance_pupil_diameter_mm=diameter_mm)
        return replace(self, entrance_pupil_diameter_mm=float(diameter_mm), raw=raw)

    def with_image_radius(self, radius_mm: float) -> "Lens":
        raw = dict(self.raw, image=dict(self.raw.get("image", {}), radius_mm=radius_mm))
        return replace(self, image=replace(self.image, radius_mm=float(radius_mm)), raw=raw)

    def scaled(self, factor: float) -> "Lens":
        """The same design with every length multiplied by ``factor`` (EPD included)."""
        surfaces = tuple(
            replace(s, radius_mm=s.radius_mm * factor, thickness_mm=s.thickness_mm * factor,
                    semi_diameter_mm=s.semi_diameter_mm * factor)
            for s in self.surfaces
        )
        image = replace(self.image, radius_mm=self.image.radius_mm * factor,
                        semi_diameter_mm=self.image.semi_diameter_mm * factor)
        lens = replace(self, surfaces=surfaces, image=image,
                       entrance_pupil_diameter_mm=self.entrance_pupil_diameter_mm * factor)
        return replace(lens, raw=lens.to_dict())

    def with_last_thickness(self, thickness_mm: float) -> "Lens":
        surfaces = self.surfaces[:-1] + (replace(self.surfaces[-1], thickness_mm=float(thickness_mm)),)
        lens = replace(self, surfaces=surfaces)
        return replace(lens, raw=lens.to_dict())

    # -- identity ---------------------------------------------------------
    def to_dict(self) -> dict:
        def r(x):
            return None if math.isinf(x) else x

        return {
            "schema": "bmi-lens/1",
            "name": self.name,
            "description": self.description,
            "source": self.source,
            "units": "mm",
            "entrance_pupil_diameter_mm": self.entrance_pupil_diameter_mm,
            "object_reference": "stop",
            "surfaces": [
                {"radius_mm": r(s.radius_mm), "thickness_mm": s.thickness_mm, "material": s.material,
                 "semi_diameter_mm": s.semi_diameter_mm, **({"stop": True} if s.is_stop else {})}
                for s in self.surfaces
            ],
            "image": {"radius_mm": r(self.image.radius_mm), "semi_diameter_mm": self.image.semi_diameter_mm},
        }

    def sha256(self) -> str:
        """Hash of the optical content (what changes the PSFs), not of the comments."""
        text = json.dumps({k: v for k, v in self.to_dict().items() if k not in ("description", "source")},
                          sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    @classmethod
    def from_dict(cls, data: dict) -> "Lens":
        return _validate(data)


def _num(value, what: str) -> float:
    if value is None:
        return math.inf
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise PrescriptionError(f"{what} must be a number or null (plane), got {value!r}") from None
    if math.isnan(x):
        raise PrescriptionError(f"{what} is NaN")
    return x


def _validate(data: dict) -> Lens:
    name = data.get("name", "unnamed")
    where = f"lens {name!r}"
    surfaces_in = data.get("surfaces")
    if not surfaces_in:
        raise PrescriptionError(f"{where}: no surfaces")
    surfaces = []
    for i, s in enumerate(surfaces_in, start=1):
        radius = _num(s.get("radius_mm"), f"{where} surface {i} radius_mm")
        if radius == 0.0:
            raise PrescriptionError(f"{where} surface {i}: radius 0 is impossible (use null for a plane)")
        thickness = _num(s.get("thickness_mm"), f"{where} surface {i} thickness_mm")
        material = str(s.get("material", "")).strip()
        if not material:
            raise PrescriptionError(f"{where} surface {i}: missing material")
        if material.lower() not in ("air", "vacuum"):
            try:
                get_glass(material)
            except ValueError as exc:
                raise PrescriptionError(f"{where} surface {i}: {exc}") from None
        sd = _num(s.get("semi_diameter_mm"), f"{where} surface {i} semi_diameter_mm")
        if not (0 < sd < math.inf):
            raise PrescriptionError(f"{where} surface {i}: semi_diameter_mm must be > 0, got {sd}")
        if sd > abs(radius) + 1e-12:
            raise PrescriptionError(
                f"{where} surface {i}: semi-diameter {sd} mm is larger than the sphere radius {abs(radius)} mm"
            )
        if material.lower() not in ("air", "vacuum") and thickness <= 0:
            raise PrescriptionError(f"{where} surface {i}: glass thickness must be > 0 mm, got {thickness}")
        surfaces.append(Surface(radius, thickness, material, sd, bool(s.get("stop", False))))
    stops = [i for i, s in enumerate(surfaces) if s.is_stop]
    if len(stops) != 1:
        raise PrescriptionError(f"{where}: exactly one surface must be marked \"stop\": true (found {len(stops)})")
    image_in = data.get("image") or {}
    image_radius = _num(image_in.get("radius_mm"), f"{where} image radius_mm")
    image_sd = _num(image_in.get("semi_diameter_mm", 1e9), f"{where} image semi_diameter_mm")
    if image_radius == 0.0:
        raise PrescriptionError(f"{where}: image radius 0 is impossible (use null for a plane sensor)")
    image = ImageSurface(image_radius, image_sd)
    epd = _num(data.get("entrance_pupil_diameter_mm"), f"{where} entrance_pupil_diameter_mm")
    if not (0 < epd < math.inf):
        raise PrescriptionError(f"{where}: entrance_pupil_diameter_mm must be > 0")
    # Surfaces must not cross each other inside their clear apertures.
    for i in range(len(surfaces)):
        a = surfaces[i]
        if i + 1 < len(surfaces):
            next_sd, b_sag = surfaces[i + 1].semi_diameter_mm, surfaces[i + 1].sag_mm
        else:
            next_sd, b_sag = image.semi_diameter_mm, Surface(image.radius_mm, 0.0, "air", 1.0).sag_mm
        h = np.linspace(0.0, min(a.semi_diameter_mm, next_sd), 257)
        gap = a.thickness_mm + b_sag(h) - a.sag_mm(h)
        if gap.min() < -1e-9:
            raise PrescriptionError(
                f"{where}: surface {i + 1} and the next surface intersect inside the clear aperture "
                f"(thickness {a.thickness_mm} mm leaves a gap of {gap.min():.4f} mm at h = {h[gap.argmin()]:.3f} mm)"
            )
    return Lens(
        name=name,
        surfaces=tuple(surfaces),
        image=image,
        entrance_pupil_diameter_mm=epd,
        source=data.get("source", ""),
        description=data.get("description", ""),
        raw=data,
    )


def builtin_lens_names() -> list[str]:
    folder = resources.files("bmi_sdk") / "data" / "lenses"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json"))


def load_lens(name_or_path: str | Path = "bmi_monocentric") -> Lens:
    """Load a built-in lens by name (``bmi_monocentric``, ``fisheye``…) or a JSON file."""
    path = Path(name_or_path)
    if path.suffix == ".json" and path.exists():
        data = json.loads(path.read_text())
    else:
        folder = resources.files("bmi_sdk") / "data" / "lenses"
        item = folder / f"{name_or_path}.json"
        if not item.is_file():
            raise PrescriptionError(
                f"no lens called {name_or_path!r}: not a JSON file and not one of {builtin_lens_names()}"
            )
        data = json.loads(item.read_text())
    return _validate(data)
