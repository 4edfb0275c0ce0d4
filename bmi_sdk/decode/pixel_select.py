"""Each pixel's depth chosen among the reads of the windows around it, where those windows disagree.

The evidence decoder reads one depth per 64-px window (stride 16) and guides it to the pixels by colour
(``volume.guided_upsample``, the 2 × 2 windows around a pixel). Where a pixel's windows disagree, one of the 16
windows within reach of it usually read it well: on ``bmi eval``'s ×4 tiles, picking the best of their reads per pixel
would read AbsRel 0.10 where the guided read gives 0.19. Which one is right depends jointly on where the pixel lies,
how its colour compares with each window's cell and with the pixels that window's evidence came from, how uniform
each window's colour is, how sharp its read is and whether it reads nearer or farther than the others: no single
weight of those says it, so a small network scores each candidate read from them.

For a pixel whose 2 × 2 windows' support reads (``support.support_read``) differ by more than
``PixelSelect.disagreement`` in log 1/d, the candidates are the 4 × 4 windows around it, each with its support read
and its own read (before the support read): 32 reads. Each candidate j gets the features

    dy², dx², |dy|, |dx|           offset of the window's centre from the pixel, in strides;
    |g_p − c_j|²                   the pixel's and window's cell log colour, as the guided upsampling compares them;
    |h_p − k_j|², |h_p − e_j|²     the same with the support read's dark floor, against the cell colour and against
                                   the colour of the pixels the window's evidence came from (``evidence_colours``);
    v_j                            the colour spread under the window's taper (``colour_spread``);
    log(σ_j / (1/d_j))             the read's relative 1σ (clipped to [−8, 3]);
    log(1/d_j) − m_p               the read against the median of the pixel's 2 × 2 support reads;
    own                            1 for a window's own read, 0 for its support read;
    log(1 + ∇_p) |h_p − k_j|², log(1 + ∇_p), log(1/d_j)

(∇_p: the Sobel gradient magnitude of the pixel's floored log colour, mirrored at the frame's edges), standardised
by the fit's means and deviations. A two-layer perceptron (ReLU) maps them to a score; the pixel reads the
softmax-weighted mean 1/d of its candidates and the mixture's variance Σ w (var_j + (1/d_j − 1/d)²). Other pixels keep
the guided read. The weights are fitted on ``bmi eval`` tiles of a seed no reported number uses, to the least mean
relative range error (``nn.pixel_select_fit``), and live in the evidence network's manifest (``pixel_select``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..parallel import map_threads
from .support import cell_colours, colour_spread, evidence_colours
from .volume import cell_colour

REACH = (-1, 0, 1, 2)
"""Window offsets on each axis around the pixel's block k (windows k and k + 1 bracket it)."""
FEATURES = ("dy2", "dx2", "abs_dy", "abs_dx", "cell_colour", "floored_cell_colour", "evidence_colour", "spread",
            "relative_sigma", "against_median", "own", "gradient_x_colour", "gradient", "log_inv_depth")
CHUNK_PX = 4096
"""Pixels scored at once: their features are 14 × CHUNK_PX × 32 float32 (7 MB), small enough to stay in the
allocator's pool (larger chunks, freshly mapped each time, take 1.7× as long)."""


