"""Typed camera settings with units in their names and ranges taken from the device's own register map.

``cam.settings.exposure_us = 5000`` validates type, range and step on the host
and raises ``ConfigurationError`` before anything is sent; the device's reply
is checked too (a refusal becomes a ``ConfigurationError`` naming the code).
``cam.settings.ranges()`` shows every setting's unit and limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from bmi_sdk.protocol.registers import ROI_REGISTERS, RegError

from .errors import ConfigurationError
from .frame import Roi


@dataclass(frozen=True)
class SettingSpec:
    name: str
    register: str
    unit: str
    minimum: float
    maximum: float
    scale: int            # register value = host value × scale
    kind: type            # int or float
    doc: str

    def to_register(self, value) -> int:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigurationError(f"{self.name} must be a number in {self.unit}, got {value!r}")
        if self.kind is int and not float(value).is_integer():
            raise ConfigurationError(f"{self.name} must be a whole number of {self.unit}, got {value!r}")
        if not (math.isfinite(value) and self.minimum <= value <= self.maximum):
            raise ConfigurationError(f"{self.name}={value!r} is outside its range "
                                     f"[{self.minimum}, {self.maximum}] {self.unit}")
        reg = round(value * self.scale)
        if abs(reg - value * self.scale) > 1e-6 * max(1.0, abs(value * self.scale)):
            raise ConfigurationError(f"{self.name}={value!r} is finer than the device step {1 / self.scale} "
                                     f"{self.unit}")
        return reg


# host name → (register, host unit, scale, type)
_HOST = {
    "exposure_us": ("EXPOSURE_US", "µs", 1, int),
    "analog_gain": ("ANALOG_GAIN_MILLI", "×", 1000, float),
    "black_level_dn": ("BLACK_LEVEL_DN", "DN", 1, int),
    "test_pattern": ("TEST_PATTERN", "0 off, 1 ramp, 2 walking ramp", 1, int),
}


def specs_from_register_map(registers: list[dict]) -> dict[str, SettingSpec]:
    by_name = {r["name"]: r for r in registers}
    specs = {}
    for name, (reg, unit, scale, kind) in _HOST.items():
        r = by_name[reg]
        specs[name] = SettingSpec(name, reg, unit, r["minimum"] / scale, r["maximum"] / scale, scale, kind, r["doc"])
    return specs


class Settings:
    """Attribute access to the camera's settings; reads come from the device, writes are checked first."""

    def __init__(self, specs: dict[str, SettingSpec], registers: list[dict],
                 read: Callable[[str], int], write: Callable[[str, int], None]):
        object.__setattr__(self, "_specs", specs)
        object.__setattr__(self, "_registers", {r["name"]: r for r in registers})
        object.__setattr__(self, "_read", read)
        object.__setattr__(self, "_write", write)

    def ranges(self) -> dict[str, dict]:
        out = {n: {"unit": s.unit, "minimum": s.minimum, "maximum": s.maximum, "step": 1 / s.scale, "doc": s.doc}
               for n, s in self._specs.items()}
        out["roi"] = {"unit": "px", "width_px": self._registers["SENSOR_WIDTH_PX"]["maximum"],
                      "height_px": self._registers["SENSOR_HEIGHT_PX"]["maximum"], "step": 2,
                      "doc": "Roi(x_px, y_px, width_px, height_px), even values, inside the sensor"}
        return out

    def __dir__(self):
        return [*self._specs, "roi", "ranges"]

    def __getattr__(self, name):
        spec = self._specs.get(name)
        if spec is None:
            raise AttributeError(f"no setting {name!r}; settings: {', '.join(self._specs)}, roi")
        value = self._read(spec.register) / spec.scale
        return spec.kind(value) if spec.kind is int else value

    def __setattr__(self, name, value):
        if name == "roi":
            self.set_roi(value)
            return
        spec = self._specs.get(name)
        if spec is None:
            raise ConfigurationError(f"no setting {name!r}; settings: {', '.join(self._specs)}, roi")
        self._write(spec.register, spec.to_register(value))

    @property
    def roi(self) -> Roi:
        return Roi(*(self._read(n) for n in ROI_REGISTERS))

    def check_roi(self, roi) -> Roi:
        if not isinstance(roi, Roi):
            try:
                roi = Roi(*roi)
            except TypeError:
                raise ConfigurationError(f"roi must be Roi(x_px, y_px, width_px, height_px), got {roi!r}") from None
        width = self._registers["SENSOR_WIDTH_PX"]["maximum"]
        height = self._registers["SENSOR_HEIGHT_PX"]["maximum"]
        values = (roi.x_px, roi.y_px, roi.width_px, roi.height_px)
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            raise ConfigurationError(f"roi values must be integers (px), got {roi}")
        if any(v % 2 for v in values):
            raise ConfigurationError(f"roi offsets and sizes must be even (whole RGGB cells), got {roi}")
        if roi.width_px < 2 or roi.height_px < 2 or roi.x_px < 0 or roi.y_px < 0 \
                or roi.x_px + roi.width_px > width or roi.y_px + roi.height_px > height:
            raise ConfigurationError(f"roi {roi} does not fit the {width}×{height} sensor")
        return roi

    def set_roi(self, roi) -> None:
        """Set the readout window (offset first to 0 so every intermediate state is valid)."""
        roi = self.check_roi(roi)
        x_reg, y_reg, width_reg, height_reg = ROI_REGISTERS
        self._write(x_reg, 0)
        self._write(y_reg, 0)
        self._write(width_reg, roi.width_px)
        self._write(height_reg, roi.height_px)
        self._write(x_reg, roi.x_px)
        self._write(y_reg, roi.y_px)


def refused(register: str, value: int, err: RegError) -> ConfigurationError:
    return ConfigurationError(f"device refused {register}={value}: {err.name}")
