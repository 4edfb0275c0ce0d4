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

CLIP_NATS = 400.0
"""The volume is clipped at this ΔNLL, so a very textured window does not dominate the network's input scale.
It must leave the posterior's shape about its mode alone: the shipped network's logits are −0.058 × the
pooled ΔNLL, so 400 nats weigh e⁻²³ against the mode; a clip within a few nats of the logits' scale flattens
the neighbours of a sharp curve's minimum, and a large surface then reads the nearest candidate."""

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
INTERVAL_POINTS = 8
"""Points per interval between neighbouring candidates at which ``posterior`` evaluates its continuous posterior
(the midpoint rule: a read resolves about 1/16 of the candidates' spacing, up to ~2 % of the depth at 10 m)."""


def logit_slopes(z, x, xp=np):
    """(D, ...) slopes d(logit)/d(1/d) of logits ``z`` (D, ...) at the candidates' 1/d ``x`` (D, 1, ...): the
    three-point differences of uneven spacing inside (exact for a parabola in 1/d), one-sided at the ends.
    ``xp``: numpy or torch."""
    h_lo, h_hi = x[1:-1] - x[:-2], x[2:] - x[1:-1]
    inner = (h_lo ** 2 * (z[2:] - z[1:-1]) + h_hi ** 2 * (z[1:-1] - z[:-2])) / (h_lo * h_hi * (h_lo + h_hi))
    return xp.concatenate([(z[1:2] - z[:1]) / (x[1:2] - x[:1]), inner, (z[-1:] - z[-2:-1]) / (x[-1:] - x[-2:-1])], 0)


def posterior(logits: np.ndarray, inv_depth_per_m: np.ndarray, axis: int = 0,
              reach: int = MODE_REACH, points: int = INTERVAL_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """(read, spread) of 1/d under the posterior the candidates' ``logits`` (along ``axis``; 1/d
    ``inv_depth_per_m``) describe.

    The read is continuous. The candidate index t is a continuous variable (a uniform prior on it, as the softmax
    over candidates has on the index) and 1/d is linear in t between candidates; the logit is the cubic Hermite
    interpolant through the candidates' logits in 1/d, its slopes the three-point differences of uneven spacing
    (``logit_slopes``: a parabola in 1/d, the shape of a likelihood about its minimum, is reproduced exactly, so
    a minimum between two candidates lies where it is). The read is that posterior's mean 1/d over the ``reach``
    candidates either side of the most probable one (a second, far mode would pull the whole mean between two
    surfaces, where neither is), evaluated at ``points`` midpoints per interval. A read snapped to the candidates
    would be off by up to half their spacing (5–10 % of the depth beyond 3 m) on a surface whose pooled evidence
    is sharp. The spread is the discrete posterior's std over every candidate: wide for flat or two-peaked
    evidence."""
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
    return continuous_read(z, x, reach, points, np), np.sqrt(var)


def continuous_read(z, x, reach: int, points: int, xp):
    """``posterior``'s read of logits ``z`` (D, ...; their maximum 0) and 1/d ``x`` (D, 1, ...), in numpy or torch
    (``xp``): the 2 ``reach`` intervals about the mode are gathered (those past either end weigh 0) and their cubic
    evaluated at ``points`` midpoints."""
    n = z.shape[0]
    slopes = logit_slopes(z, x, xp)
    mode = xp.argmax(z, 0)
    u = (xp.arange(points) + 0.5) / points
    u = u.reshape((points,) + (1,) * (z.ndim - 1))
    basis = (2 * u ** 3 - 3 * u ** 2 + 1, u ** 3 - 2 * u ** 2 + u, -2 * u ** 3 + 3 * u ** 2, u ** 3 - u ** 2)
    x_flat = x.reshape(-1)
    take = (lambda a, i: np.take_along_axis(a, i, 0)) if xp is np else (lambda a, i: xp.gather(a, 0, i))
    total = first = 0.0
    for offset in range(-reach, reach):
        j = mode + offset
        ok = (j >= 0) & (j <= n - 2)
        j = xp.clip(j, 0, n - 2)[None]
        x0, x1 = x_flat[j], x_flat[j + 1]   # the candidates' 1/d at each window's interval ends
        z0, z1 = take(z, j), take(z, j + 1)
        m0, m1 = take(slopes, j) * (x1 - x0), take(slopes, j + 1) * (x1 - x0)   # d(logit)/du, u ∈ [0, 1]
        zi = basis[0] * z0 + basis[1] * m0 + basis[2] * z1 + basis[3] * m1      # (points, ...)
        w = xp.exp(zi) * ok
        xi = x0 + u * (x1 - x0)
        total = total + w.sum(0)
        first = first + (w * xi).sum(0)
    return first / total


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
    made sums (``cell_sums``) and divided by each cell's clipped area (an empty cell reads 0). float32."""
    height, width = image.shape[:2]
    area = np.maximum(cell_area_px(stride_px, grid_shape, height, width), 1)[..., None]
    return cell_sums(image, stride_px, *grid_shape) / area.astype(np.float32)


def cell_sums(image: np.ndarray, stride_px: int, rows: int, cols: int, first_row_half: bool = True) -> np.ndarray:
    """(rows, cols, C) float32 sums of an H × W × C image over the ``rows`` × ``cols`` cells (``cell_bounds``) it starts
    at: the first cell row is half a cell (a frame's, ``first_row_half``) or a whole one (a band of a frame that starts
    at a cell's top), the first cell column is half a cell, and the last ones may be clipped; pixels past the cells are
    left out. Zero-padded to whole cells, one area resampling gives the means (exact for a whole-number factor)."""
    import cv2

    s, half = int(stride_px), int(stride_px) // 2
    top = half if first_row_half else 0
    crop = np.ascontiguousarray(image[:max(0, rows * s - top), :max(0, cols * s - half)], np.float32)
    if crop.size == 0:
        return np.zeros((rows, cols, image.shape[2]), np.float32)
    padded = cv2.copyMakeBorder(crop, top, rows * s - top - crop.shape[0], half, cols * s - half - crop.shape[1],
                                cv2.BORDER_CONSTANT, value=0)
    means = cv2.resize(padded, (cols, rows), interpolation=cv2.INTER_AREA)
    return means.reshape(rows, cols, -1) * np.float32(s * s)


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
