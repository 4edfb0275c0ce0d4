"""``bmi eval``'s breakdown of a decoder's depth error: by range band, by distance to a depth edge, by signal level,
and the σ's worth.

Every pixel a row scores (valid, true range finite and > 0, read finite and > 0) falls in one range band of its
*true* range (``RANGE_BANDS_M``: < 2, 2–4, 4–6, ≥ 6 m) and in one edge band (``EDGE_BANDS``: within
``EDGE_NEAR_PX`` px of a depth edge, or beyond). A **depth edge** is a pixel whose true log range differs from a
4-neighbour's by more than ``EDGE_LOG_STEP`` (a range ratio above e^0.1 ≈ 1.105 between neighbours, the step the
procedural scenes' own test counts as an occlusion edge; a slanted surface changes far less per pixel); both
pixels of such a pair are edge pixels, and a pixel's distance to the nearest one is the Euclidean distance
transform (``scipy.ndimage.distance_transform_edt``) of the tile's rendered window, so a step just outside the
tile counts. Each pixel also falls in one signal band (``SIGNAL_BANDS``) of its noiseless signal at the sensor: the
mean over colours of the optical image (the scene blurred by the camera's kernels, relative illumination applied),
as a fraction of the white level. The noise is the same at every signal in the benchmark's conditions, so the
bands are bands of signal-to-noise ratio: at σ 0.005, < 4, 4–10 and ≥ 10. A stratum's numbers pool its pixels
over the tiles of a region (every pixel weighs the same; the headline row averages per tile): AbsRel, RMSE, δ1, its
share of the pixels and its share of the summed absolute relative error.

For a decoder that reports a 1σ:

* **confident coverage**: the share of the scored pixels whose reported σ / read depth ≤ ``CONFIDENT_REL_SIGMA``
  (0.1), as ``report.json``'s; with the AbsRel of those pixels (``confident_absrel``);
* **σ honesty**: z = (read − true) / σ over the scored pixels; ``sigma_z_std`` is its standard deviation (1 for an
  honest σ, ≫ 1 confidently wrong, ≪ 1 too wide) and ``sigma_z_rms`` its RMS. Both are sums of squares, so a few
  confidently wrong pixels (an occluding rim read as the background behind it) can hold them near 1 while the σ is
  far too wide everywhere else; ``sigma_z_within_1``, the share of pixels with |z| ≤ 1, reads the typical pixel
  instead (``HONEST_WITHIN_1`` for an honest Gaussian σ; near 1 where the σ is too wide).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

RANGE_BANDS_M = {"< 2 m": (0.0, 2.0), "2–4 m": (2.0, 4.0), "4–6 m": (4.0, 6.0), "> 6 m": (6.0, math.inf)}
"""Range bands of the true range (lower bound included, upper excluded)."""
EDGE_LOG_STEP = 0.1
"""|Δ log range| between 4-neighbours above which both are depth-edge pixels."""
EDGE_NEAR_PX = 8.0
"""Pixels at most this far (px, Euclidean) from a depth-edge pixel are "near an edge"."""
EDGE_BANDS = ("≤ 8 px from an edge", "> 8 px from an edge")
SIGNAL_BANDS = {"signal < 0.02": (-math.inf, 0.02), "signal 0.02–0.05": (0.02, 0.05), "signal ≥ 0.05": (0.05, math.inf)}
"""Bands of a pixel's noiseless signal at the sensor (fraction of white; lower bound included, upper excluded)."""
CONFIDENT_REL_SIGMA = 0.1
"""A pixel is confident where its reported 1σ is at most this fraction of its read depth."""
HONEST_WITHIN_1 = math.erf(1 / math.sqrt(2))
"""The share of a Gaussian's draws within one σ of its mean (0.683): ``sigma_z_within_1`` of an honest σ."""


def depth_edges(range_m: np.ndarray, log_step: float = EDGE_LOG_STEP) -> np.ndarray:
    """H × W bool: pixels whose log range differs from a 4-neighbour's by more than ``log_step`` (both finite)."""
    log_range = np.log(np.where(np.isfinite(range_m) & (range_m > 0), range_m, np.nan))
    edges = np.zeros(range_m.shape, bool)
    with np.errstate(invalid="ignore"):
        rows = np.abs(np.diff(log_range, axis=0)) > log_step
        cols = np.abs(np.diff(log_range, axis=1)) > log_step
    edges[:-1] |= rows
    edges[1:] |= rows
    edges[:, :-1] |= cols
    edges[:, 1:] |= cols
    return edges


def edge_distance_px(range_m: np.ndarray, log_step: float = EDGE_LOG_STEP) -> np.ndarray:
    """H × W float: each pixel's Euclidean distance (px) to the nearest depth-edge pixel (0 on one; inf when the
    map holds none)."""
    edges = depth_edges(range_m, log_step)
    if not edges.any():
        return np.full(range_m.shape, np.inf)
    return ndimage.distance_transform_edt(~edges)


