"""Pooling the windows' evidence over neighbours that look alike: robust, colour-guided cost aggregation.

One window's likelihood curve is flat where its texture is weak (a dark or smooth surface), and its
read there is noise. Neighbouring windows of the same surface see the same depth; under that
hypothesis their negative log-likelihoods add. The pooled curve of window i is

    A_i(d) = E_i(d) + Σ_{j ≠ i} w_ij · min(E_j(d), τ),
    w_ij = exp(−r_ij² / 2 s²) · exp(−|g_i − g_j|² / 2 c²),

E the window's NLL less its minimum (nats), r the distance between the windows (in windows), g
the windows' log mean colour, s the pooling radius, c the colour scale and τ the truncation.
Two choices keep it from spreading one surface's depth into another (cost-volume filtering with
an edge-aware weight, as in stereo: Hosni et al., "Fast cost-volume filtering for visual
correspondence and beyond", TPAMI 2013):

* the colour weight: windows across a colour edge, usually an object's outline, barely count;
* the truncation τ: a neighbour can speak against a depth by at most τ nats, so a few confident
  windows of another surface (or windows that mix two depths) cannot outvote the window's own
  evidence; flat curves, which carry no evidence, still take their neighbours' depth.

Window i's own curve is never truncated. Only the estimate moves: the decoder keeps each window's
own curvature for its σ (``classical``, step 4), since the neighbours' curves share pixels with it
and with each other and do not add up to independent evidence.
"""

from __future__ import annotations

import math

import numpy as np

COLOUR_FLOOR = 1e-3
"""Mean signal (units of full scale) below which a window's colour is taken as this floor: the log of a
black window's mean is noise."""


def window_colour(means: list[np.ndarray]) -> np.ndarray:
    """(windows, 3) log mean colour (R, mean of the two G, B) from the four Bayer planes' per-window means
    (R, G1, G2, B order), floored at ``COLOUR_FLOOR``."""
    r, g1, g2, b = (np.asarray(m, np.float64) for m in means)
    rgb = np.stack([r, 0.5 * (g1 + g2), b], axis=-1)
    return np.log(np.maximum(rgb, COLOUR_FLOOR)).astype(np.float32)


def pool_evidence(curves: np.ndarray, colour: np.ndarray, sigma_windows: float, colour_sigma: float,
                  truncate_nats: float) -> np.ndarray:
    """Pooled curves (module doc) of a window grid.

    ``curves``: (rows, cols, D) each window's NLL less its minimum, NaN for windows without a decode (skipped
    blocks), which neither pool nor are pooled; ``colour``: (rows, cols, 3) ``window_colour``. Neighbours are
    taken within 2 ``sigma_windows`` (the Gaussian's weight beyond is < 0.14). Returns (rows, cols, D) float32.
    """
    if not sigma_windows > 0 or not colour_sigma > 0 or not truncate_nats >= 0:
        raise ValueError(f"pooling needs sigma_windows > 0, colour_sigma > 0 and truncate_nats >= 0; got "
                         f"{sigma_windows}, {colour_sigma}, {truncate_nats}")
    rows, cols, _ = curves.shape
    valid = np.isfinite(curves).all(axis=-1)
    own = np.where(valid[..., None], curves, 0.0).astype(np.float32)
    clipped = np.minimum(own, np.float32(truncate_nats))
    reach = int(math.ceil(2.0 * sigma_windows))
    pad = ((reach, reach), (reach, reach))
    clipped_p = np.pad(clipped, pad + ((0, 0),))
    colour_p = np.pad(np.where(valid[..., None], colour, 0.0).astype(np.float32), pad + ((0, 0),))
    valid_p = np.pad(valid, pad)
    pooled = own.copy()
    inv_two_c2 = np.float32(1.0 / (2.0 * colour_sigma ** 2))
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            r2 = dr * dr + dc * dc
            if r2 == 0 or r2 > reach * reach:
                continue
            box = slice(reach + dr, reach + dr + rows), slice(reach + dc, reach + dc + cols)
            diff = colour_p[box] - colour
            weight = np.exp(np.float32(-r2 / (2.0 * sigma_windows ** 2)) - (diff * diff).sum(axis=-1) * inv_two_c2)
            weight *= valid_p[box]
            pooled += weight[..., None] * clipped_p[box]
    return np.where(valid[..., None], pooled, np.nan).astype(np.float32)
