"""The sRGB transfer function (IEC 61966-2-1), both ways: linear light ↔ display-encoded values in [0, 1].

The one home of the curve. Dataset images (NYU's Kinect RGB, FlyingThings3D's
renders, Middlebury's photographs), ``bmi simulate --rgb`` files and the
simulated camera's image stand-in are stored display-encoded and are decoded
here to the linear radiance the simulator needs; the runtime's AiF images,
point-cloud colours and ``bmi simulate``'s previews are encoded here for
viewing. numpy only and outside the layered packages, so every layer may use it.

The curve is a line near black and a 2.4 power law above it, the two meeting
at linear ``SRGB_LINEAR_KNEE`` (encoded ``SRGB_ENCODED_KNEE``).
"""

from __future__ import annotations

import numpy as np

SRGB_LINEAR_KNEE = 0.0031308
"""Linear value where the encoding turns from ``12.92 x`` to ``1.055 x^(1/2.4) − 0.055``."""
SRGB_ENCODED_KNEE = 0.04045
"""Encoded value where the decoding turns from ``v / 12.92`` to ``((v + 0.055) / 1.055)^2.4`` (the same knee)."""


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Encode linear values (clipped to [0, 1] first) to sRGB in [0, 1], float32."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= SRGB_LINEAR_KNEE, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] (float) to linear light, float32."""
    v = np.asarray(encoded, dtype=np.float32)
    return np.where(v <= SRGB_ENCODED_KNEE, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_uint_to_linear(image: np.ndarray) -> np.ndarray:
    """Decode a uint8 or uint16 sRGB image (full scale = the type's maximum) to linear float32 in [0, 1]
    through a lookup table of every code value."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"expected a uint8 or uint16 sRGB image, got {image.dtype}")
    levels = np.iinfo(image.dtype).max
    lut = srgb_to_linear(np.arange(levels + 1, dtype=np.float64) / levels)
    return lut[image]