@dataclass(frozen=True)
class PixelSelect:
    """The fitted scorer (module doc): ``mean``/``std`` standardise the features; ``layers`` are (W, b) pairs, W of
    shape (in, out), ReLU between them; ``disagreement`` the log 1/d spread of a pixel's 2 × 2 support reads beyond
    which it is scored."""

    mean: np.ndarray
    std: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    disagreement: float

    @classmethod
    def from_dict(cls, d: dict) -> "PixelSelect":
        """From a manifest's ``pixel_select``; ``ValueError`` naming what is wrong."""
        try:
            if tuple(d["features"]) != FEATURES:
                raise ValueError(f"features {d['features']}, expected {list(FEATURES)}")
            mean = np.asarray(d["mean"], np.float32)
            std = np.asarray(d["std"], np.float32)
            layers = tuple((np.asarray(w, np.float32), np.asarray(b, np.float32)) for w, b in d["layers"])
            disagreement = float(d["disagreement"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"pixel_select lacks or garbles {exc}") from None
        n = len(FEATURES)
        if mean.shape != (n,) or std.shape != (n,) or not np.all(std > 0):
            raise ValueError(f"mean and std must be {n} numbers, std positive")
        width = n
        for w, b in layers:
            if w.ndim != 2 or w.shape[0] != width or b.shape != (w.shape[1],):
                raise ValueError(f"a layer of shape {w.shape} / {b.shape} does not follow a width of {width}")
            width = w.shape[1]
        if not layers or width != 1:
            raise ValueError("the last layer must give one score")
        arrays = [mean, std] + [a for layer in layers for a in layer]
        if not all(np.isfinite(a).all() for a in arrays) or not np.isfinite(disagreement) or disagreement < 0:
            raise ValueError("non-finite weights or a negative disagreement")
        return cls(mean, std, layers, disagreement)

    def to_dict(self) -> dict:
        return {"features": list(FEATURES), "mean": self.mean.tolist(), "std": self.std.tolist(),
                "layers": [[w.tolist(), b.tolist()] for w, b in self.layers], "disagreement": self.disagreement}

    def scores(self, features: np.ndarray) -> np.ndarray:
        """(…,) scores of feature-major (n_features, …) features (``candidate_features``)."""
        shape = features.shape[1:]
        x = features.reshape(len(FEATURES), -1)
        x = (x - self.mean[:, None]) / self.std[:, None]
        for n, (w, b) in enumerate(self.layers):
            x = w.T @ x + b[:, None]
            if n < len(self.layers) - 1:
                np.maximum(x, np.float32(0.0), out=x)
        return x.reshape(shape)


@dataclass
class Grids:
    """What the features read, on a frame's window grid (R × C) and its pixels (H × W)."""

    inv_support: np.ndarray
    var_support: np.ndarray
    inv_own: np.ndarray
    var_own: np.ndarray
    cell_log: np.ndarray      # (R, C, 3) mean log colour of each cell (the guided upsampling's)
    cells: np.ndarray         # (R, C, 3) log(mean colour + dark floor) (the support read's)
    evidence: np.ndarray      # (R, C, 3) the colour each window's evidence came from
    spread: np.ndarray        # (R, C)
    log_rgb: np.ndarray       # (H, W, 3) floored log colour (``volume.pixel_log_colour``)
    rgb: np.ndarray           # (H, W, 3) linear colour
    dark_floor: float         # the support read's: pixels are compared as log(colour + dark floor)
    stride_px: int

    def floored_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n, 3) log(colour + dark floor) of the given pixels (taken where needed, not for the whole frame)."""
        return floored_log(self.rgb[rows, cols], self.dark_floor)

    @cached_property
    def window_table(self) -> np.ndarray:
        """(R · C, 14) float32: each window's cell colour, floored cell colour, evidence colour, spread, support read
        and variance, own read and variance, in one row, so a pixel's 16 windows are one gather."""
        columns = [self.cell_log, self.cells, self.evidence] + [a[..., None] for a in (
            self.spread, self.inv_support, self.var_support, self.inv_own, self.var_own)]
        return np.concatenate([np.asarray(a, np.float32) for a in columns], -1).reshape(-1, 14)

    @classmethod
    def of_frame(cls, inv_support, var_support, inv_own, var_own, rgb, log_rgb, stride_px: int, window_px: int,
                 dark_floor: float, threads: int = 1, colours: tuple | None = None) -> "Grids":
        """The grids of a frame; ``colours``: the (cells, cells holding pixels, reads' colours) the support read
        compared (``support.support_colours``), reused rather than taken again (the reads' colours are taken here
        when the support read compared cell colours only)."""
        shape = inv_support.shape
        cells, cell_ok, evidence = colours if colours is not None else (*cell_colours(rgb, stride_px, shape,
                                                                                      dark_floor), None)
        if evidence is None:
            evidence = evidence_colours(rgb, stride_px, shape, window_px, dark_floor, threads)
        return cls(inv_support, var_support, inv_own, var_own, cell_colour(log_rgb, stride_px, shape), cells,
                   evidence, colour_spread(cells, cell_ok, window_px, stride_px), log_rgb, rgb, dark_floor,
                   stride_px)


