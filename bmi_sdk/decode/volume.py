"""The evidence volume as a network's input and the posterior it returns, in numpy (no torch).

The classical decoder scores every window of a frame against every depth candidate (``classical``): its
negative log-likelihood less the window's minimum, ΔNLL, over the candidates is a cost volume in the sense
of stereo matching. The evidence decoder (``runtime`` kind ``evidence``) hands that volume to a small
network that returns logits over the same candidates; its depth is the posterior mean of 1/d and its 1σ the
posterior's spread (``posterior``). Because the network adds a residual to −ΔNLL of the pooled curves, an
untrained network returns the pooled evidence's own posterior: what the camera's kernels say, for a
calibrated camera as for the design.

This module holds what both training and inference need around the network:

* ``volume_inputs``: a decode's volume (pooled and own curves, clipped), and the guide (window colour);
* ``grid_targets``: a scene's 1/d at each window's cell, the training target;
* ``posterior``: the read (the continuous posterior's mean about its mode) and spread of 1/d under the logits;
* ``guided_upsample``: window-grid 1/d and its variance to every pixel, each pixel taking the windows
  whose cell colour matches its own (joint bilateral upsampling, Kopf et al., SIGGRAPH 2007), with the
  mixture's variance, so a pixel between two surfaces reports the gap between them.
"""

from __future__ import annotations

import numpy as np

CLIP_NATS = 60.0
"""ΔNLL above this carries no more information about a window's depth (its posterior weight is e⁻⁶⁰):
the volume is clipped there, so a very textured window does not dominate the network's input scale."""

VOLUME_SCALE_NATS = 10.0
"""The network reads ΔNLL / this (order-one inputs); its anchor, −ΔNLL of the pooled curves, stays in nats."""

MIN_CELL_VALID = 0.25
"""Least fraction of a window cell's pixels with a finite scene depth for the cell to carry a training target."""


def volume_inputs(grid_pooled: np.ndarray, grid_curves: np.ndarray, grid_colour: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(volume, guide, valid) of one decode's window grid (R × C windows, D candidates).

    ``volume``: (2, D, R, C) float32: the pooled and the own ΔNLL curves in nats, each less its minimum (a
    pooled curve's minimum is its neighbours' cost there) and clipped at ``CLIP_NATS`` (0 in windows without a
    decode); ``guide``: (4, R, C) float32: the windows' log mean colour less its mean
    over the grid's valid windows (the picture's colour edges, independent of exposure), and 1 where a window
    has a decode, 0 elsewhere; ``valid``: (R, C) windows with a decode.
    """
    if grid_pooled.shape != grid_curves.shape or grid_pooled.ndim != 3 or grid_colour.shape[:2] != grid_pooled.shape[:2]:
        raise ValueError(f"a volume needs pooled and own curves of one R × C × D shape and R × C × 3 colours, got "
                         f"{grid_pooled.shape}, {grid_curves.shape} and {grid_colour.shape}")
    valid = np.isfinite(grid_pooled).all(axis=-1) & np.isfinite(grid_curves).all(axis=-1)
    vol = np.stack([grid_pooled, grid_curves]).astype(np.float32)             # (2, R, C, D)
    vol = np.nan_to_num(vol - np.nanmin(np.where(valid[None, ..., None], vol, np.inf), axis=-1, keepdims=True))
    vol = np.where(valid[None, ..., None], np.clip(vol, 0.0, CLIP_NATS), 0.0)
    colour = np.asarray(grid_colour, np.float32)
    mean = colour[valid].mean(axis=0) if valid.any() else np.zeros(3, np.float32)
    guide = np.concatenate([np.where(valid[..., None], colour - mean, 0.0), valid[..., None]], axis=-1)
    return (np.ascontiguousarray(vol.transpose(0, 3, 1, 2)),
            np.ascontiguousarray(guide.transpose(2, 0, 1).astype(np.float32)), valid)


def cell_bounds(k: int, stride_px: int, size_px: int) -> tuple[int, int]:
    """Pixel range [lo, hi) of window k's cell along one axis: the stride around its centre k·stride − ½, clipped
    to the frame (the grid reaches a stride past the last pixel, so the last cell may be empty: lo = hi)."""
    half = stride_px // 2
    return min(size_px, max(0, k * stride_px - half)), min(size_px, k * stride_px + half)


def grid_targets(range_m: np.ndarray, stride_px: int, grid_shape: tuple[int, int]) -> np.ndarray:
    """(R, C) float32 median 1/d (m⁻¹) of the scene over each window's cell (``cell_bounds``); NaN where fewer
    than ``MIN_CELL_VALID`` of the cell's pixels have a finite positive depth."""
    height, width = range_m.shape
    inv = np.where(np.isfinite(range_m) & (range_m > 0), 1.0 / np.where(range_m > 0, range_m, 1.0), np.nan)
    out = np.full(grid_shape, np.nan, np.float32)
    for r in range(grid_shape[0]):
        r0, r1 = cell_bounds(r, stride_px, height)
        for c in range(grid_shape[1]):
            c0, c1 = cell_bounds(c, stride_px, width)
            cell = inv[r0:r1, c0:c1]
            ok = np.isfinite(cell)
            if cell.size and ok.mean() >= MIN_CELL_VALID:
                out[r, c] = np.median(cell[ok])
    return out


