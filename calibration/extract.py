"""Spot extraction: dark subtraction, photon-transfer noise, detection, sub-pixel centroids, PSF patches.

Per source, from its ROI frames:

1. exposure: the longest one with no pixel at the white level in any repeat
   (a saturated spot's core is clipped and would bias every shape term);
   none left → rejected ``saturated``;
2. signal S = mean(lamp-on repeats) − mean(dark frames) at that exposure (DN);
3. noise by photon transfer, pooled over all spots: the read variance r is
   the mean per-pixel variance of the dark frames, the shot-noise slope k
   (DN per DN) the least-squares slope of repeat variance − r against S.
   The variance of S at a pixel of mean signal μ is
   (k μ + r)/n_repeats + r/n_dark; the fit re-evaluates it with its model's μ;
4. detection: the brightest 3 × 3 box of S among the lamp's CFA channels;
   rejected ``no spot`` below a peak SNR of 10;
5. sub-pixel centroid: first moment of S − (median of the ROI border) within
   the kernel radius;
6. PSF patch: K × K pixels centred on the centroid's nearest pixel; rejected
   ``frame edge`` when the patch is cut by the ROI at the sensor's border
   (a spot in the frame corner) or ``roi edge`` inside it, and
   ``overlapping`` when another lamp lit in the same frames lands within one
   kernel width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.sensor import cfa_channel_map, relative_illumination

from .targets import CalibrationError, Captures, PointSource, design_landing_px

MIN_PEAK_SNR = 10.0
SPOT_BOX_PX = 7  # side of the box summed to tell a dim spot from none (a spot's core; docs/reliability.md)


@dataclass
class Spot:
    index: int  # source index in the target
    source: PointSource
    row0: int  # top-left pixel of the patch on the full sensor
    col0: int
    data_dn: np.ndarray  # (K, K) dark-subtracted mean signal
    sigma_dn: np.ndarray  # (K, K) its noise (photon transfer, from the data)
    channel: np.ndarray  # (K, K) CFA channel index
    used: np.ndarray  # (K, K) bool: pixels of the lamp's channels
    illumination: np.ndarray  # (K, K) relative illumination the readout applies
    exposure_us: int
    centroid_px: tuple  # (row, col) on the full sensor
    design_px: tuple  # (row, col) where the design lens puts the chief ray
    peak_snr: float
    n_repeats: int
    n_dark: int


@dataclass
class Extraction:
    spots: list  # Spot, usable
    rejected: list  # (source index, reason)
    shot_slope_dn_per_dn: float  # k: variance per DN of signal
    read_variance_dn2: float  # r

    def variance(self, mean_dn, n_repeats, n_dark):
        """Variance of a dark-subtracted mean signal of expectation ``mean_dn`` (see module doc)."""
        return (self.shot_slope_dn_per_dn * np.maximum(mean_dn, 0.0) + self.read_variance_dn2) / n_repeats + \
            self.read_variance_dn2 / n_dark


def _box3(a):
    p = np.pad(a, 1)
    return sum(p[i:i + a.shape[0], j:j + a.shape[1]] for i in range(3) for j in range(3))


def _why_no_signal(stats: dict, read_var: float) -> str:
    """Why the lamp-on frames show (almost) no pixel clearly above the dark ones.

    Judged from the best ``SPOT_BOX_PX``-square sum of the signal in each ROI,
    in units of its read noise: a spot too dim for bright pixels still stands
    out there; a spot that missed its ROI leaves noise (a few σ at most), and
    lamp-on frames darker than the dark frames mean swapped kinds.
    """
    from scipy.ndimage import uniform_filter

    best, worst = -np.inf, np.inf
    for _, _, signal, n_rep, n_dark in stats.values():
        sigma_box = np.sqrt(SPOT_BOX_PX**2 * read_var * (1.0 / n_rep + 1.0 / n_dark))
        box = uniform_filter(signal, SPOT_BOX_PX, mode="constant") * SPOT_BOX_PX**2 / sigma_box
        best, worst = max(best, float(box.max())), min(worst, float(box.min()))
    if worst < -MIN_PEAK_SNR and best < MIN_PEAK_SNR:
        return ("the lamp-on frames are darker than the dark frames (down to "
                f"{worst:.0f} σ): light and dark frames are swapped; check the kinds in captures.json")
    if best < MIN_PEAK_SNR:
        return (f"no light from any source reached its ROI (at most {best:.1f} σ): the spots landed outside the "
                "ROIs planned around the design positions, e.g. a lens decentered or tilted far beyond tolerance "
                "(check the mounting, or raise roi_margin_px), or the lamps were off")
    return ("too few bright pixels to measure the noise (photon transfer), though light reached the ROIs "
            f"(up to {best:.0f} σ): raise the exposure")


def extract_spots(captures: Captures, geometry=BMI_SENSOR) -> Extraction:
    """Usable spots and rejections with reasons (see module doc)."""
    target, plan = captures.target, captures.plan
    k = plan.kernel_px
    h = k // 2
    design = design_landing_px(target, geometry)
    chosen, rejected = [], []
    for i, frames in enumerate(captures.frames):
        if not frames:
            rejected.append((i, "no frames captured"))
            continue
        pick = None
        for exposure in sorted({e for _, e, _ in frames}, reverse=True):
            lights = [f for kind, e, f in frames if kind == "light" and e == exposure]
            darks = [f for kind, e, f in frames if kind == "dark" and e == exposure]
            if len(lights) < 2 or len(darks) < 2:
                continue
            if any((f.data >= f.white_level_dn).any() for f in lights):
                continue
            pick = (exposure, lights, darks)
            break
        if pick is None:
            rejected.append((i, "saturated at every exposure (pixels at the white level): dim the lamp or add a "
                                "shorter exposure to the plan"))
            continue
        chosen.append((i, *pick))
    # Photon transfer, pooled over the spots.
    read_vars, xs, ys = [], [], []
    stats = {}
    for i, exposure, lights, darks in chosen:
        light = np.stack([f.data for f in lights]).astype(np.float64)
        dark = np.stack([f.data for f in darks]).astype(np.float64)
        signal = light.mean(0) - dark.mean(0)
        rv = float(dark.var(0, ddof=1).mean())
        read_vars.append(rv)
        stats[i] = (exposure, lights, signal, len(lights), len(darks))
        bright = signal > 20.0
        xs.append(signal[bright])
        ys.append(light.var(0, ddof=1)[bright])
    if not chosen:
        return Extraction([], rejected, float("nan"), float("nan"))
    read_var = float(np.mean(read_vars))
    x, y = np.concatenate(xs), np.concatenate(ys) - read_var
    if len(x) < 10:
        raise CalibrationError(_why_no_signal(stats, read_var))
    slope = float(np.sum(x * y) / np.sum(x * x))
    spots = []
    simultaneous = not plan.one_lamp_at_a_time
    for i, exposure, lights, darks in chosen:
        _, _, signal, n_rep, n_dark = stats[i]
        roi = lights[0].roi
        chan = cfa_channel_map(roi.height_px, roi.width_px, roi.y_px, roi.x_px)
        used = np.isin(chan, target.channels)
        noise = np.sqrt(Extraction([], [], slope, read_var).variance(signal, n_rep, n_dark))
        score = np.where(used, _box3(np.where(used, signal, 0.0) / noise), -np.inf)
        pr, pc = np.unravel_index(np.argmax(score), score.shape)
        snr = float(signal[pr, pc] / noise[pr, pc])
        if snr < MIN_PEAK_SNR:
            rejected.append((i, f"no spot above the noise (peak SNR {snr:.1f} < {MIN_PEAK_SNR:g})"))
            continue
        border = np.concatenate([signal[0], signal[-1], signal[:, 0], signal[:, -1]])
        border_used = np.concatenate([used[0], used[-1], used[:, 0], used[:, -1]])
        bg = float(np.median(border[border_used]))
        rr, cc = np.mgrid[0:roi.height_px, 0:roi.width_px]
        near = used & (np.abs(rr - pr) <= h) & (np.abs(cc - pc) <= h)
        w = np.where(near, np.maximum(signal - bg, 0.0), 0.0)
        cr, ccol = float((w * rr).sum() / w.sum()), float((w * cc).sum() / w.sum())
        centroid = (roi.y_px + cr, roi.x_px + ccol)
        r0, c0 = int(round(cr)) - h, int(round(ccol)) - h
        if r0 < 0 or c0 < 0 or r0 + k > roi.height_px or c0 + k > roi.width_px:
            at_edge = (roi.x_px == 0 or roi.y_px == 0 or roi.x_px + roi.width_px >= geometry.width_px
                       or roi.y_px + roi.height_px >= geometry.height_px)
            rejected.append((i, "frame edge: the PSF patch is cut by the sensor boundary (a spot in the frame "
                                "corner); move the source inwards" if at_edge else
                                "roi edge: the spot landed too far from its design position for the ROI; "
                                "raise roi_margin_px"))
            continue
        if simultaneous:
            d = np.max(np.abs(design - np.array(centroid)), axis=1)
            d[i] = np.inf
            if d.min() < k:
                j = int(np.argmin(d))
                rejected.append((i, f"overlapping: source {j} lands {d[j]:.0f} px away (< {k} px kernel): "
                                    "light them in separate frames"))
                continue
        sl = (slice(r0, r0 + k), slice(c0, c0 + k))
        spots.append(Spot(
            index=i, source=target.sources[i], row0=roi.y_px + r0, col0=roi.x_px + c0, data_dn=signal[sl],
            sigma_dn=noise[sl], channel=chan[sl], used=used[sl],
            illumination=relative_illumination(geometry, roi.y_px + r0, roi.x_px + c0, k, k).astype(np.float64),
            exposure_us=exposure, centroid_px=centroid, design_px=tuple(design[i]), peak_snr=snr,
            n_repeats=n_rep, n_dark=n_dark))
    return Extraction(spots, sorted(rejected), slope, read_var)
