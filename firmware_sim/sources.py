"""Irradiance sources: what the simulated sensor sees.

The simulated world shows the sensor one *irradiance source* at a time. A
source is any object with

* ``name: str`` — a short label that says what it is (goes into frame metadata);
* ``irradiance(row0, col0, height, width) -> np.ndarray`` — float32
  ``height × width × 3`` linear RGB irradiance at the sensor, in relative units
  (1.0 fills the well at the default 10 ms exposure), for the window whose
  top-left pixel is (row0, col0) on the full 6000×4500 sensor. It is what the
  lens delivers *before* relative illumination (cos θ), noise, CFA and ADC,
  which the readout applies. It must be deterministic (same window → same
  values), and it is called on horizontal strips of the window, so it must not
  assume it sees the whole frame at once;
* ``metadata() -> dict`` — JSON-able description (scene id, lens, PSF file…);
* optionally ``work(row0, col0, height, width) -> (done, total) | None`` — how
  much of that window's slow work (a render) is done, in units the source
  chooses; the device's PROGRESS heartbeats report it (rows read out otherwise).

Sources here are optics-free: flat field, dark frame, a polar test chart and
``InFocusImageStandIn``, a plain RGB image painted onto the sensor *without*
any lens blur — a stand-in, never the optical simulation. The forward simulator
(RGB + depth through the lens, procedural scenes, point-source targets)
registers its sources by name with ``register_source`` so that ``--scene``
options and ``sim://?scene=…`` URIs find them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from bmi_sdk.color import srgb_uint_to_linear
from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry


@runtime_checkable
class IrradianceSource(Protocol):
    @property
    def name(self) -> str: ...  # read-only: the sources are frozen dataclasses

    def irradiance(self, row0: int, col0: int, height: int, width: int) -> np.ndarray: ...

    def metadata(self) -> dict: ...


@dataclass(frozen=True)
class FlatField:
    """Uniform irradiance (per channel): flat-field and photon-transfer captures."""

    level_rgb: tuple[float, float, float] = (0.5, 0.5, 0.5)
    name: str = "flat"

    def __post_init__(self):
        if len(self.level_rgb) != 3 or min(self.level_rgb) < 0:
            raise ValueError(f"flat-field levels must be three values >= 0, got {self.level_rgb}")

    def irradiance(self, row0, col0, height, width):
        return np.broadcast_to(np.asarray(self.level_rgb, np.float32), (height, width, 3))

    def metadata(self):
        return {"source": self.name, "level_rgb": list(self.level_rgb)}


@dataclass(frozen=True)
class DarkFrame:
    """No light at all (capped lens): the frame is black level + read noise."""

    name: str = "dark"

    def irradiance(self, row0, col0, height, width):
        return np.broadcast_to(np.zeros(3, np.float32), (height, width, 3))

    def metadata(self):
        return {"source": self.name}


@dataclass(frozen=True)
class PolarChart:
    """A chart drawn in field coordinates: rings every ``ring_deg`` of θ, spokes every ``spoke_deg`` of φ.

    Background 0.25, lines 0.9, and R/G/B tints by azimuth third, so that
    geometry (θ, φ mapping), CFA phase and relative illumination are visible in
    one raw frame. No lens blur: a sensor-plane test pattern.
    """

    geometry: SensorGeometry = BMI_SENSOR
    ring_deg: float = 10.0
    spoke_deg: float = 30.0
    line_deg: float = 0.4
    name: str = "chart"

    def irradiance(self, row0, col0, height, width):
        theta, phi = self.geometry.grid(row0, col0, height, width)
        theta = np.nan_to_num(theta, nan=1e3)
        ring = np.abs((theta + self.ring_deg / 2) % self.ring_deg - self.ring_deg / 2) < self.line_deg / 2
        # spoke width in degrees of arc on the sensor: scale the azimuth distance by sin θ
        dphi = np.abs((phi + self.spoke_deg / 2) % self.spoke_deg - self.spoke_deg / 2)
        spoke = dphi * np.sin(np.radians(np.minimum(theta, 90))) < self.line_deg / 2
        grey = np.where(ring | spoke, 0.9, 0.25).astype(np.float32)
        third = ((phi + 180.0) // 120.0).astype(np.intp) % 3
        tint = np.full((height, width, 3), 0.6, np.float32)
        np.put_along_axis(tint, third[..., None], 1.0, axis=2)
        return grey[..., None] * tint

    def metadata(self):
        return {"source": self.name, "ring_deg": self.ring_deg, "spoke_deg": self.spoke_deg,
                "geometry": self.geometry.to_dict()}


class InFocusImageStandIn:
    """STAND-IN, NOT THE OPTICAL SIMULATION: an RGB image stretched over the sensor rectangle, no blur.

    Each sensor pixel takes the nearest image pixel (the image covers the whole
    6000×4500 array). Useful to exercise the device path with recognisable
    content until the forward simulator's sources are plugged in. ``image`` is
    linear float in [0, 1], H×W×3.
    """

    def __init__(self, image: np.ndarray, geometry: SensorGeometry = BMI_SENSOR, label: str = "array"):
        image = np.asarray(image, dtype=np.float32)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"the stand-in needs an H×W×3 image, got shape {image.shape}")
        if not np.isfinite(image).all() or image.min() < 0:
            raise ValueError("the stand-in image must be finite and >= 0 (linear irradiance)")
        self.image = image
        self.geometry = geometry
        self.label = label
        self.name = "in-focus-stand-in"

    @classmethod
    def from_file(cls, path: str | Path, geometry: SensorGeometry = BMI_SENSOR) -> "InFocusImageStandIn":
        """Read an 8/16-bit sRGB image file and linearise it (sRGB transfer curve)."""
        import cv2

        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
        if bgr is None:
            raise FileNotFoundError(f"cannot read an image from {path}")
        return cls(srgb_uint_to_linear(bgr[..., ::-1]), geometry, label=str(path))

    def irradiance(self, row0, col0, height, width):
        ih, iw, _ = self.image.shape
        rows = ((np.arange(row0, row0 + height) + 0.5) * ih / self.geometry.height_px).astype(np.intp)
        cols = ((np.arange(col0, col0 + width) + 0.5) * iw / self.geometry.width_px).astype(np.intp)
        return self.image[np.minimum(rows, ih - 1)[:, None], np.minimum(cols, iw - 1)[None, :]]

    def metadata(self):
        return {"source": self.name, "image": self.label, "image_shape": list(self.image.shape),
                "note": "optics-free stand-in: image painted on the sensor without lens blur"}


# -- registry: names for --scene and sim://?scene= ------------------------------
SourceFactory = Callable[[str | None], IrradianceSource]
_FACTORIES: dict[str, SourceFactory] = {}


def register_source(name: str, factory: SourceFactory) -> None:
    """Make ``make_source("name")`` / ``"name:ARG"`` build a source with ``factory(ARG or None)``."""
    if not name.isidentifier():
        raise ValueError(f"source names must be identifiers, got {name!r}")
    _FACTORIES[name] = factory


def source_names() -> list[str]:
    return sorted(_FACTORIES)


def make_source(spec: str) -> IrradianceSource:
    """Build a source from ``NAME`` or ``NAME:ARG`` (e.g. ``flat:0.3``, ``image:photo.png``)."""
    name, _, arg = spec.partition(":")
    factory = _FACTORIES.get(name)
    if factory is None:
        raise ValueError(f"unknown scene {name!r}; known: {', '.join(source_names())}")
    return factory(arg or None)


def _flat(arg):
    if arg is None:
        return FlatField()
    try:
        levels = [float(v) for v in arg.split(",")]
    except ValueError:
        raise ValueError(f"flat:ARG takes one level or R,G,B levels, got {arg!r}") from None
    return FlatField(tuple(levels * 3 if len(levels) == 1 else levels))


def _image(arg):
    if arg is None:
        raise ValueError("image:PATH needs a path to an RGB image file")
    return InFocusImageStandIn.from_file(arg)


register_source("flat", _flat)
register_source("dark", lambda arg: DarkFrame())
register_source("chart", lambda arg: PolarChart())
register_source("image", _image)
