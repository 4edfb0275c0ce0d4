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

The window's read is a point estimate of that mixture (``SupportConfig.estimate``):

* ``relative_median`` (a new network's default): the depth that minimises the mixture's expected relative error
  Σ_j w_ij |d − d_j| / d_j, which is the weighted median of the reads d_j with weights w_ij / d_j. It is always
  one of the neighbours' reads, so a window whose neighbours see two surfaces reads one of them, never a depth
  between them that neither has (a point floating between an object and its background); where the weights are
  close it takes the nearer surface, whose relative error costs more when missed (reading a 1 m surface at 4 m
  is an error of 3, reading a 4 m one at 1 m an error of 0.75);
* ``mean``: the mixture's mean 1/d, the minimiser of its expected squared error in 1/d.

Either way the variance is the mixture's about the read, Σ_j w_ij (var_j + (1/d_j − 1/d)²) / Σ_j w_ij.

Whose read is it? A window straddling an occlusion reads the surface its evidence comes from, and its evidence comes
from the pixels with fine detail: the depth is read from how blur takes detail away, so a sharp surface's texture
outweighs a blurred one's. The sensor is focused near infinity, so at an object's rim that is the far wall, and the
window centred on the rim reads the wall although its centre cell holds the object's colour. With
``SupportConfig.attribution`` "evidence" each neighbour's read is compared with the window's cell colour through the
colour of the pixels its evidence came from (``evidence_colours``: the window's mean colour weighted by the local
high-frequency energy under its taper) instead of its own cell colour: a rim window's wall read then lends to the wall,
not to the object's rim. "cell" compares cell colours on both sides.

Weights are formed in the log domain and normalised per window, so a window all of whose neighbours have a
large spread or a far colour still reads them (relatively) rather than dividing by an underflowed zero.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .volume import cell_area_px, cell_bounds, cell_colour, cell_sums

MAX_RADIUS_WINDOWS = 4
"""The widest support read: 9 × 9 windows (64 px either side at stride 16), whose 81 weight grids a full frame
holds at once (~70 MB; the relative median sorts them, a few times that)."""
ESTIMATES = ("relative_median", "mean")
"""The point estimates of a window's mixture of reads (module doc)."""
ATTRIBUTIONS = ("cell", "evidence")
"""Which colour a neighbour's read is taken to belong to: its centre cell's, or that of the pixels its evidence came
from (module doc)."""
HIGHPASS_SIGMA_PX = 1.5
"""The fine detail ``evidence_colours`` weighs pixels by: the luminance less its Gaussian blur of this σ, squared.
Defocus takes that band away first (the camera's near kernels are 20–40 px wide, its far ones a few px)."""
EVIDENCE_BAND_CELLS = 32
"""Cell rows of a frame ``evidence_colours`` filters at a time (a full frame's weighted colour at once would be
0.3 GB; a band of 32 cells is 37 MB)."""


@dataclass(frozen=True)
class SupportConfig:
    """The knobs of ``support_read`` (an evidence network's manifest ``support``)."""

    radius_windows: int = 1          # neighbours up to this many windows away on each axis (0: the read as it is)
    spatial_sigma_windows: float = 1.0
    colour_sigma: float = 0.3        # log colour
    spread_scale: float = 0.05       # τ: a support whose colour variance is τ weighs e⁻¹
    dark_floor: float = 0.01         # added to the linear cell colour (white = 1) before its log
    estimate: str = "relative_median"  # the mixture's point estimate (``ESTIMATES``, module doc)
    attribution: str = "evidence"  # the colour a neighbour's read belongs to (``ATTRIBUTIONS``, module doc)

    def __post_init__(self):
        if isinstance(self.radius_windows, bool) or not isinstance(self.radius_windows, int) \
                or not 0 <= self.radius_windows <= MAX_RADIUS_WINDOWS:
            raise ValueError(f"support radius_windows must be a whole number in [0, {MAX_RADIUS_WINDOWS}], got "
                             f"{self.radius_windows!r}")
        for name in ("spatial_sigma_windows", "colour_sigma", "spread_scale", "dark_floor"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ValueError(f"support {name} must be a finite number > 0, got {value!r}")
        if self.estimate not in ESTIMATES:
            raise ValueError(f"support estimate must be one of {', '.join(ESTIMATES)}, got {self.estimate!r}")
        if self.attribution not in ATTRIBUTIONS:
            raise ValueError(f"support attribution must be one of {', '.join(ATTRIBUTIONS)}, got {self.attribution!r}")

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
    g = np.where(cell_ok[..., None], cells, 0.0).astype(np.float64)
    weight = _taper_smooth(cell_ok.astype(np.float64), w1)
    first = _taper_smooth(g, w1)
    second = _taper_smooth(np.einsum("...c,...c->...", g, g), w1)
    safe = np.maximum(weight, 1e-300)
    mean = first / safe[..., None]
    spread = second / safe - np.einsum("...c,...c->...", mean, mean)
    return np.where(weight > 0, np.maximum(spread, 0.0), 0.0)


def _taper_smooth(grid: np.ndarray, weights_1d: np.ndarray) -> np.ndarray:
    """(R, C, …) the separable sum Σ_ab w_a w_b grid[r + a, c + b] over the cells a window's taper covers
    (``taper_weights``), the grid zero beyond its edges."""
    reach = len(weights_1d) // 2
    rows, cols = grid.shape[:2]
    padded = np.pad(grid, ((reach, reach), (reach, reach)) + ((0, 0),) * (grid.ndim - 2))
    along_rows = sum(w * padded[a:a + rows] for a, w in enumerate(weights_1d))
    return sum(w * along_rows[:, b:b + cols] for b, w in enumerate(weights_1d))


def evidence_colours(rgb: np.ndarray, stride_px: int, grid_shape: tuple[int, int], window_px: int,
                     dark_floor: float, threads: int = 1) -> np.ndarray:
    """(R × C × 3) log colour of the pixels each window's evidence comes from (module doc): the mean linear colour of
    the window's support weighted by the taper (sampled at its cells' centres, ``taper_weights``) times each pixel's
    fine-detail energy e = (L − G_σ ⊛ L)², L the luminance (the mean of R, G, B) and σ ``HIGHPASS_SIGMA_PX``; plus
    ``dark_floor``, then the log, as ``cell_colours``. A window whose support holds no energy at all (a flat or empty
    one) reads its cells' plain mean colour under the same taper. Bands of ``EVIDENCE_BAND_CELLS`` cell rows run on
    ``threads`` threads."""
    import cv2

    from ..parallel import map_threads

    rows, cols = grid_shape
    height, width = rgb.shape[:2]
    halo = int(math.ceil(4.0 * HIGHPASS_SIGMA_PX)) + 1
    n_cols = sum(1 for lo, hi in (cell_bounds(k, stride_px, width) for k in range(cols)) if hi > lo)
    third = np.full((1, 3), 1.0 / 3.0, np.float32)

    def band(k0: int) -> tuple[int, np.ndarray] | None:
        """(k0, (cells, n_cols, 7) sums of e, e·RGB and RGB) over the band's cell rows, None past the frame."""
        bounds = [cell_bounds(k, stride_px, height) for k in range(k0, min(rows, k0 + EVIDENCE_BAND_CELLS))]
        bounds = [b for b in bounds if b[1] > b[0]]
        if not bounds or not n_cols:
            return None
        top, bottom = bounds[0][0], bounds[-1][1]
        lo, hi = max(0, top - halo), min(height, bottom + halo)
        lum = cv2.transform(np.ascontiguousarray(rgb[lo:hi], np.float32), third)
        detail = lum - cv2.GaussianBlur(lum, (0, 0), HIGHPASS_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
        e = np.square(detail[top - lo:bottom - lo])[..., None]
        colour = np.asarray(rgb[top:bottom], np.float32)
        stack = np.concatenate([e, e * colour, colour], axis=-1)
        return k0, cell_sums(stack, stride_px, len(bounds), n_cols, first_row_half=k0 == 0).astype(np.float64)

    sums = np.zeros((rows, cols, 7))
    for _, done in map_threads(band, range(0, rows, EVIDENCE_BAND_CELLS), threads, "evidence colours"):
        if done is not None:
            k0, part = done
            sums[k0:k0 + part.shape[0], :n_cols] = part
    w1 = taper_weights(window_px, stride_px)
    smooth = _taper_smooth(sums, w1)
    energy_t, weighted_t = smooth[..., 0], smooth[..., 1:4]
    area_t = _taper_smooth(cell_area_px(stride_px, grid_shape, height, width).astype(np.float64), w1)
    plain_t = smooth[..., 4:7] / np.maximum(area_t, 1.0)[..., None]
    flat = energy_t <= 0
    colour = np.where(flat[..., None], plain_t, weighted_t / np.where(flat, 1.0, energy_t)[..., None])
    return np.log(np.maximum(colour, 0.0) + dark_floor)


def support_read(inv_grid: np.ndarray, var_grid: np.ndarray, cells: np.ndarray, cell_ok: np.ndarray,
                 config: SupportConfig, window_px: int, stride_px: int,
                 source_colours: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(1/d, variance of 1/d) of every window (R × C, float32) as the mixture of its like-coloured, single-surface
    neighbours' reads (module doc). ``inv_grid``/``var_grid``: the windows' reads (NaN where a window has none,
    which stays NaN and lends nothing); ``cells``/``cell_ok``: the windows' cell colours and which cells hold
    pixels (``cell_colours``); ``source_colours`` (R × C × 3): the colour each window's read belongs to
    (``evidence_colours``), compared with the reading window's cell colour; None: the cell colours."""
    source = cells if source_colours is None else source_colours
    if inv_grid.shape != var_grid.shape or cells.shape[:2] != inv_grid.shape or cell_ok.shape != inv_grid.shape \
            or source.shape != cells.shape:
        raise ValueError(f"support_read needs R × C reads, variances and cell flags and R × C × 3 cell and source "
                         f"colours, got {inv_grid.shape}, {var_grid.shape}, {cell_ok.shape}, {cells.shape} and "
                         f"{source.shape}")
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
    g_p = np.pad(np.asarray(source, np.float64), pad + ((0, 0),))
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
    weights = [np.exp(lw - top) for lw in log_weights]
    reads = [inv_p[a:a + rows, b:b + cols] for a, b in offsets]
    weight = np.zeros((rows, cols))
    first = np.zeros((rows, cols))
    second = np.zeros((rows, cols))
    for (a, b), w, x in zip(offsets, weights, reads):
        weight += w
        first += w * x
        second += w * (var_p[a:a + rows, b:b + cols] + x * x)
    safe = np.where(valid, weight, 1.0)
    mean = first / safe
    read = mean if config.estimate == "mean" else relative_median(np.stack(reads), np.stack(weights))
    # the mixture's variance about the read: E[var_j + x_j²] − 2 read E[x_j] + read²
    var = np.maximum(second / safe - 2.0 * read * mean + read * read, 0.0)
    return np.where(valid, read, np.nan).astype(np.float32), np.where(valid, var, np.nan).astype(np.float32)


def relative_median(inv_depths: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(...) the read of (K, ...) neighbours' 1/d ``inv_depths`` (> 0 where ``weights`` > 0) that minimises the
    expected relative error Σ_k w_k |d − d_k| / d_k of depth d = 1/read: the weighted median of the reads with
    weights w_k / d_k = w_k · (1/d_k) (on a tie, the smaller 1/d of the two). Entries of weight 0 take no part;
    where every weight is 0 the result is the smallest read."""
    mass = np.where(weights > 0, weights * inv_depths, 0.0)
    order = np.argsort(inv_depths, axis=0)
    sorted_inv = np.take_along_axis(inv_depths, order, axis=0)
    cumulative = np.cumsum(np.take_along_axis(mass, order, axis=0), axis=0)
    first_past_half = np.argmax(cumulative >= 0.5 * cumulative[-1:], axis=0)
    return np.take_along_axis(sorted_inv, first_past_half[None], axis=0)[0]


def support_colours(rgb: np.ndarray, config: SupportConfig, grid_shape: tuple[int, int], window_px: int,
                    stride_px: int, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(cells, cells holding pixels, the reads' colours or None) a frame's support read compares: its cell colours
    from the frame's H × W × 3 linear RGB (``cell_colours`` at the config's dark floor) and, with the config's
    ``attribution`` "evidence", its reads' colours (``evidence_colours``, on ``threads`` threads)."""
    cells, cell_ok = cell_colours(rgb, stride_px, grid_shape, config.dark_floor)
    source = (evidence_colours(rgb, stride_px, grid_shape, window_px, config.dark_floor, threads)
              if config.attribution == "evidence" and config.radius_windows > 0 else None)
    return cells, cell_ok, source


def frame_support_read(inv_grid: np.ndarray, var_grid: np.ndarray, rgb: np.ndarray, config: SupportConfig,
                       window_px: int, stride_px: int, threads: int = 1,
                       colours: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``support_read`` of a frame's window grid with the colours ``support_colours`` takes from the frame's linear
    RGB (or ``colours``, those already taken): the step the evidence decoder runs."""
    cells, cell_ok, source = colours or support_colours(rgb, config, inv_grid.shape, window_px, stride_px, threads)
    return support_read(inv_grid, var_grid, cells, cell_ok, config, window_px, stride_px, source)
