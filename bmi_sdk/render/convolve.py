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


@dataclass(frozen=True)
class Zone:
    row: int  # centre, window coordinates (may lie just outside the window)
    col: int
    rows: slice  # support of its tent weight (window coordinates)
    cols: slice
    weight: np.ndarray  # (h, w) weight on that support


def _trapezoids(length: int, step: int, origin: int, ramp: int):
    """Centres (window coordinates; absolute multiples of ``step``) and 1-D weights on [0, length).

    w = clip(½ + (step/2 − |x − c|)/ramp, 0, 1): neighbouring weights sum to 1 for any ramp.
    """
    first = -(origin % step)
    centres = np.arange(first, length - 1 + step, step)
    centres = centres[(centres > -step) & (centres < length - 1 + step)]
    x = np.arange(length)[None, :]
    w = np.clip(0.5 + (step / 2 - np.abs(x - centres[:, None])) / ramp, 0.0, 1.0)
    w /= w.sum(axis=0, keepdims=True)
    return centres, w


def zones(height: int, width: int, zone_px: int, row0: int = 0, col0: int = 0, ramp_px: int | None = None):
    """The zones of a window at (row0, col0) of the sensor, each with its weight's support.

    ``ramp_px`` (default ``zone_px``: bilinear tents) is the width of the blend across zone borders.
    """
    if zone_px < 2:
        raise ValueError(f"zone_px must be ≥ 2, got {zone_px}")
    ramp = zone_px if ramp_px is None else ramp_px
    if not 1 <= ramp <= zone_px:
        raise ValueError(f"ramp_px must be in [1, zone_px = {zone_px}], got {ramp_px}")
    rc, rw = _trapezoids(height, zone_px, row0, ramp)
    cc, cw = _trapezoids(width, zone_px, col0, ramp)
    out = []
    for i, r in enumerate(rc):
        rnz = np.nonzero(rw[i])[0]
        for j, c in enumerate(cc):
            cnz = np.nonzero(cw[j])[0]
            if len(rnz) == 0 or len(cnz) == 0:  # a border zone whose weight stays outside the window
                continue
            rows = slice(rnz[0], rnz[-1] + 1)
            cols = slice(cnz[0], cnz[-1] + 1)
            out.append(Zone(int(r), int(c), rows, cols,
                            np.outer(rw[i, rows], cw[j, cols]).astype(np.float32)))
    return out


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
