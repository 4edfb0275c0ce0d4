"""PSF for any pixel from the radial tensor: interpolate in θ, rotate by φ, resample.

PSF_map(c, h, w, d) = P_resize ∘ P_rot( Σ_θ W(θ) PSF(c, θ, d) )  (paper §3.3).

* θ interpolation between the two bracketing tensor fields, either linear
  or with the paper's inverse-square weights W ∝ 1/Δθ² (compared in
  ``bmi bench render``).
* Rotation: tensor kernels have their radial axis along +col; a pixel at
  azimuth φ (measured from +col towards +row, image coordinates) needs that
  axis along (cos φ, sin φ). OpenCV's warpAffine with bicubic weights,
  negatives clipped, each channel renormalised to unit sum. Multiples of 90°
  are exact (np.rot90).
* Resampling when the sensor pitch differs from the tensor's (area
  interpolation, renormalised); identity for the nominal 2 µm sensor.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..geometry import SensorGeometry
from ..optics.tensor import PsfTensor

INTERPOLATIONS = ("linear", "inverse_square")


def rotate_kernel(kernel: np.ndarray, phi_deg: float) -> np.ndarray:
    """Rotate a (K, K) kernel so its +col axis points along azimuth φ (image coordinates, y down)."""
    turns = phi_deg / 90.0
    if abs(turns - round(turns)) < 1e-9:
        # +col → +row is a clockwise quarter turn on screen: np.rot90 with k = -1.
        return np.ascontiguousarray(np.rot90(kernel, k=-int(round(turns)) % 4))
    size = kernel.shape[-1]
    centre = ((size - 1) / 2.0, (size - 1) / 2.0)
    # cv2's positive angle turns counter-clockwise on screen; we need clockwise by φ.
    matrix = cv2.getRotationMatrix2D(centre, -phi_deg, 1.0)
    out = cv2.warpAffine(kernel.astype(np.float32), matrix, (size, size), flags=cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    out = np.maximum(out, 0.0)
    total = out.sum()
    return out / total if total > 0 else out


def resample_kernel(kernel: np.ndarray, scale: float) -> np.ndarray:
    """Resample a kernel by ``scale`` (output pixels per input pixel inverse: >1 enlarges), odd size kept."""
    if abs(scale - 1.0) < 1e-12:
        return kernel
    size = kernel.shape[-1]
    new = max(1, int(round(size * scale)) | 1)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    out = np.maximum(cv2.resize(kernel.astype(np.float32), (new, new), interpolation=interp), 0.0)
    return out / out.sum()


class PsfMap:
    """Kernels for arbitrary (θ, φ, depth index), built from a lazily filled :class:`PsfTensor`."""

    def __init__(self, tensor: PsfTensor, geometry: SensorGeometry, interpolation: str = "linear"):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
        self.tensor = tensor
        self.geometry = geometry
        self.interpolation = interpolation
        self.scale = tensor.spec.pitch_um / geometry.pitch_um
        self.field_deg = np.asarray(tensor.spec.field_deg, dtype=np.float64)

    @property
    def n_channels(self) -> int:
        return len(self.tensor.spec.channels)

    @property
    def kernel_px(self) -> int:
        return resample_kernel(np.zeros((self.tensor.spec.kernel_px,) * 2) + 1, self.scale).shape[-1]

    def _bracket(self, theta_deg: float):
        """Tensor indices and weights for θ (clamped to the tensor's field range)."""
        grid = self.field_deg
        t = float(np.clip(theta_deg, grid[0], grid[-1]))
        i = int(np.clip(np.searchsorted(grid, t) - 1, 0, len(grid) - 2))
        lo, hi = grid[i], grid[i + 1]
        if t <= lo:
            return [i], [1.0]
        if t >= hi:
            return [i + 1], [1.0]
        if self.interpolation == "linear":
            f = (t - lo) / (hi - lo)
            return [i, i + 1], [1.0 - f, f]
        w_lo, w_hi = 1.0 / (t - lo) ** 2, 1.0 / (hi - t) ** 2
        return [i, i + 1], [w_lo / (w_lo + w_hi), w_hi / (w_lo + w_hi)]

    def ensure(self, theta_deg, depth_indices) -> None:
        """Make the tensor entries that these fields and depths need available (batched)."""
        needed = sorted({i for t in np.atleast_1d(theta_deg) for i in self._bracket(float(t))[0]})
        self.tensor.ensure(needed, depth_indices)

    def kernels(self, theta_deg: float, phi_deg: float, depth_indices) -> np.ndarray:
        """(C, n_depths, K, K) float32 unit-sum kernels for one field position."""
        depth_indices = np.atleast_1d(np.asarray(depth_indices, dtype=int))
        idx, w = self._bracket(theta_deg)
        self.tensor.ensure(idx, depth_indices)
        base = sum(wi * self.tensor.data[:, i][:, depth_indices] for i, wi in zip(idx, w))
        out = np.empty((base.shape[0], base.shape[1], self.kernel_px, self.kernel_px), dtype=np.float32)
        for c in range(base.shape[0]):
            for j in range(base.shape[1]):
                k = resample_kernel(base[c, j], self.scale)
                out[c, j] = rotate_kernel(k, phi_deg) if not math.isclose(phi_deg, 0.0, abs_tol=1e-12) else k / k.sum()
        return out