def floored_log(rgb: np.ndarray, dark_floor: float) -> np.ndarray:
    """log(max(colour, 0) + dark floor), float32."""
    return np.log(np.maximum(rgb, 0.0) + np.float32(dark_floor)).astype(np.float32)


def gradient_at(rgb: np.ndarray, rows: np.ndarray, cols: np.ndarray, dark_floor: float) -> np.ndarray:
    """Sobel gradient magnitude √(Σ_c (S_r g_c)² + (S_c g_c)²) of the floored log colour g = ``floored_log`` of an
    H × W × 3 linear image at the given pixels, g mirrored about the frame's edges (``scipy.ndimage.sobel``'s
    "reflect"), from their 3 × 3 neighbourhoods only."""
    height, width = rgb.shape[:2]

    def at(dr: int, dc: int) -> np.ndarray:
        r, c = rows + dr, cols + dc
        r = np.where(r < 0, -r - 1, np.where(r >= height, 2 * height - r - 1, r))
        c = np.where(c < 0, -c - 1, np.where(c >= width, 2 * width - c - 1, c))
        return floored_log(rgb[r, c], dark_floor).astype(np.float64)

    n = {(dr, dc): at(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)}
    along_rows = (n[1, -1] + 2 * n[1, 0] + n[1, 1]) - (n[-1, -1] + 2 * n[-1, 0] + n[-1, 1])
    along_cols = (n[-1, 1] + 2 * n[0, 1] + n[1, 1]) - (n[-1, -1] + 2 * n[0, -1] + n[1, -1])
    return np.sqrt((along_rows ** 2 + along_cols ** 2).sum(-1)).astype(np.float32)


