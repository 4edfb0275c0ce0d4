"""Spatially varying convolution: overlap-add over field zones, and a brute-force reference.

Zones sit on a square grid ``zone_px`` apart, anchored to absolute sensor
coordinates (centres at multiples of ``zone_px``), so a window rendered on
its own uses the same zones, hence the same result, as a larger render. Each zone owns a bilinear tent weight w_z (the weights form a
partition of unity over the window) and one kernel set, taken at its centre
pixel's (θ, φ). The output is Σ_z h_z * (w_z · x): every source pixel spreads
with a blend of its nearest zones' kernels, which conserves energy exactly
(each kernel sums to 1) and varies continuously across the field. The
brute-force reference spreads every source pixel with its own kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import fftconvolve


@dataclass(frozen=True)
class Zone:
    row: int  # centre, window coordinates (may lie just outside the window)
    col: int
    rows: slice  # support of its tent weight (window coordinates)
    cols: slice
    weight: np.ndarray  # (h, w) tent weight on that support


def _tents(length: int, step: int, origin: int):
    """Centres (window coordinates; absolute multiples of ``step``) and tent weights on [0, length)."""
    first = -(origin % step)
    centres = np.arange(first, length - 1 + step, step)
    centres = centres[(centres > -step) & (centres < length - 1 + step)]
    x = np.arange(length)[None, :]
    w = np.maximum(0.0, 1.0 - np.abs(x - centres[:, None]) / step)
    w /= w.sum(axis=0, keepdims=True)
    return centres, w


def zones(height: int, width: int, zone_px: int, row0: int = 0, col0: int = 0):
    """The zones of a window at (row0, col0) of the sensor, each with its tent weight support."""
    if zone_px < 2:
        raise ValueError(f"zone_px must be ≥ 2, got {zone_px}")
    rc, rw = _tents(height, zone_px, row0)
    cc, cw = _tents(width, zone_px, col0)
    out = []
    for i, r in enumerate(rc):
        rnz = np.nonzero(rw[i])[0]
        for j, c in enumerate(cc):
            cnz = np.nonzero(cw[j])[0]
            rows = slice(rnz[0], rnz[-1] + 1)
            cols = slice(cnz[0], cnz[-1] + 1)
            if len(rnz) == 0 or len(cnz) == 0:
                continue
            out.append(Zone(int(r), int(c), rows, cols,
                            np.outer(rw[i, rows], cw[j, cols]).astype(np.float32)))
    return out


def add_convolved(out: np.ndarray, images: np.ndarray, kernels: np.ndarray, rows: slice, cols: slice) -> None:
    """out[q] += kernels[q] * images[q] (full convolution), placed on the window, clipped to ``out``.

    images (Q, h, w) sit at (rows, cols) of out (Q, H, W); kernels (Q, K, K) are centred.
    """
    k = kernels.shape[-1]
    r = k // 2
    full = fftconvolve(images, kernels, mode="full", axes=(1, 2))
    top, left = rows.start - r, cols.start - r
    h, w = full.shape[1:]
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + h, out.shape[1]), min(left + w, out.shape[2])
    if r1 > r0 and c1 > c0:
        out[:, r0:r1, c0:c1] += full[:, r0 - top:r1 - top, c0 - left:c1 - left]


def spread_per_pixel(out: np.ndarray, image: np.ndarray, kernel_of) -> None:
    """Reference: out += Σ_y kernel_of(y) placed at y · image[y] (every source pixel its own kernel).

    image (H, W); kernel_of(row, col) -> (K, K). Only for small windows.
    """
    height, width = image.shape
    for row, col in zip(*np.nonzero(image)):
        k = kernel_of(row, col)
        r = k.shape[0] // 2
        r0, r1 = max(row - r, 0), min(row + r + 1, height)
        c0, c1 = max(col - r, 0), min(col + r + 1, width)
        out[r0:r1, c0:c1] += image[row, col] * k[r0 - row + r:r1 - row + r, c0 - col + r:c1 - col + r]
