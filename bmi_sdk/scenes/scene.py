"""The scene record every source produces, and the pinhole camera of dataset images.

A scene is what the forward simulator images: linear RGB (H×W×3 float32 in
[0, 1]) and the *range along each pixel's ray* in metres (H×W float32, NaN
where unknown) — the SDK's depth convention (DESIGN.md). Dataset images come
from ordinary pinhole cameras, so their record carries those intrinsics; the
conversion between a pinhole's planar z and range is explicit here, never
assumed elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeIntrinsics:
    """A pinhole camera: focal lengths and principal point in pixels, 0-based pixel centres."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int

    def __post_init__(self):
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx_px}, fy={self.fy_px}")
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}×{self.height_px}")

    def ray_length_per_z(self) -> np.ndarray:
        """H×W factor range/z = 1/cos α = √(1 + x² + y²) of each pixel's ray (float64)."""
        x = (np.arange(self.width_px, dtype=np.float64) - self.cx_px) / self.fx_px
        y = (np.arange(self.height_px, dtype=np.float64) - self.cy_px) / self.fy_px
        return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)

    def z_to_range(self, z_m: np.ndarray) -> np.ndarray:
        """Range along each pixel's ray from the planar z-depth map (H×W) of this camera."""
        self._check_shape(z_m)
        return (np.asarray(z_m, dtype=np.float64) * self.ray_length_per_z()).astype(np.float32)

    def range_to_z(self, range_m: np.ndarray) -> np.ndarray:
        """Planar z-depth map of this camera from the range along each pixel's ray (H×W)."""
        self._check_shape(range_m)
        return (np.asarray(range_m, dtype=np.float64) / self.ray_length_per_z()).astype(np.float32)

    def _check_shape(self, a) -> None:
        if np.shape(a) != (self.height_px, self.width_px):
            raise ValueError(f"depth map of shape {np.shape(a)} does not match the "
                             f"{self.height_px}×{self.width_px} intrinsics")


@dataclass(frozen=True)
class Scene:
    """Linear RGB + range along the ray (metres, NaN unknown); ``intrinsics`` is None for sensor-space scenes."""

    rgb: np.ndarray
    range_m: np.ndarray
    name: str
    intrinsics: PinholeIntrinsics | None = None

    def __post_init__(self):
        rgb, rng = self.rgb, self.range_m
        if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.float32):
            raise ValueError(f"scene {self.name!r}: rgb must be an H×W×3 float32 array, got "
                             f"{getattr(rgb, 'shape', None)} {getattr(rgb, 'dtype', type(rgb))}")
        if not (isinstance(rng, np.ndarray) and rng.shape == rgb.shape[:2] and rng.dtype == np.float32):
            raise ValueError(f"scene {self.name!r}: range_m must be an H×W float32 array matching rgb "
                             f"{rgb.shape[:2]}, got {getattr(rng, 'shape', None)} {getattr(rng, 'dtype', type(rng))}")
        k = self.intrinsics
        if k is not None and (k.height_px, k.width_px) != rgb.shape[:2]:
            raise ValueError(f"scene {self.name!r}: intrinsics are for {k.height_px}×{k.width_px}, "
                             f"image is {rgb.shape[0]}×{rgb.shape[1]}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.rgb.shape[:2]
