"""The classical decoder's output as per-pixel channels for the learned refinement (``--decoder learned``).

The refinement network (``bmi_sdk.nn``, exported to ONNX) reads the usual network input (demosaiced
RGB and the field channels, ``model_io``) and, appended to it, what the physics found. Channel order
(``EXTRA_CHANNELS`` of them, all float32, 0 where a pixel is outside the image circle):

  0        log(d / d_ref), d the classical depth (d_ref = √7 m, the network's reference range), clipped to ±3
  1        log(σ_d / d), the classical decoder's reported relative 1σ, clipped to [−6, 3]
  2 … 2+E  the coarse evidence curve: log(1 + ΔNLL_k) for the E coarse candidates, ΔNLL_k the window's
           negative log-likelihood at candidate k minus its minimum (0 at the best candidate; a flat
           curve means no texture, a sharp one a confident depth)
  last 3   the classical all-in-focus RGB (linear, clipped to [0, 2])

Window-grid quantities are interpolated bilinearly to pixels (``classical.upsample_grid``). The evidence
curve needs the coarse candidates to be the same at training and at run time, so a learned model's
manifest carries the ``ClassicalConfig`` it was trained with and the runtime decodes with it.
"""

from __future__ import annotations

import math

import numpy as np

from .classical import ClassicalDecoder, DecodeResult, coarse_indices, upsample_grid

FEATURE_DEPTH_REF_M = math.sqrt(0.7 * 10.0)
"""Reference range of the log-depth channel: the network's depth reference (nn.model.DEPTH_REF_M)."""
AIF_CLIP = 2.0


def extra_channels(decoder: ClassicalDecoder) -> int:
    """Channels ``refinement_features`` appends to the network input for ``decoder`` (its distinct
    candidates, after snapping to the kernel grid, set the evidence length)."""
    return 2 + len(coarse_indices(len(decoder.candidates), decoder.config.coarse_step)) + 3


def refinement_features(result: DecodeResult, stride_px: int) -> np.ndarray:
    """C × H × W float32 channels (module doc) of one decoded window."""
    height, width = result.depth_m.shape
    valid = result.valid
    n_ev = result.grid_evidence.shape[-1]
    out = np.zeros((2 + n_ev + 3, height, width), np.float32)
    depth = np.where(valid, result.depth_m, FEATURE_DEPTH_REF_M)
    rel_sigma = np.where(valid, result.depth_sigma_m / depth, 1.0)
    out[0] = np.clip(np.log(depth / FEATURE_DEPTH_REF_M), -3.0, 3.0)
    out[1] = np.clip(np.log(np.maximum(rel_sigma, 1e-6)), -6.0, 3.0)
    for k in range(n_ev):
        grid = np.log1p(np.maximum(result.grid_evidence[..., k], 0.0))
        out[2 + k] = upsample_grid(grid, stride_px, height, width)
    out[2 + n_ev:] = np.clip(result.aif, 0.0, AIF_CLIP).transpose(2, 0, 1)
    out[:, ~valid] = 0.0
    return np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