def _band_sums(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """[pixels, Σ |p − t| / t, Σ (p − t)², pixels with max(p/t, t/p) < 1.25] of 1-D reads and truths."""
    rel = np.abs(pred - true) / true
    ratio = np.maximum(pred / true, true / pred)
    return np.array([pred.size, rel.sum(), ((pred - true) ** 2).sum(), np.count_nonzero(ratio < 1.25)], np.float64)


class StrataSums:
    """Running sums of the breakdown over any number of tiles (``add``), read as metrics by ``summary``."""

    def __init__(self):
        self.bands = {name: np.zeros(4) for name in (*RANGE_BANDS_M, *EDGE_BANDS, *SIGNAL_BANDS)}
        self.total = np.zeros(4)
        self.confident = np.zeros(4)
        self.sigma_pixels = self.z_count = self.z_within_1 = 0
        self.z_sum = self.z2_sum = 0.0

    def add(self, pred_m: np.ndarray, true_m: np.ndarray, valid: np.ndarray, sigma_m: np.ndarray | None,
            edge_distance: np.ndarray, signal: np.ndarray) -> None:
        """One tile: its read ``pred_m``, true range ``true_m``, scored pixels ``valid`` (further narrowed to finite,
        positive reads and truths), reported 1σ ``sigma_m`` (None: the decoder reports none), each pixel's
        ``edge_distance`` (``edge_distance_px``) and its noiseless ``signal`` at the sensor (fraction of white), all
        H × W."""
        with np.errstate(invalid="ignore"):
            ok = valid & np.isfinite(pred_m) & np.isfinite(true_m) & (pred_m > 0) & (true_m > 0)
        p, t, d, g = (np.asarray(a, np.float64)[ok] for a in (pred_m, true_m, edge_distance, signal))
        self.total += _band_sums(p, t)
        for name, (lo, hi) in RANGE_BANDS_M.items():
            inside = (t >= lo) & (t < hi)
            self.bands[name] += _band_sums(p[inside], t[inside])
        near = d <= EDGE_NEAR_PX
        self.bands[EDGE_BANDS[0]] += _band_sums(p[near], t[near])
        self.bands[EDGE_BANDS[1]] += _band_sums(p[~near], t[~near])
        for name, (lo, hi) in SIGNAL_BANDS.items():
            inside = (g >= lo) & (g < hi)
            self.bands[name] += _band_sums(p[inside], t[inside])
        if sigma_m is not None:
            s = np.asarray(sigma_m, np.float64)[ok]
            with np.errstate(divide="ignore", invalid="ignore"):
                confident = s <= CONFIDENT_REL_SIGMA * p
                z = (p - t) / s
            self.confident += _band_sums(p[confident], t[confident])
            z = z[np.isfinite(z)]
            self.sigma_pixels += p.size
            self.z_sum += float(z.sum())
            self.z2_sum += float((z ** 2).sum())
            self.z_within_1 += int(np.count_nonzero(np.abs(z) <= 1.0))
            self.z_count += z.size

    def summary(self) -> dict:
        """{"by_range": {band: metrics}, "by_edge": {band: metrics}, "by_signal": {band: metrics}} and, with a σ,
        ``confident_coverage``, ``confident_absrel``, ``sigma_z_rms``, ``sigma_z_std``, ``sigma_z_within_1``;
        metrics: pixel_share, error_share, absrel, rmse_m, delta1 (NaN where a band holds no pixel)."""
        def metrics(sums: np.ndarray) -> dict:
            n, rel, sq, hits = sums
            share = {"pixel_share": n / self.total[0] if self.total[0] else math.nan,
                     "error_share": rel / self.total[1] if self.total[1] else math.nan}
            if not n:
                return {**share, "absrel": math.nan, "rmse_m": math.nan, "delta1": math.nan}
            return {**share, "absrel": rel / n, "rmse_m": math.sqrt(sq / n), "delta1": hits / n}

        out = {"by_range": {name: metrics(self.bands[name]) for name in RANGE_BANDS_M},
               "by_edge": {name: metrics(self.bands[name]) for name in EDGE_BANDS},
               "by_signal": {name: metrics(self.bands[name]) for name in SIGNAL_BANDS}}
        if self.sigma_pixels:
            out["confident_coverage"] = float(self.confident[0] / self.sigma_pixels)
            out["confident_absrel"] = float(self.confident[1] / self.confident[0]) if self.confident[0] else math.nan
            count = max(self.z_count, 1)
            mean = self.z_sum / count
            out["sigma_z_rms"] = math.sqrt(self.z2_sum / count)
            out["sigma_z_std"] = math.sqrt(max(self.z2_sum / count - mean ** 2, 0.0))
            out["sigma_z_within_1"] = self.z_within_1 / count if self.z_count else math.nan
        return out
