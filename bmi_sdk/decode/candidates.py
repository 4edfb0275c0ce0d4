"""Candidate depths for the evidence: evenly spaced in inverse depth, on the kernel source's depth grid.

Defocus (W020) is nearly linear in 1/d, so a grid even in 1/d spends its candidates where the PSF
changes. The kernels come from a ``PsfMap`` over a PSF tensor whose depth axis is fixed (0.7–10 m
every 0.1 m by default, the grid the renderer also quantises scenes to), so each wanted 1/d is
snapped to the nearest tensor depth and duplicates are dropped: near the camera, where 0.1 m is
already coarser than the wanted 1/d step, every tensor depth is a candidate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Candidates:
    """Depth candidates: ``depth_m`` (increasing) and their ``index`` into the kernel source's depth grid."""

    depth_m: np.ndarray
    index: np.ndarray

    @property
    def inv_depth_per_m(self) -> np.ndarray:
        return 1.0 / self.depth_m

    def __len__(self) -> int:
        return len(self.depth_m)

    def subset(self, keep: np.ndarray) -> "Candidates":
        return Candidates(self.depth_m[keep], self.index[keep])


def inverse_depth_candidates(grid_depth_m, count: int, near_m: float | None = None,
                             far_m: float | None = None) -> Candidates:
    """About ``count`` candidates from ``grid_depth_m`` (finite values), evenly spaced in 1/d over [near, far]."""
    grid = np.asarray(grid_depth_m, dtype=np.float64)
    finite = np.flatnonzero(np.isfinite(grid))
    if len(finite) < 3:
        raise ValueError("the kernel source needs at least 3 finite depths")
    near_m = float(grid[finite].min()) if near_m is None else near_m
    far_m = float(grid[finite].max()) if far_m is None else far_m
    if not 0 < near_m < far_m:
        raise ValueError(f"candidate range must satisfy 0 < near < far, got {near_m}, {far_m} m")
    if count < 3:
        raise ValueError(f"at least 3 candidates are needed to refine a minimum, got {count}")
    wanted = np.linspace(1.0 / far_m, 1.0 / near_m, count)
    inv_grid = 1.0 / grid[finite]
    picks = np.unique(finite[np.argmin(np.abs(inv_grid[None, :] - wanted[:, None]), axis=1)])
    order = np.argsort(grid[picks])
    picks = picks[order]
    return Candidates(grid[picks], picks.astype(int))