MODE_REACH = 2
"""Candidates either side of the posterior's mode that its read averages over (``posterior``)."""
SERIES_BELOW = 0.1
"""|δ| below which ``interval_moments`` uses its power series (float32 keeps ~1e-5 of the intervals' tail terms)."""


def interval_moments(z_lo, z_hi, xp=np):
    """(mass, moment) of one interval of the continuous candidate index t ∈ [k, k + 1] whose logit runs linearly
    from ``z_lo`` to ``z_hi`` (both ≤ 0: logits less their maximum): ∫₀¹ e^(z_lo + δ u) du and ∫₀¹ u e^(z_lo + δ u) du,
    δ = z_hi − z_lo, in closed form, with their power series where |δ| < ``SERIES_BELOW`` (the closed forms cancel
    there). ``xp``: numpy or torch (the same arithmetic for the network's training and export)."""
    delta = z_hi - z_lo
    e_lo, e_hi = xp.exp(z_lo), xp.exp(z_hi)
    small = xp.abs(delta) < SERIES_BELOW
    safe = xp.where(small, xp.ones_like(delta), delta)
    mass = xp.where(small, e_lo * (1 + delta / 2 + delta ** 2 / 6 + delta ** 3 / 24 + delta ** 4 / 120),
                    (e_hi - e_lo) / safe)
    moment = xp.where(small, e_lo * (0.5 + delta / 3 + delta ** 2 / 8 + delta ** 3 / 30 + delta ** 4 / 144),
                      (e_hi * (delta - 1) + e_lo) / (safe * safe))
    return mass, moment


def posterior(logits: np.ndarray, inv_depth_per_m: np.ndarray, axis: int = 0,
              reach: int = MODE_REACH) -> tuple[np.ndarray, np.ndarray]:
    """(read, spread) of 1/d under the posterior the candidates' ``logits`` (along ``axis``; 1/d
    ``inv_depth_per_m``) describe.

    The read is continuous: the candidate index t is a continuous variable whose logit runs linearly between
    neighbouring candidates (a uniform prior on t, as the softmax over candidates has on the index), and 1/d runs
    linearly with it; the read is the mean 1/d of that posterior over the ``reach`` candidates either side of the
    most probable one (a second, far mode would pull the whole mean between two surfaces, where neither is). Each
    interval's share is in closed form (``interval_moments``). A read snapped to the candidates would be off by up
    to half their spacing (5–10 % of the depth beyond 3 m) on a surface whose pooled evidence is sharp.
    The spread is the discrete posterior's std over every candidate: wide for flat or two-peaked evidence."""
    if isinstance(reach, bool) or not isinstance(reach, int) or reach < 1:
        raise ValueError(f"posterior reach must be a whole number >= 1, got {reach!r}")
    z = np.moveaxis(np.asarray(logits, np.float64), axis, 0)
    z = z - z.max(axis=0, keepdims=True)
    x = np.asarray(inv_depth_per_m, np.float64).reshape((-1,) + (1,) * (z.ndim - 1))
    p = np.exp(z)
    p /= p.sum(axis=0, keepdims=True)
    mean = (p * x).sum(axis=0)
    var = (p * (x - mean) ** 2).sum(axis=0)
    if z.shape[0] == 1:
        return np.broadcast_to(x[0], mean.shape).copy(), np.sqrt(var)
    mass, moment = interval_moments(z[:-1], z[1:])
    k = np.arange(z.shape[0] - 1).reshape((-1,) + (1,) * (z.ndim - 1))
    mode = np.argmax(z, axis=0)
    inside = (k >= mode - reach) & (k + 1 <= mode + reach)
    mass = np.where(inside, mass, 0.0)
    first = np.where(inside, x[:-1] * mass + (x[1:] - x[:-1]) * moment, 0.0)
    return first.sum(axis=0) / mass.sum(axis=0), np.sqrt(var)


