"""The paper's metrics (§4.2) on valid pixels: depth δ < 1.25ⁿ, RMSE, AbsRel; image PSNR, SSIM.

The one home of the metrics: ``bmi eval`` (``nn.evaluate``) and ``bmi demo``'s
error against the scene's ground truth both use them. numpy and scipy only, and
outside ``bmi_sdk.nn``, so a caller does not load the training package.

Conventions (one image at a time; a benchmark averages the per-image values,
as the NYU-style protocols do):

* depth metrics use the pixels where ``valid`` holds and both ranges are
  finite and > 0; δₙ is the fraction with max(d̂/d, d/d̂) < 1.25ⁿ,
  RMSE = √mean((d̂ − d)²) in metres, AbsRel = mean(|d̂ − d| / d);
* PSNR = 10 log₁₀(1 / MSE) over the valid pixels and the three channels, for
  linear RGB clipped to [0, 1] (peak 1);
* SSIM is Wang et al. (2004): Gaussian window σ = 1.5 px truncated at 11×11,
  K₁ = 0.01, K₂ = 0.03, data range 1, per channel; the SSIM map is averaged
  over the channels and over the valid pixels whose whole 11×11 window is
  valid (so nothing outside the image circle leaks into the statistic).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

SSIM_SIGMA_PX = 1.5
SSIM_RADIUS_PX = 5
SSIM_K1, SSIM_K2 = 0.01, 0.03
DEPTH_METRICS = ("delta1", "delta2", "delta3", "rmse_m", "absrel")
IMAGE_METRICS = ("psnr_db", "ssim")


def depth_metrics(pred_m: np.ndarray, true_m: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """δ1, δ2, δ3, RMSE (m), AbsRel over valid pixels; NaN for all when none is valid."""
    pred = np.asarray(pred_m, dtype=np.float64)
    true = np.asarray(true_m, dtype=np.float64)
    ok = np.isfinite(pred) & np.isfinite(true) & (pred > 0) & (true > 0)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if not ok.any():
        return dict.fromkeys(DEPTH_METRICS, float("nan"))
    p, t = pred[ok], true[ok]
    ratio = np.maximum(p / t, t / p)
    return {"delta1": float(np.mean(ratio < 1.25)), "delta2": float(np.mean(ratio < 1.25 ** 2)),
            "delta3": float(np.mean(ratio < 1.25 ** 3)), "rmse_m": float(np.sqrt(np.mean((p - t) ** 2))),
            "absrel": float(np.mean(np.abs(p - t) / t))}


def psnr_db(pred: np.ndarray, true: np.ndarray, valid: np.ndarray | None = None) -> float:
    """PSNR (dB, peak 1) of H×W×C linear images over valid pixels, after clipping both to [0, 1]."""
    p = np.clip(np.asarray(pred, dtype=np.float64), 0, 1)
    t = np.clip(np.asarray(true, dtype=np.float64), 0, 1)
    err = (p - t) ** 2
    if valid is not None:
        err = err[np.asarray(valid, dtype=bool)]
    if err.size == 0:
        return float("nan")
    mse = float(err.mean())
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def _blur(x: np.ndarray) -> np.ndarray:
    return ndimage.gaussian_filter(x, SSIM_SIGMA_PX, mode="reflect", truncate=SSIM_RADIUS_PX / SSIM_SIGMA_PX)


def ssim(pred: np.ndarray, true: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Mean SSIM of H×W×C images in [0, 1] (clipped) over valid pixels (see module doc)."""
    p = np.clip(np.asarray(pred, dtype=np.float64), 0, 1)
    t = np.clip(np.asarray(true, dtype=np.float64), 0, 1)
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    maps = []
    for c in range(p.shape[2]):
        x, y = p[..., c], t[..., c]
        mx, my = _blur(x), _blur(y)
        vx = _blur(x * x) - mx * mx
        vy = _blur(y * y) - my * my
        cxy = _blur(x * y) - mx * my
        maps.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    ssim_map = np.mean(maps, axis=0)
    region = np.ones(p.shape[:2], bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid is not None:
        size = 2 * SSIM_RADIUS_PX + 1
        region = ndimage.minimum_filter(region.astype(np.uint8), size=size, mode="constant", cval=0).astype(bool)
    return float(ssim_map[region].mean()) if region.any() else float("nan")


def image_metrics(pred: np.ndarray, true: np.ndarray, valid: np.ndarray | None = None) -> dict:
    return {"psnr_db": psnr_db(pred, true, valid), "ssim": ssim(pred, true, valid)}


def mean_metrics(rows: list[dict]) -> dict:
    """Per-key mean over images, ignoring NaN (an image without valid pixels for a metric)."""
    keys = [k for k in DEPTH_METRICS + IMAGE_METRICS if any(k in r for r in rows)]
    return {k: float(np.nanmean([r[k] for r in rows if k in r])) for k in keys}
