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

Window-grid quantities are interpolated bilinearly to pixels (``classical.upsample_grid``). A full frame's
channels are made tile by tile (``FeatureTiles``): held whole they are 13 × 27 M float32, 1.4 GB. The evidence
curve needs the coarse candidates to be the same at training and at run time, so a learned model's
manifest carries the ``ClassicalConfig`` it was trained with and the runtime decodes with it.
"""

from __future__ import annotations

import math

import numpy as np

from .classical import ClassicalDecoder, DecodeResult, coarse_indices, fill_grid, upsample_grid

FEATURE_DEPTH_REF_M = math.sqrt(0.7 * 10.0)
"""Reference range of the log-depth channel: the network's depth reference (nn.model.DEPTH_REF_M)."""
AIF_CLIP = 2.0


def extra_channels(decoder: ClassicalDecoder) -> int:
    """Channels ``refinement_features`` appends to the network input for ``decoder`` (its distinct
    candidates, after snapping to the kernel grid, set the evidence length)."""
    return 2 + len(coarse_indices(len(decoder.candidates), decoder.config.coarse_step)) + 3


class FeatureTiles:
    """The channels (module doc) of one decoded window, made for any block of its pixels on demand.

    ``gather(rows, cols)`` gives the C × len(rows) × len(cols) channels of those pixel rows and columns (index
    arrays, as a tile with mirror-reflected edges asks for them), the same values the whole window's channels
    hold there; only the evidence grids (small) are prepared up front.
    """

    def __init__(self, result: DecodeResult, stride_px: int):
        self.result = result
        self.stride_px = stride_px
        self.shape = result.depth_m.shape
        self._evidence = [fill_grid(np.log1p(np.maximum(result.grid_evidence[..., k], 0.0)))
                          for k in range(result.grid_evidence.shape[-1])]
        self.count = 2 + len(self._evidence) + 3

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """C × len(rows) × len(cols) float32 channels of the given frame rows and columns."""
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        box = slice(r0, r1), slice(c0, c1)
        res = self.result
        valid = res.valid[box]
        out = np.zeros((self.count, r1 - r0, c1 - c0), np.float32)
        depth = np.where(valid, res.depth_m[box], FEATURE_DEPTH_REF_M)
        rel_sigma = np.where(valid, res.depth_sigma_m[box] / depth, 1.0)
        out[0] = np.clip(np.log(depth / FEATURE_DEPTH_REF_M), -3.0, 3.0)
        out[1] = np.clip(np.log(np.maximum(rel_sigma, 1e-6)), -6.0, 3.0)
        for k, grid in enumerate(self._evidence):
            out[2 + k] = upsample_grid(grid, self.stride_px, r1 - r0, c1 - c0, r0, c0)
        out[2 + len(self._evidence):] = np.clip(res.aif[box], 0.0, AIF_CLIP).transpose(2, 0, 1)
        out[:, ~valid] = 0.0
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        if np.array_equal(rows, np.arange(r0, r1)) and np.array_equal(cols, np.arange(c0, c1)):
            return out  # a tile inside the frame: its pixels in order, no reflected edge to copy them into
        return out[np.ix_(np.arange(self.count), rows - r0, cols - c0)]


def refinement_features(result: DecodeResult, stride_px: int) -> np.ndarray:
    """C × H × W float32 channels (module doc) of one whole decoded window (a tile's; a frame's go per tile)."""
    height, width = result.depth_m.shape
    return FeatureTiles(result, stride_px).gather(np.arange(height), np.arange(width))