def pixel_log_colour(rgb: np.ndarray, floor: float = 1e-3) -> np.ndarray:
    """H × W × 3 float32 log colour of a linear RGB image, floored (the guide of ``guided_upsample``)."""
    out = np.maximum(np.asarray(rgb, np.float32), np.float32(floor))
    return np.log(out, out=out)


def cell_colour(image: np.ndarray, stride_px: int, grid_shape: tuple[int, int]) -> np.ndarray:
    """(R, C, 3) mean colour of each window's cell (``cell_bounds``) of an H × W × 3 image (log colour for the
    guided upsampling; linear colour for ``support.cell_colours``).

    Cell k spans pixels [k·stride − stride/2, k·stride + stride/2) clipped to the frame: in the frame shifted
    by stride/2 down and right and zero-padded to R·stride × C·stride, it is the stride × stride block k. The
    blocks' means are one area resampling (``cv2.resize``, ``INTER_AREA``, exact for a whole-number factor),
    made sums and divided by each cell's clipped area (an empty cell reads 0). float32."""
    import cv2

    rows, cols = grid_shape
    s, half = int(stride_px), int(stride_px) // 2
    height, width = image.shape[:2]
    crop = np.ascontiguousarray(image[:max(0, rows * s - half), :max(0, cols * s - half)], np.float32)
    if crop.size == 0:
        return np.zeros((rows, cols, 3), np.float32)
    shifted = cv2.copyMakeBorder(crop, half, rows * s - half - crop.shape[0], half, cols * s - half - crop.shape[1],
                                 cv2.BORDER_CONSTANT, value=0)
    sums = cv2.resize(shifted, (cols, rows), interpolation=cv2.INTER_AREA) * np.float32(s * s)
    area = np.maximum(cell_area_px(s, grid_shape, height, width), 1)[..., None]
    return sums / area.astype(np.float32)


def cell_area_px(stride_px: int, grid_shape: tuple[int, int], height: int, width: int) -> np.ndarray:
    """(R, C) pixel count of each window's cell (``cell_bounds``) in an H × W frame: 0 for the empty cells of a
    grid that reaches a stride past the frame."""
    def extent(count: int, size: int) -> np.ndarray:
        return np.array([hi - lo for lo, hi in (cell_bounds(k, stride_px, size) for k in range(count))])

    return extent(grid_shape[0], height)[:, None] * extent(grid_shape[1], width)[None, :]


