"""The contract between simulation, training and inference.

One preprocessing path turns a raw Bayer window into the network's input, in
training (simulated raw frames) and at run time (camera or DNG frames) alike:
demosaic (OpenCV, bilinear, on the raw integers: OpenCV demosaics only 8/16-bit
data, and bilinear demosaicing is linear, so this equals demosaicing after the
black-level subtraction) → black level → scale to [0, 1] → clip.

Network input (N × 6 × H × W float32, H and W multiples of 4):
  0–2  demosaiced linear RGB in [0, 1]
  3    θ / 60°  (field angle of each pixel's chief ray; 1.0 at the field edge)
  4    cos φ    (azimuth of the pixel around the optical centre)
  5    sin φ
Outputs: ``aif`` N × 3 × H × W (linear RGB), ``depth_m`` N × 1 × H × W (range
in metres along each pixel's chief ray). The field channels come from the
sensor geometry and the window's offset on the full sensor (ROI frames too),
so a tile knows where it sits on the sensor.
"""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import SensorGeometry

INPUT_CHANNELS = 6
FIELD_NORM_DEG = 60.0
SIZE_MULTIPLE = 4
INPUT_NAME = "coded"
OUTPUT_NAMES = ("aif", "depth_m")
SIGMA_OUTPUT_NAME = "depth_sigma_m"
"""The learned refinement's third output: 1σ of ``depth_m`` (m). Its input is the 6 channels above followed
by the classical decoder's channels (``decode.features``); its manifest says how many and the decoder
knobs that make them (``decoder: "learned"``, ``classical_config``)."""

# OpenCV names Bayer codes after the 2×2 pattern starting at the second row/col:
# an RGGB sensor is COLOR_BayerBG2RGB (checked against a synthetic mosaic in the tests).
_BAYER_CODES = {"RGGB": cv2.COLOR_BayerBG2RGB, "BGGR": cv2.COLOR_BayerRG2RGB,
                "GRBG": cv2.COLOR_BayerGB2RGB, "GBRG": cv2.COLOR_BayerGR2RGB}
_SHIFT = {(0, 0): "RGGB", (0, 1): "GRBG", (1, 0): "GBRG", (1, 1): "BGGR"}


def window_cfa(sensor_cfa: str, row0: int, col0: int) -> str:
    """CFA pattern as seen from a window starting at (row0, col0) of a sensor whose pattern is ``sensor_cfa``."""
    if sensor_cfa != "RGGB":
        raise ValueError(f"only RGGB sensors are supported, got {sensor_cfa!r}")
    return _SHIFT[(row0 % 2, col0 % 2)]


def reflect_indices(start: int, length: int, size: int) -> np.ndarray:
    """Indices ``start … start+length-1`` folded into ``[0, size)`` by mirror reflection (edge not repeated).

    Reflection maps index i to one of the same parity, so a Bayer mosaic keeps
    its phase; it works for any extent, also far beyond a tiny frame.
    """
    idx = np.arange(start, start + length)
    if size == 1:
        return np.zeros(length, np.intp)
    period = 2 * (size - 1)
    m = np.mod(idx, period)
    return np.where(m < size, m, period - m).astype(np.intp)


def raw_to_rgb(raw: np.ndarray, black_level: float, white_level: float, cfa: str = "RGGB") -> np.ndarray:
    """Raw Bayer window (H × W integers) → H × W × 3 float32 linear RGB in [0, 1].

    ``cfa`` is the pattern at the window's (0, 0) pixel (see :func:`window_cfa`).
    """
    if raw.ndim != 2:
        raise ValueError(f"raw frame must be H × W, got shape {raw.shape}")
    if not white_level > black_level:
        raise ValueError(f"white level {white_level} must exceed black level {black_level}")
    if cfa not in _BAYER_CODES:
        raise ValueError(f"unknown CFA {cfa!r}; one of {sorted(_BAYER_CODES)}")
    if raw.dtype != np.uint16:
        if raw.min() < 0 or raw.max() > 65535:
            raise ValueError("raw values must fit in 16 bits")
        raw = raw.astype(np.uint16)
    rgb = cv2.cvtColor(raw, _BAYER_CODES[cfa]).astype(np.float32)
    np.subtract(rgb, np.float32(black_level), out=rgb)  # in place: a full frame's RGB is 324 MB a copy
    np.divide(rgb, np.float32(white_level - black_level), out=rgb)
    return np.clip(rgb, 0.0, 1.0, out=rgb)


def field_channels(geometry: SensorGeometry, row0: int, col0: int, height: int, width: int) -> np.ndarray:
    """3 × H × W float32: θ/60°, cos φ, sin φ of each pixel of the window."""
    radial, cos_phi, sin_phi = geometry.window_polar(row0, col0, height, width)
    theta = geometry.field_deg_from_radial_mm(radial)
    out = np.empty((3, height, width), np.float32)
    np.divide(theta, FIELD_NORM_DEG, out=out[0], casting="unsafe")
    np.nan_to_num(out[0], copy=False, nan=1.0)
    out[1], out[2] = cos_phi, sin_phi
    return out


def network_input(rgb: np.ndarray, geometry: SensorGeometry, row0: int, col0: int) -> np.ndarray:
    """1 × 6 × H × W float32 from a demosaiced window and its position on the sensor."""
    h, w, _ = rgb.shape
    return np.concatenate([rgb.transpose(2, 0, 1), field_channels(geometry, row0, col0, h, w)])[None]
