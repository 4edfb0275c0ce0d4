"""Occlusion-aware layered rendering (paper §3.3, after Ikoma et al. 2021).

Layers run from the farthest (k = 0) to the nearest (K − 1). With α_k the
mask of layer k, A_k = Σ_{k' ≤ k} α_k' (layer k and everything behind it) and
h_k,c the spatially varying PSF of layer k in channel c:

    Ĩ_k = h_k * (I α_k) / (E_k + ε),  α̃_k = h_k * α_k / (E_k + ε),  E_k = h_k * A_k,
    P = Σ_k Ĩ_k Π_{k' > k} (1 − α̃_k'),  computed back to front as P ← P (1 − α̃_k) + Ĩ_k.

Because 0 ≤ I α_k ≤ α_k ≤ A_k and kernels are non-negative, Ĩ_k ≤ max I and
α̃_k ≤ 1 whatever E_k is: the guard ε = 1e-9 only turns 0/0 into 0, no
layer can blow up. The ratio is only as good as the convolutions where E_k
is small, so they run in float64 (rounding ~1e-16): in float32 the FFT's
~1e-7 rounding divided by an E_k of the same size made the result depend on
the window (up to 4e-4 in a scene). With one PSF for every layer the model reduces exactly to
h * I (tested). ``*`` is the zone overlap-add convolution of ``convolve``;
only the layers present in a zone (within a kernel width of its support) are
convolved there, and each layer only over its own bounding box.

The result is the optical image of the window (irradiance in the scene's
units, before relative illumination and noise). Scene points outside the
window are not known; E_k is computed over the window too, so near the
window's edge the layers are renormalised to the light that is there (a
flat field stays flat up to the edge instead of darkening). Render a margin
of half a kernel and crop when the exact edge matters.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ..geometry import BMI_SENSOR, SensorGeometry
from ..optics.tensor import PsfTensor
from .convolve import spread_per_pixel, zones
from .layers import layer_index, tensor_depth_index
from .psf_map import PsfMap

DEFAULT_ZONE_PX = 512
DEFAULT_RAMP_PX = 64
EPS = 1e-9


def _check(rgb: np.ndarray, range_m: np.ndarray) -> None:
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be H × W × 3, got {rgb.shape}")
    if range_m.shape != rgb.shape[:2]:
        raise ValueError(f"range_m {range_m.shape} does not match rgb {rgb.shape[:2]}")
    if rgb.size and (not np.all(np.isfinite(rgb)) or rgb.min() < 0):
        raise ValueError("rgb must be finite and non-negative (linear irradiance)")


def _dilate(sl: slice, by: int, limit: int) -> slice:
    return slice(max(sl.start - by, 0), min(sl.stop + by, limit))


def _bbox(mask: np.ndarray):
    rows = np.nonzero(mask.any(axis=1))[0]
    if len(rows) == 0:
        return None
    cols = np.nonzero(mask.any(axis=0))[0]
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def _convolve_into(acc, box, images, kernels, rows, cols):
    """acc[q] += kernel_for(q) * images(...) on the window (rows, cols), clipped to box.

    images: (5, h, w) = I·α (3 channels), α, A; kernels (C=3, K, K). Produces
    9 outputs: num (3), α per channel (3), A per channel (3).
    """
    k = kernels.shape[-1]
    r = k // 2
    h, w = images.shape[1:]
    shape = (sfft.next_fast_len(h + k - 1, real=True), sfft.next_fast_len(w + k - 1, real=True))
    fi = sfft.rfft2(images.astype(np.float64), shape, axes=(1, 2), workers=-1)
    fk = sfft.rfft2(kernels.astype(np.float64), shape, axes=(1, 2), workers=-1)
    prod = np.concatenate([fi[:3] * fk, fi[3:4] * fk, fi[4:5] * fk])
    full = sfft.irfft2(prod, shape, axes=(1, 2), workers=-1)[:, : h + k - 1, : w + k - 1]
    top, left = rows.start - r, cols.start - r
    r0, c0 = max(top, box[0].start), max(left, box[1].start)
    r1, c1 = min(top + h + k - 1, box[0].stop), min(left + w + k - 1, box[1].stop)
    if r1 > r0 and c1 > c0:
        acc[:, r0 - box[0].start:r1 - box[0].start, c0 - box[1].start:c1 - box[1].start] += \
            full[:, r0 - top:r1 - top, c0 - left:c1 - left]


def render_zones(geometry: SensorGeometry, tensor: PsfTensor, row0: int, col0: int, height: int, width: int,
                 zone_px: int | None = None, ramp_px: int | None = None) -> tuple[list, np.ndarray, np.ndarray]:
    """(zones, θ°, φ° of each zone's centre) of the ``height`` × ``width`` window at (row0, col0) as ``render_coded``
    renders it (its ``zone_px`` and ``ramp_px`` defaults); θ outside the image circle is the tensor's last field."""
    if zone_px is None:
        zone_px = DEFAULT_ZONE_PX
    if ramp_px is None:
        ramp_px = max(1, min(DEFAULT_RAMP_PX, zone_px // 8))
    zone_list = zones(height, width, zone_px, row0, col0, ramp_px)
    theta, phi = geometry.field_angles(np.array([row0 + z.row for z in zone_list]),
                                       np.array([col0 + z.col for z in zone_list]))
    return zone_list, np.nan_to_num(theta, nan=float(tensor.field_deg[-1])), phi


def render_coded(rgb: np.ndarray, range_m: np.ndarray, tensor: PsfTensor, geometry: SensorGeometry = BMI_SENSOR,
                 row0: int = 0, col0: int = 0, *, zone_px: int | None = None, ramp_px: int | None = None,
                 interpolation: str = "linear", psf_mode: str = "exact", psf_map: PsfMap | None = None,
                 progress: bool = False) -> np.ndarray:
    """Coded optical image (H × W × 3 float32) of a scene window placed at (row0, col0) of the sensor.

    ``psf_mode`` chooses how zone kernels are made (``render.psf_map``): ``exact`` traces each
    zone's own (θ, φ); ``tensor`` interpolates and rotates the radial tensor like the paper.
    ``zone_px``: the zone size (default ``DEFAULT_ZONE_PX``; a built camera's ``BuiltCamera.render_zone_px``).
    ``ramp_px`` is the blend width across zone borders (``render.convolve``); the default,
    ``zone_px`` / 8 up to 64 px, errs by 7e-5 against 64 px zones at a sixth of the cost of
    bilinear tents (``bmi bench render``). Pass a ``psf_map`` built for the same tensor and
    geometry to reuse its memoised kernels across calls (e.g. neighbouring blocks of one
    frame); ``interpolation`` and ``psf_mode`` then come from it. A built lens with hardware
    errors renders through ``PsfMap(tensor, geometry, perturbation=...)`` (``exact`` mode).
    """
    _check(rgb, range_m)
    height, width, _ = rgb.shape
    layers = layer_index(range_m, tensor.depth_m)
    n_depths = len(tensor.depth_m)
    if psf_map is None:
        psf_map = PsfMap(tensor, geometry, interpolation, psf_mode)
    elif psf_map.tensor is not tensor or psf_map.geometry != geometry:
        raise ValueError("psf_map was built for another tensor or geometry")
    kpx = psf_map.kernel_px
    zone_list, theta, phi = render_zones(geometry, tensor, row0, col0, height, width, zone_px, ramp_px)
    # Layers present near each zone (support dilated by one kernel width, see module doc).
    near = []
    for z in zone_list:
        window = layers[_dilate(z.rows, kpx, height), _dilate(z.cols, kpx, width)]
        near.append(np.unique(window))
    occupied = np.unique(np.concatenate(near)) if near else np.array([], dtype=int)
    psf_map.ensure(theta, tensor_depth_index(occupied, n_depths))
    kernel_cache: dict[tuple[int, int], np.ndarray] = {}
    image = np.zeros((3, height, width), dtype=np.float32)
    rgb_chw = np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32)
    iterator = occupied
    if progress:
        from tqdm import tqdm

        iterator = tqdm(occupied, desc="layers", unit="layer")
    for k in iterator:  # back to front
        alpha = layers == k
        bb = _bbox(alpha)
        if bb is None:
            continue
        box = (_dilate(bb[0], kpx, height), _dilate(bb[1], kpx, width))
        acc = np.zeros((9, box[0].stop - box[0].start, box[1].stop - box[1].start), dtype=np.float32)
        for zi, z in enumerate(zone_list):
            if k not in near[zi]:
                continue
            rows, cols = z.rows, z.cols
            local = _bbox(alpha[_dilate(rows, kpx, height), _dilate(cols, kpx, width)])
            if local is None:
                continue
            r_off, c_off = _dilate(rows, kpx, height).start, _dilate(cols, kpx, width).start
            # Sources that matter: within one kernel width of this layer's pixels, inside the zone support.
            rows = slice(max(rows.start, r_off + local[0].start - kpx), min(rows.stop, r_off + local[0].stop + kpx))
            cols = slice(max(cols.start, c_off + local[1].start - kpx), min(cols.stop, c_off + local[1].stop + kpx))
            if rows.stop <= rows.start or cols.stop <= cols.start:
                continue
            w = z.weight[rows.start - z.rows.start:rows.stop - z.rows.start,
                         cols.start - z.cols.start:cols.stop - z.cols.start]
            a = alpha[rows, cols].astype(np.float32) * w
            cum = (layers[rows, cols] <= k).astype(np.float32) * w
            images = np.concatenate([rgb_chw[:, rows, cols] * a, a[None], cum[None]])
            key = (zi, int(k))
            if key not in kernel_cache:
                kernel_cache[key] = psf_map.kernels(theta[zi], phi[zi], [tensor_depth_index(k, n_depths)])[:, 0]
            _convolve_into(acc, box, images, kernel_cache[key], rows, cols)
        num, den_a, den_e = acc[:3], acc[3:6], acc[6:9]
        inv = 1.0 / (np.maximum(den_e, 0.0) + EPS)
        i_k = np.maximum(num, 0.0) * inv
        a_k = np.clip(den_a * inv, 0.0, 1.0)
        view = image[:, box[0], box[1]]
        view *= 1.0 - a_k
        view += i_k
    return image.transpose(1, 2, 0).copy()


def render_reference(rgb: np.ndarray, range_m: np.ndarray, tensor: PsfTensor, geometry: SensorGeometry = BMI_SENSOR,
                     row0: int = 0, col0: int = 0, interpolation: str = "linear", psf_mode: str = "tensor") -> np.ndarray:
    """Brute-force layered rendering: every source pixel spreads with its own PSF (small windows only).

    Per-pixel kernels in ``exact`` mode cost a trace each; the default ``tensor`` mode checks the
    spatially varying convolution itself (same kernels as ``render_coded(psf_mode="tensor")``).
    """
    _check(rgb, range_m)
    height, width, _ = rgb.shape
    if height * width > 128 * 128:
        raise ValueError(f"the per-pixel reference is for small windows (≤ 128²), got {height}×{width}")
    layers = layer_index(range_m, tensor.depth_m)
    n_depths = len(tensor.depth_m)
    psf_map = PsfMap(tensor, geometry, interpolation, psf_mode)
    rows, cols = np.mgrid[0:height, 0:width]
    theta, phi = geometry.field_angles(row0 + rows, col0 + cols)
    theta = np.nan_to_num(theta, nan=float(tensor.field_deg[-1]))
    occupied = np.unique(layers)
    psf_map.ensure(theta.ravel(), tensor_depth_index(occupied, n_depths))
    image = np.zeros((3, height, width), dtype=np.float64)
    for k in occupied:
        alpha = (layers == k).astype(np.float64)
        cum = (layers <= k).astype(np.float64)
        d_idx = tensor_depth_index(k, n_depths)
        kernels = {}

        def kernel_of(r, c, ch):
            key = (r, c)
            if key not in kernels:
                kernels[key] = psf_map.kernels(theta[r, c], phi[r, c], [d_idx])[:, 0]
            return kernels[key][ch]

        num = np.zeros((3, height, width))
        den_a = np.zeros((3, height, width))
        den_e = np.zeros((3, height, width))
        for ch in range(3):
            spread_per_pixel(num[ch], rgb[..., ch] * alpha, lambda r, c: kernel_of(r, c, ch))
            spread_per_pixel(den_a[ch], alpha, lambda r, c: kernel_of(r, c, ch))
            spread_per_pixel(den_e[ch], cum, lambda r, c: kernel_of(r, c, ch))
        inv = 1.0 / (den_e + EPS)
        image = image * (1.0 - np.clip(den_a * inv, 0, 1)) + num * inv
    return image.transpose(1, 2, 0).astype(np.float32)
