"""Depth layers: which tensor depth each scene pixel belongs to.

Layer k holds the pixels whose range is nearest to the tensor's depth d_k
(default grid 0.7–10 m every 0.1 m, so K = 94). Layer 0 is the farthest,
K − 1 the nearest (the compositing order of ``compose``). Ranges beyond the
grid clamp to its ends; unknown ranges (NaN, ≤ 0) go to the farthest layer —
they are background of unknown depth, rendered with the far-field PSF.
"""

from __future__ import annotations

import numpy as np


def layer_index(range_m: np.ndarray, depth_grid_m: np.ndarray) -> np.ndarray:
    """Per pixel, the layer index (0 = farthest) of the nearest grid depth."""
    grid = np.asarray(depth_grid_m, dtype=np.float64)
    if np.any(np.diff(grid) <= 0):
        raise ValueError("the depth grid must increase")
    r = np.asarray(range_m, dtype=np.float64)
    r = np.where(np.isfinite(r) & (r > 0), r, grid[-1])
    nearest = np.abs(r[..., None] - grid).argmin(axis=-1) if r.size < 4096 else _nearest_sorted(r, grid)
    return (len(grid) - 1 - nearest).astype(np.int32)


def _nearest_sorted(r: np.ndarray, grid: np.ndarray) -> np.ndarray:
    j = np.clip(np.searchsorted(grid, r), 1, len(grid) - 1)
    left = grid[j - 1]
    right = grid[j]
    return np.where(r - left <= right - r, j - 1, j)


def tensor_depth_index(k, n_depths: int):
    """Index into the tensor's depth axis for layer ``k``."""
    return n_depths - 1 - np.asarray(k)
