"""Sensor readout: irradiance source → cos θ falloff → RGGB → exposure, noise, gain → 12-bit ADC.

Runs on horizontal strips of the readout window so a full 6000×4500 frame
never holds more than a strip of float irradiance. Noise is independent per
pixel, so filtering by the CFA before drawing noise (as here) has the same
distribution as noising three planes and then filtering, at a third of the cost.
Every step calls ``bmi_sdk.sensor``; nothing is re-implemented here.
"""

from __future__ import annotations

import threading
from typing import Callable

import numpy as np

from bmi_sdk.geometry import SensorGeometry
from bmi_sdk.protocol.registers import TestPattern
from bmi_sdk.sensor import SensorModel, bayer_mosaic, relative_illumination

from .sources import IrradianceSource

STRIP_ROWS = 256


class ReadoutCancelled(Exception):
    """The readout was abandoned between strips (the host stopped, left, or the process is exiting)."""


class Readout:
    """Produces raw frames of a window; caches the cos θ map of the last window."""

    def __init__(self, geometry: SensorGeometry, model: SensorModel):
        self.geometry = geometry
        self.model = model
        self._ri_key = None
        self._ri = None

    def _illumination(self, x, y, w, h):
        key = (x, y, w, h)
        if self._ri_key != key:
            self._ri = relative_illumination(self.geometry, y, x, h, w)
            self._ri_key = key
        return self._ri

    def sensor_frame(self, source: IrradianceSource, roi: tuple[int, int, int, int], exposure_us: float,
                     analog_gain: float, black_level_dn: int, rng: np.random.Generator,
                     cancel: threading.Event | None = None,
                     progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """H×W uint16 raw DN of the window ``roi = (x, y, width, height)``.

        Between strips it raises ``ReadoutCancelled`` once ``cancel`` is set and reports
        ``progress(rows_done, rows_total)``: a slow source (a scene rendered through the lens) can be
        stopped, and the host can tell "still reading out" from "dead".
        """
        x, y, w, h = roi
        out = np.empty((h, w), np.uint16)
        ri = self._illumination(x, y, w, h)
        for r in range(0, h, STRIP_ROWS):
            if cancel is not None and cancel.is_set():
                raise ReadoutCancelled(f"readout cancelled after {r} of {h} rows")
            if progress is not None:
                progress(r, h)
            rows = min(STRIP_ROWS, h - r)
            irr = np.asarray(source.irradiance(y + r, x, rows, w))
            if irr.shape != (rows, w, 3):
                raise ValueError(f"source {source.name!r} returned shape {irr.shape} for a {rows}×{w} window "
                                 f"(expected {(rows, w, 3)})")
            mosaic = bayer_mosaic(irr, y + r, x).astype(np.float32, copy=False) * ri[r:r + rows]
            out[r:r + rows] = self.model.expose_mosaic(mosaic, exposure_us, analog_gain, black_level_dn, rng)
        return out

    def test_pattern(self, pattern: TestPattern, roi: tuple[int, int, int, int], frame_id: int) -> np.ndarray:
        """Digital pattern in full-sensor coordinates, bit-exact (bypasses the analog chain)."""
        x, y, w, h = roi
        offset = frame_id if pattern == TestPattern.WALKING else 0
        rows = (np.arange(y, y + h, dtype=np.uint32) + np.uint32(offset % 4096))[:, None]
        cols = np.arange(x, x + w, dtype=np.uint32)[None, :]
        out = np.empty((h, w), np.uint16)
        np.add(rows, cols, out=out, dtype=np.uint16, casting="unsafe")  # wraps mod 65536, a multiple of 4096
        out &= np.uint16(self.model.white_level_dn)
        return out
