"""Evidence of windows holding clipped samples: the likelihood of their unclipped samples alone.

A sample at the white level is censored: its true signal is somewhere above, and it fits no Gaussian model. A
window that holds one would read a clipped plateau's sharp rim as a sharp kernel, confidently and wrongly, so
the plain likelihood (``evidence``) gives such a window none of that plane's evidence. But every other sample of
the window is the blurred image plus noise, exactly as in an unclipped window: clipping happens at the sensor,
after the blur. Leaving the clipped samples out is a change of taper: t' = t · g, g 0 at each clipped sample and
rising smoothly to 1 over ``ClassicalConfig.clipped_ramp_samples`` around it (``clipped_weights``; a ramp, not a
hard hole, because clipping is not missing at random). The model of the tapered window's periodogram changes with
the taper: the exact expected periodogram under t' (``masked_window``, ``evidence.tapered_periodogram``; a taper
with holes has a broad transform, through which the window's mean removal reaches every bin, which the
taper-smoothed model leaves out). So a bright surface whose noise pushes a few samples over white, or a window
reaching the rim of a saturated highlight, keeps its evidence.

Each such (window, plane) has its own taper, so its model is made for it alone from the zone's plane
autocovariances (``evidence.plane_autocovariance``, once per block and pass, at the candidates the pass scores,
``ClippedPairs.nll``): a few transforms of the window's size per
candidate, about 6–7 ms per window and plane for 28 candidates on one core. Only blocks that hold clipped samples
pay it, and a frame scores at most ``ClassicalConfig.clipped_planes_per_frame`` pairs this way
(``choose_clipped_planes``): an over-exposed frame's every window may hold a clipped sample.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import fft as sfft

from .bayer import PLANE_CHANNELS
from .evidence import plane_autocovariance, plane_nll, taper_terms, tapered_periodogram

MIN_UNCLIPPED_TAPER_SHARE = 0.25
"""A window's plane keeps evidence when its taper, weighted down at and around clipped samples (``clipped_weights``),
keeps at least this share of its energy Σt² (``masked_window``); with less, most of what the window saw is censored
or next to a censored sample, and it gives none."""


def clipped_weights(clipped: np.ndarray, ramp_samples: float) -> np.ndarray:
    """(H, W) float32 weights of a plane's samples, given its ``clipped`` flags (H × W bool): 0 at each clipped
    sample, rising as sin² over ``ramp_samples`` of distance (Euclidean, in samples) from the nearest one, 1
    beyond (0: a hard hole). A window holding clipped samples is scored with its taper times these weights
    (``masked_window``).

    A ramp, not a hard hole, because clipping is not missing at random: the clipped samples are an image's
    brightest, and their unclipped neighbours are bright too, so a hard hole's rim is a sharp step in the tapered
    window that the model (holes independent of the image) does not hold, and the window reads sharper, so
    farther, than it is. ``ClassicalConfig.clipped_ramp_samples`` (8 samples, 16 px) was chosen on ``bmi bench
    clipped``'s scenes and the default decoder's reads of clipped `bmi eval` tiles (docs/benchmarks.md, "Clipped
    samples")."""
    if not clipped.any():
        return np.ones(clipped.shape, np.float32)
    if ramp_samples <= 0:
        return (~clipped).astype(np.float32)
    distance = cv2.distanceTransform((~clipped).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return (np.sin(np.float32(0.5 * np.pi) * np.minimum(distance / np.float32(ramp_samples), np.float32(1.0)))
            ** 2).astype(np.float32)


def masked_window(window: np.ndarray, taper: np.ndarray, full_taper: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """(power spectrum n × n//2+1, taper energy Σt'², t'²-weighted mean signal) of one n × n plane window scored
    under ``taper`` t' (``full_taper`` t times the window's ``clipped_weights``), its t'-weighted mean removed, as
    ``window_spectra`` does with t. A clipped sample is censored (its true signal lies somewhere above white) and
    fits no Gaussian model, but the others are the blurred image plus noise, exactly as in an unclipped window; so
    the model is the expected periodogram under t' (``evidence.tapered_periodogram``: a taper with holes has a broad
    transform, through which the mean's removal reaches every bin, so the taper-smoothed model's approximation
    does not hold) and the noise power Σt'² σ². None when t' keeps less than ``MIN_UNCLIPPED_TAPER_SHARE`` of t's
    energy."""
    t = np.asarray(taper, np.float64)
    energy = float((t * t).sum())
    if energy < MIN_UNCLIPPED_TAPER_SHARE * float((np.asarray(full_taper, np.float64) ** 2).sum()):
        return None
    x = window.astype(np.float64)
    mean = float((t * x).sum() / t.sum())
    spec = sfft.rfft2((x - mean) * t)
    return (spec.real ** 2 + spec.imag ** 2), energy, float((t * t * x).sum() / energy)


def choose_clipped_planes(clipped_padded: np.ndarray, weights_padded: np.ndarray, n_plane: int, stride_plane: int,
                          grid_shape: tuple[int, int], taper: np.ndarray, most: int) -> np.ndarray:
    """(planes, rows, cols) bool: the (plane, window) pairs of a frame's window grid that ``ClippedPairs``
    scores. ``clipped_padded`` / ``weights_padded``: (planes, H', W') clipped flags and their ``clipped_weights`` on
    the padded planes, window (r, c) reading [r·stride, r·stride + n) × [c·stride, c·stride + n) (``window_spectra``'s
    grid).

    A pair qualifies when its window holds clipped samples and its taper times the weights keeps at least
    ``MIN_UNCLIPPED_TAPER_SHARE`` of the taper's energy; of those, the ``most`` that keep the largest share
    (ties in plane, row, column order). The cap bounds the cost on an over-exposed frame (module doc) and is one
    choice for the whole frame, so it does not depend on how blocks are spread over threads.
    """
    rows, cols = grid_shape
    w = np.sqrt(np.asarray(np.diag(taper), np.float64))
    # the Hann taper is separable, t = w wᵀ, so Σ t² weight² over a window is two 1-D sums
    if not np.allclose(np.outer(w, w), taper, rtol=1e-5, atol=1e-9):
        raise ValueError("choose_clipped_planes needs a separable taper t = w wᵀ")
    w2 = (w * w).astype(np.float32)
    total = float(w2.sum()) ** 2

    def window_sums(x: np.ndarray) -> np.ndarray:  # Σ over each window of x(i, j) w2(i) w2(j)
        along_rows = np.einsum("rwn,n->rw", np.lib.stride_tricks.sliding_window_view(x, n_plane, axis=0)
                               [::stride_plane][:rows], w2)
        return np.einsum("rcn,n->rc", np.lib.stride_tricks.sliding_window_view(along_rows, n_plane, axis=1)
                         [:, ::stride_plane][:, :cols], w2)

    share = np.full((len(clipped_padded), rows, cols), -1.0)
    for p, (flags, weights) in enumerate(zip(clipped_padded, weights_padded)):
        touched = window_sums(flags.astype(np.float32)) > 0
        share[p] = np.where(touched, window_sums(weights * weights) / total, -1.0)
    order = np.flatnonzero((share >= MIN_UNCLIPPED_TAPER_SHARE).ravel())
    order = order[np.argsort(-share.ravel()[order], kind="stable")][:max(int(most), 0)]
    chosen = np.zeros(share.shape, bool)
    chosen.ravel()[order] = True
    return chosen


class ClippedPairs:
    """A block's (window, plane) pairs scored from their unclipped samples (module doc; ``choose_clipped_planes``
    picks them): each pair's window spectrum and noise under its own taper, then its NLL at any candidates
    (``nll``), as the block's coarse and fine passes ask for them.

    ``plane_windows`` / ``weight_windows``: per plane, the (windows, n, n) samples and clipped weights of the
    block's windows (``window_spectra``'s grid); ``chosen``: (planes, windows) the pairs to score; ``kernels_of(zone,
    which)``: (channels, len(which), K, K) kernels of candidates ``which`` at a zone; ``reads``: the block's zone
    reads (``ZoneKernels.field_reads``: zone, window indices, weights); ``slopes``: the prior slopes, whose NLLs
    ``nll`` keeps apart for the decoder to profile (``evidence.profile_exponent``); ``noise``: the frame's
    ``NoiseProfile``. ``scored``: (planes, windows) which pairs give evidence (a chosen pair whose weighted taper
    keeps too little gives none).
    """

    def __init__(self, plane_windows: list, weight_windows: list, chosen: np.ndarray, taper: np.ndarray, kernels_of,
                 reads: list, slopes: tuple, noise):
        self.n_windows = chosen.shape[1]
        self.n_plane = taper.shape[0]
        self.kernels_of, self.reads, self.slopes = kernels_of, reads, tuple(slopes)
        self.scored = np.zeros(chosen.shape, bool)
        self.pairs = []
        for p, w in zip(*np.nonzero(chosen)):
            masked_taper = taper * weight_windows[p][w]
            masked = masked_window(plane_windows[p][w], masked_taper, taper)
            if masked is None:  # on the share's edge, where the frame's float32 sums chose it
                continue
            power, energy, mean_signal = masked
            self.pairs.append((int(p), int(w), power[None].astype(np.float32), energy,
                               float(noise.variance(mean_signal)), taper_terms(masked_taper)))
            self.scored[p, w] = True
        self._grid_models: dict = {}

    def nll(self, which: np.ndarray) -> np.ndarray:
        """(slopes, windows, len(which)) NLL of candidates ``which`` at each prior slope, summed over each window's
        scored pairs (0 for a window with none). The first call's models place each pair's β grid for every later
        call, as the coarse pass's models place the fine pass's (``evidence.plane_nll``), so that the passes' NLLs form
        one curve."""
        total = np.zeros((len(self.slopes), self.n_windows, len(which)))
        autocovariances: dict = {}
        for p, w, power, energy, noise_var, terms in self.pairs:
            for zone, idx, weight in self.reads:
                hit = np.flatnonzero(idx == w)
                if not len(hit):
                    continue
                key = (zone, PLANE_CHANNELS[p])
                if key not in autocovariances:
                    k = self.kernels_of(zone, which)[PLANE_CHANNELS[p]]
                    autocovariances[key] = [plane_autocovariance(k, self.n_plane, a) for a in self.slopes]
                for a, r in enumerate(autocovariances[key]):
                    model = tapered_periodogram(r, terms)
                    grid = self._grid_models.setdefault((p, w, zone, a), model)
                    total[a, w] += weight[hit[0]] * plane_nll(power, model, noise_var, energy, grid_model=grid)[0]
        return total
