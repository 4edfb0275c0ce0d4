"""sRGB-encoded 8/16-bit images to linear light (IEC 61966-2-1 transfer curve).

Dataset images (NYU's Kinect RGB, FlyingThings3D's renders, Middlebury's
photographs) are stored display-encoded; the simulator needs linear radiance.
"""

from __future__ import annotations

import numpy as np


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] (float) to linear light, float32."""
    v = np.asarray(encoded, dtype=np.float32)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_uint_to_linear(image: np.ndarray) -> np.ndarray:
    """Decode a uint8 or uint16 sRGB image to linear float32 in [0, 1] via a lookup table."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"expected a uint8 or uint16 sRGB image, got {image.dtype}")
    levels = np.iinfo(image.dtype).max
    lut = srgb_to_linear(np.arange(levels + 1, dtype=np.float64) / levels)
    return lut[image]
