"""Each window's read taken from the windows around it that see one surface of its colour (adaptive support).

The likelihood (``evidence``) assumes one depth per window. A window whose support straddles an occlusion
fits one candidate anyway, and confidently: a near object's blurred texture beside a sharp background is read
as the background, since no near kernel makes the background's high frequencies. So the rims of near objects
read far, and a depth edge carries most of a frame's error. Its neighbours whose support lies on one surface
read that surface well.

The read of window i becomes the weighted mixture of the reads of the windows j within ``radius_windows``:

    w_ij = exp(−r²/2s²) · exp(−|g_i − g_j|²/2c²) · exp(−v_j / τ),

r the distance in windows, g a window's cell colour (``cell_colours``: the log of the mean colour of the
stride × stride cell at its centre, plus a dark floor, so that the noise and faint texture of a dark surface
are not read as colour edges), and v_j the spread of colour over window j's support: the variance of the
cell colours under the window's taper (``colour_spread``). A window of one colour most likely sees one
surface (v ≈ 0, full weight); one across a colour edge gets e^(−v/τ). The colour term keeps the mixture on
the window's own side of the edge; the spatial term keeps it local. Its variance is the mixture's (each
window's own plus the spread of the reads), so a window between two surfaces still reports the gap. This is
the adaptive support weighting of stereo matching (Yoon & Kweon, "Adaptive support-weight approach for
correspondence search", TPAMI 2006; Hosni et al., TPAMI 2013) applied to the windows' reads.

Weights are formed in the log domain and normalised per window, so a window all of whose neighbours have a
large spread or a far colour still reads them (relatively) rather than dividing by an underflowed zero.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .volume import cell_area_px, cell_colour

MAX_RADIUS_WINDOWS = 4
"""The widest support read: 9 × 9 windows (64 px either side at stride 16), whose 81 weight grids a full frame
holds at once (~70 MB)."""


@dataclass(frozen=True)
class SupportConfig:
    """The knobs of ``support_read`` (an evidence network's manifest ``support``)."""

    radius_windows: int = 1          # neighbours up to this many windows away on each axis (0: the read as it is)
    spatial_sigma_windows: float = 1.0
    colour_sigma: float = 0.3        # log colour
    spread_scale: float = 0.05       # τ: a support whose colour variance is τ weighs e⁻¹
    dark_floor: float = 0.01         # added to the linear cell colour (white = 1) before its log

    def __post_init__(self):
        if isinstance(self.radius_windows, bool) or not isinstance(self.radius_windows, int) \
                or not 0 <= self.radius_windows <= MAX_RADIUS_WINDOWS:
            raise ValueError(f"support radius_windows must be a whole number in [0, {MAX_RADIUS_WINDOWS}], got "
                             f"{self.radius_windows!r}")
        for name in ("spatial_sigma_windows", "colour_sigma", "spread_scale", "dark_floor"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ValueError(f"support {name} must be a finite number > 0, got {value!r}")

    def to_dict(self) -> dict:
        return asdict(self)


def cell_colours(rgb: np.ndarray, stride_px: int, grid_shape: tuple[int, int], dark_floor: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(R × C × 3 colours, R × C cells holding pixels) of the window grid over an H × W × 3 linear RGB frame
    (white = 1): log(mean colour of the window's cell + ``dark_floor``). The floor makes colours darker than it
    differ by their difference rather than their ratio: a cell mean of a dark surface, a few noise σ above
    black, would otherwise swing by whole units of log colour."""
    mean = cell_colour(rgb, stride_px, grid_shape)
    return np.log(np.maximum(mean, 0.0) + np.float32(dark_floor)), cell_area_px(stride_px, grid_shape,
                                                                                   *rgb.shape[:2]) > 0


def taper_weights(window_px: int, stride_px: int) -> np.ndarray:
    """The Hann taper of a ``window_px`` window at the centres of the cells it covers (offsets k · stride,
    |k · stride| < window / 2): cos²(π k stride / window). 64-px windows at stride 16: (½, 1, ½)."""
    reach = math.ceil(window_px / (2 * stride_px)) - 1
    k = np.arange(-reach, reach + 1)
    return np.cos(np.pi * k * stride_px / window_px) ** 2


def colour_spread(cells: np.ndarray, cell_ok: np.ndarray, window_px: int, stride_px: int) -> np.ndarray:
    """(R, C) spread of colour over each window's support: the variance of the cell colours (R × C × 3 log
    colour, summed over the channels) under the window's taper sampled at the cell centres (``taper_weights``),
    over the cells that hold pixels (``cell_ok``). A window none of whose support's cells holds pixels reads 0."""
    w1 = taper_weights(window_px, stride_px)
    reach = len(w1) // 2
    rows, cols = cell_ok.shape
    ok = cell_ok.astype(np.float64)
    g = np.where(cell_ok[..., None], cells, 0.0).astype(np.float64)
    pad = ((reach, reach), (reach, reach))
    ok_p = np.pad(ok, pad)
    g_p = np.pad(g, pad + ((0, 0),))
    weight = np.zeros((rows, cols))
    first = np.zeros((rows, cols, 3))
    second = np.zeros((rows, cols))
    for a, wa in enumerate(w1):
        for b, wb in enumerate(w1):
            w = wa * wb * ok_p[a:a + rows, b:b + cols]
            x = g_p[a:a + rows, b:b + cols]
            weight += w
            first += w[..., None] * x
            second += w * np.einsum("...c,...c->...", x, x)
    safe = np.maximum(weight, 1e-300)
    mean = first / safe[..., None]
    spread = second / safe - np.einsum("...c,...c->...", mean, mean)
    return np.where(weight > 0, np.maximum(spread, 0.0), 0.0)


def support_read(inv_grid: np.ndarray, var_grid: np.ndarray, cells: np.ndarray, cell_ok: np.ndarray,
                 config: SupportConfig, window_px: int, stride_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(1/d, variance of 1/d) of every window (R × C, float32) as the mixture of its like-coloured, single-surface
    neighbours' reads (module doc). ``inv_grid``/``var_grid``: the windows' reads (NaN where a window has none,
    which stays NaN and lends nothing); ``cells``/``cell_ok``: the windows' cell colours and which cells hold
    pixels (``cell_colours``)."""
    if inv_grid.shape != var_grid.shape or cells.shape[:2] != inv_grid.shape or cell_ok.shape != inv_grid.shape:
        raise ValueError(f"support_read needs R × C reads, variances and cell flags and R × C × 3 cell colours, got "
                         f"{inv_grid.shape}, {var_grid.shape}, {cell_ok.shape} and {cells.shape}")
    valid = np.isfinite(inv_grid) & np.isfinite(var_grid)
    if config.radius_windows == 0:
        return (np.where(valid, inv_grid, np.nan).astype(np.float32),
                np.where(valid, var_grid, np.nan).astype(np.float32))
    rows, cols = inv_grid.shape
    r = config.radius_windows
    log_purity = -colour_spread(cells, cell_ok, window_px, stride_px) / config.spread_scale
    pad = ((r, r), (r, r))
    lp_p = np.pad(np.where(valid, log_purity, -np.inf), pad, constant_values=-np.inf)
    g = np.asarray(cells, np.float64)
    g_p = np.pad(g, pad + ((0, 0),))
    inv_p = np.pad(np.where(valid, inv_grid, 0.0).astype(np.float64), pad)
    var_p = np.pad(np.where(valid, var_grid, 0.0).astype(np.float64), pad)
    offsets = [(a, b) for a in range(2 * r + 1) for b in range(2 * r + 1)]

    def log_weight(a: int, b: int) -> np.ndarray:
        d2 = (a - r) ** 2 + (b - r) ** 2
        diff = g - g_p[a:a + rows, b:b + cols]
        colour = np.einsum("...c,...c->...", diff, diff) / (2.0 * config.colour_sigma ** 2)
        return lp_p[a:a + rows, b:b + cols] - d2 / (2.0 * config.spatial_sigma_windows ** 2) - colour

    log_weights = [log_weight(a, b) for a, b in offsets]  # ≤ 81 grids (radius ≤ MAX_RADIUS_WINDOWS)
    top = np.max(log_weights, axis=0)
    top = np.where(valid, top, 0.0)  # a valid window lends to itself, so its largest log weight is finite
    weight = np.zeros((rows, cols))
    first = np.zeros((rows, cols))
    second = np.zeros((rows, cols))
    for (a, b), lw in zip(offsets, log_weights):
        w = np.exp(lw - top)
        x = inv_p[a:a + rows, b:b + cols]
        weight += w
        first += w * x
        second += w * (var_p[a:a + rows, b:b + cols] + x * x)
    safe = np.where(valid, weight, 1.0)
    mean = first / safe
    var = np.maximum(second / safe - mean * mean, 0.0)
    return np.where(valid, mean, np.nan).astype(np.float32), np.where(valid, var, np.nan).astype(np.float32)


def frame_support_read(inv_grid: np.ndarray, var_grid: np.ndarray, rgb: np.ndarray, config: SupportConfig,
                       window_px: int, stride_px: int) -> tuple[np.ndarray, np.ndarray]:
    """``support_read`` of a frame's window grid, its cell colours taken from the frame's H × W × 3 linear RGB
    (``cell_colours`` at the config's dark floor): the step the evidence decoder runs."""
    cells, cell_ok = cell_colours(rgb, stride_px, inv_grid.shape, config.dark_floor)
    return support_read(inv_grid, var_grid, cells, cell_ok, config, window_px, stride_px)