def candidate_features(grids: Grids, rows: np.ndarray, cols: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(features (14, n, 32), feature-major; 1/d (n, 32), variance (n, 32), usable (n, 32)) of the candidates of the
    pixels at ``rows``, ``cols`` (module doc): the 16 windows' support reads, then their own reads, each 16 in
    ``REACH`` order (rows outer). A candidate outside the grid or without a read is not usable; its features are
    finite (1/d taken as 1) and its score is never used. float32."""
    s = grids.stride_px
    n_rows, n_cols = grids.inv_support.shape
    kr, kc = rows // s, cols // s
    fy = ((rows % s + 0.5) / s).astype(np.float32)
    fx = ((cols % s + 0.5) / s).astype(np.float32)
    reach = np.asarray(REACH)
    off_r, off_c = np.repeat(reach, len(reach)), np.tile(reach, len(reach))
    r_all, c_all = kr[:, None] + off_r, kc[:, None] + off_c
    inside = (r_all >= 0) & (r_all < n_rows) & (c_all >= 0) & (c_all < n_cols)
    r, c = np.clip(r_all, 0, n_rows - 1), np.clip(c_all, 0, n_cols - 1)
    dy, dx = off_r.astype(np.float32) - fy[:, None], off_c.astype(np.float32) - fx[:, None]
    pixel_floored = grids.floored_at(rows, cols)[:, None, :]
    window = np.take(grids.window_table, r * n_cols + c, axis=0)  # (n, 16, 14)

    def distance(pixel: np.ndarray, colours: np.ndarray) -> np.ndarray:
        d = pixel - colours
        return np.einsum("...c,...c->...", d, d)

    cell = distance(grids.log_rgb[rows, cols][:, None, :], window[..., 0:3])
    floored_cell = distance(pixel_floored, window[..., 3:6])
    evidence = distance(pixel_floored, window[..., 6:9])
    spread = window[..., 9]
    grad = np.log1p(gradient_at(grids.rgb, rows, cols, grids.dark_floor))[:, None]
    centre = grids.inv_support[np.clip(kr[:, None] + np.array([0, 0, 1, 1]), 0, n_rows - 1),
                               np.clip(kc[:, None] + np.array([0, 1, 0, 1]), 0, n_cols - 1)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a pixel none of whose windows has a read: 0
        median = np.nan_to_num(np.nanmedian(np.where(np.isfinite(centre) & (centre > 0),
                                                     np.log(np.where(centre > 0, centre, 1.0)), np.nan), 1))
    m = len(off_r)
    out = np.empty((len(FEATURES), len(rows), 2 * m), np.float32)
    shared = (dy * dy, dx * dx, np.abs(dy), np.abs(dx), cell, floored_cell, evidence, spread)
    for k, v in enumerate(shared):
        out[k, :, :m] = v
        out[k, :, m:] = v
    invs, vars_, usable = [], [], []
    for half in (0, 1):
        inv, var = window[..., 10 + 2 * half], window[..., 11 + 2 * half]
        ok = inside & np.isfinite(inv) & (inv > 0) & np.isfinite(var)
        inv_safe = np.where(ok, inv, np.float32(1.0))
        log_inv = np.log(inv_safe)
        rel_sigma = 0.5 * np.log(np.maximum(np.where(ok, var, np.float32(1.0)), np.float32(1e-12))) - log_inv
        cols_half = slice(half * m, (half + 1) * m)
        for k, v in ((8, np.clip(rel_sigma, -8.0, 3.0)), (9, log_inv - median[:, None]), (10, float(half)),
                     (11, grad * floored_cell), (12, grad), (13, log_inv)):
            out[k, :, cols_half] = v
        invs.append(inv_safe)
        vars_.append(np.where(ok, var, np.float32(0.0)))
        usable.append(ok)
    return (out, np.concatenate(invs, 1).astype(np.float32), np.concatenate(vars_, 1).astype(np.float32),
            np.concatenate(usable, 1))


def disagreeing_blocks(inv_support: np.ndarray, threshold: float, block_rows: int, block_cols: int) -> np.ndarray:
    """(block_rows, block_cols) bool: the stride × stride pixel blocks whose 2 × 2 windows' support reads span more
    than ``threshold`` in log 1/d (windows without a read left out)."""
    grid = np.where(np.isfinite(inv_support) & (inv_support > 0), inv_support, np.nan)
    corners = np.stack([np.log(grid[dr:dr + block_rows, dc:dc + block_cols]) for dr in (0, 1) for dc in (0, 1)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a block none of whose windows has a read: no span
        span = np.nanmax(corners, 0) - np.nanmin(corners, 0)
    return np.nan_to_num(span, nan=0.0) > threshold


def select_depth(select: PixelSelect, grids: Grids, inv_px: np.ndarray, var_px: np.ndarray, threads: int = 1) -> int:
    """Replace, in place, the 1/d and variance of the pixels of disagreeing blocks (``disagreeing_blocks``) by their
    scored candidates' mixture (module doc), ``CHUNK_PX`` pixels at a time on ``threads`` threads
    (``parallel.map_threads``; each chunk writes its own pixels, so any thread count gives the same bits); returns how
    many pixels were scored."""
    height, width = inv_px.shape
    s = grids.stride_px
    blocks = disagreeing_blocks(grids.inv_support, select.disagreement, -(-height // s), -(-width // s))
    block_r, block_c = np.nonzero(blocks)
    if block_r.size == 0:
        return 0
    offsets = np.arange(s)
    rows = np.broadcast_to(block_r[:, None, None] * s + offsets[None, :, None], (block_r.size, s, s)).ravel()
    cols = np.broadcast_to(block_c[:, None, None] * s + offsets[None, None, :], (block_c.size, s, s)).ravel()
    keep = (rows < height) & (cols < width)
    rows, cols = rows[keep], cols[keep]
    keep = np.isfinite(inv_px[rows, cols])
    rows, cols = rows[keep], cols[keep]

    def chunk(a: int) -> None:
        r, c = rows[a:a + CHUNK_PX], cols[a:a + CHUNK_PX]
        feats, inv, var, ok = candidate_features(grids, r, c)
        any_ok = np.asarray(ok.any(axis=1))
        score = np.where(ok, select.scores(feats), -np.inf)
        score = np.where(any_ok[:, None], score, 0.0)
        w = np.where(ok, np.exp(score - score.max(1, keepdims=True)), 0.0)
        w /= np.maximum(w.sum(1, keepdims=True), 1e-30)
        mean = (w * inv).sum(1)
        mix = (w * (var + (inv - mean[:, None]) ** 2)).sum(1)
        inv_px[r[any_ok], c[any_ok]] = mean[any_ok]
        var_px[r[any_ok], c[any_ok]] = mix[any_ok]

    for _ in map_threads(chunk, range(0, rows.size, CHUNK_PX), threads, name="pixel-select"):
        pass  # each chunk writes its own pixels
    return int(rows.size)
