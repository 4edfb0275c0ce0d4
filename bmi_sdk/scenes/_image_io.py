"""Reading dataset PNGs as linear RGB (shared by the FlyingThings3D and Middlebury loaders)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from bmi_sdk.color import srgb_uint_to_linear


def read_srgb_png_linear(path: Path) -> np.ndarray:
    """An 8/16-bit sRGB PNG (grey, RGB or RGBA) as linear H×W×3 float32."""
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: not a readable image")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = image[:, :, :3]
    return srgb_uint_to_linear(np.ascontiguousarray(image[:, :, ::-1]))  # OpenCV's BGR -> RGB
