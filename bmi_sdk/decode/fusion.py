"""Inverse-variance fusion of two depth reads of the same pixels, in log depth.

The learned refinement (``--decoder learned``) returns a depth and a 1σ from its network; its classical
stage returned its own depth and 1σ from the camera's kernels. Each σ is honest on its own (``bmi eval``'s
error/σ spread), and neither read is better everywhere: the network fills textureless windows and reads
tile-scale clutter better, the physics reads large textured surfaces better (docs/results.md, session 15).
The learned decoder's output is their fusion:

    p = r_b² / (r_a² + r_b²),   log d = p log d_a + (1 − p) log d_b,   r = p r_a + (1 − p) r_b,   σ = r d,

with r = σ / d each read's relative 1σ, the 1σ of its log depth to first order. The weight is the
inverse-variance one. The fused σ is the one the two reads would have if their errors were fully
correlated (ρ = 1): the network reads the classical stage's output, so the two errors are not
independent, and for any ρ ≤ 1 the fused estimate's spread is at most this
(p² r_a² + (1−p)² r_b² + 2ρ p(1−p) r_a r_b ≤ (p r_a + (1−p) r_b)²). The tests check that bound against
correlated draws.

Where only one read is valid (finite, positive depth and σ), it is the output; where neither, NaN.
"""

from __future__ import annotations

import numpy as np


def _read_ok(depth_m: np.ndarray, sigma_m: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth_m) & np.isfinite(sigma_m) & (depth_m > 0) & (sigma_m > 0)


def fuse_log_depth(depth_a_m: np.ndarray, sigma_a_m: np.ndarray, depth_b_m: np.ndarray,
                   sigma_b_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth_m, sigma_m, weight_a) of the fusion (module doc) of reads a and b, arrays of one shape.

    ``weight_a`` is p, the share read a has in each pixel's log depth (1 where only a is valid, 0 where only
    b is, NaN where neither): its mean says how much of a frame each read decided.
    """
    shapes = {np.shape(x) for x in (depth_a_m, sigma_a_m, depth_b_m, sigma_b_m)}
    if len(shapes) != 1:
        raise ValueError(f"the two reads' depth and sigma maps must have one shape, got {sorted(shapes)}")
    ok_a, ok_b = _read_ok(depth_a_m, sigma_a_m), _read_ok(depth_b_m, sigma_b_m)
    both = ok_a & ok_b
    safe_a, safe_b = np.where(ok_a, depth_a_m, 1.0), np.where(ok_b, depth_b_m, 1.0)
    rel_a = np.where(ok_a, sigma_a_m, 1.0) / safe_a
    rel_b = np.where(ok_b, sigma_b_m, 1.0) / safe_b
    weight_a = np.where(both, rel_b ** 2 / (rel_a ** 2 + rel_b ** 2), np.where(ok_a, 1.0, 0.0))
    log_depth = weight_a * np.log(safe_a) + (1.0 - weight_a) * np.log(safe_b)
    depth = np.exp(log_depth)
    sigma = (weight_a * rel_a + (1.0 - weight_a) * rel_b) * depth
    none = ~(ok_a | ok_b)
    dtype = np.result_type(depth_a_m, depth_b_m)
    depth, sigma, weight_a = (np.where(none, np.nan, x).astype(dtype, copy=False) for x in (depth, sigma, weight_a))
    return depth, sigma, weight_a