def guided_upsample(inv_grid: np.ndarray, var_grid: np.ndarray, log_rgb: np.ndarray, stride_px: int,
                    colour_sigma: float, band_cells: int = 32, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(1/d, variance of 1/d) at every pixel of an H × W frame from its window grid (R × C, NaN where no read).

    Each pixel reads the 2 × 2 windows around it, weighted by the bilinear weight times
    exp(−|g_p − g_w|² / 2 ``colour_sigma``²), g_p the pixel's log colour (``log_rgb``, H × W × 3) and g_w
    the mean log colour of window w's cell: across a colour edge the pixel follows the windows of its own
    side. Its variance is the mixture's: Σ w (var_w + (1/d_w − 1/d_p)²), so a pixel whose windows disagree
    reports that. Where every colour weight vanishes (a colour none of its windows has) the bilinear weights
    stand. NaN where none of the 2 × 2 windows has a read.

    Window k's centre lies at pixel k·stride − ½, so every pixel of the stride × stride block k reads windows
    k and k + 1 on each axis with the same bilinear weights: the frame is read as blocks (broadcasting, no
    gathers), ``band_cells`` block rows at a time, on ``threads`` threads (numpy releases the GIL). float32.
    """
    if not colour_sigma > 0:
        raise ValueError(f"guided upsampling needs colour_sigma > 0, got {colour_sigma}")
    height, width = log_rgb.shape[:2]
    rows, cols = inv_grid.shape
    s = int(stride_px)
    block_rows, block_cols = -(-height // s), -(-width // s)
    if rows < block_rows + 1 or cols < block_cols + 1:
        raise ValueError(f"a {rows}×{cols} window grid at stride {s} px does not cover a {height}×{width} frame")
    cells = cell_colour(log_rgb, s, (rows, cols))
    ok_grid = np.isfinite(inv_grid) & np.isfinite(var_grid)
    inv_g = np.where(ok_grid, inv_grid, 0.0).astype(np.float32)
    var_g = np.where(ok_grid, var_grid, 0.0).astype(np.float32)
    out_inv = np.full((height, width), np.nan, np.float32)
    out_var = np.full((height, width), np.nan, np.float32)
    # the bilinear weight of window k + 1 for offset j inside a block: (j + ½) / stride
    far = ((np.arange(s) + 0.5) / s).astype(np.float32)
    near = np.float32(1.0) - far
    inv_two_c2 = np.float32(0.5 / colour_sigma ** 2)

    def band(b0: int) -> None:
        b1 = min(block_rows, b0 + band_cells)
        top, bottom = b0 * s, min(height, b1 * s)
        g = np.zeros(((b1 - b0) * s, block_cols * s, 3), np.float32)
        g[:bottom - top, :width] = log_rgb[top:bottom]
        g = g.reshape(b1 - b0, s, block_cols, s, 3)
        weights, values, variances = [], [], []
        for dr, wr in ((0, near), (1, far)):
            for dc, wc in ((0, near), (1, far)):
                sl = (slice(b0 + dr, b1 + dr), slice(dc, block_cols + dc))
                ok = ok_grid[sl][:, None, :, None]
                spatial = np.where(ok, wr[None, :, None, None] * wc[None, None, None, :], np.float32(0.0))
                diff = g - cells[sl][:, None, :, None, :]
                colour = np.exp(-np.einsum("...c,...c->...", diff, diff) * inv_two_c2)
                weights.append((spatial, spatial * colour))
                values.append(inv_g[sl][:, None, :, None])
                variances.append(var_g[sl][:, None, :, None])
        spatial_sum = sum(w[0] for w in weights)
        guided_sum = sum(w[1] for w in weights)
        use_guided = guided_sum > np.float32(1e-6) * np.maximum(spatial_sum, np.float32(1e-30))
        any_read = spatial_sum > 0
        norm = np.where(use_guided, guided_sum, spatial_sum)
        safe = np.where(any_read, norm, np.float32(1.0))
        ws = [np.where(use_guided, w[1], w[0]) / safe for w in weights]
        mean = sum(w * v for w, v in zip(ws, values))
        var = sum(w * (v_s + (v - mean) ** 2) for w, v, v_s in zip(ws, values, variances))
        shape = ((b1 - b0) * s, block_cols * s)
        out_inv[top:bottom] = np.where(any_read, mean, np.nan).reshape(shape)[:bottom - top, :width]
        out_var[top:bottom] = np.where(any_read, var, np.nan).reshape(shape)[:bottom - top, :width]

    starts = range(0, block_rows, band_cells)
    if threads > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(band, starts))
    else:
        for b0 in starts:
            band(b0)
    return out_inv, out_var
