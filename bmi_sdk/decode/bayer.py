"""Raw Bayer window → the four colour planes the evidence is computed on, and the raw noise level.

An RGGB sensor's pixel (row, col) of the *full* sensor sees R when both are even, B when both
are odd, G otherwise (``bmi_sdk.sensor``). A window whose offset is even on both axes therefore
splits into R = [0::2, 0::2], G1 = [0::2, 1::2], G2 = [1::2, 0::2], B = [1::2, 1::2]. Each plane
is the colour channel's optical image sampled every second pixel, with white noise: no
demosaicing enters the likelihood.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

PLANE_OFFSETS = ((0, 0), (0, 1), (1, 0), (1, 1))
PLANE_CHANNELS = (0, 1, 1, 2)
"""Colour channel (0 R, 1 G, 2 B) of each plane of ``PLANE_OFFSETS``."""
MAD_TO_SIGMA = 1.4826
"""σ of a normal law per unit of median absolute deviation."""


def normalised_planes(raw: np.ndarray, black_level_dn: float, white_level_dn: float, row0: int = 0,
                      col0: int = 0) -> np.ndarray:
    """(4, H/2, W/2) float32 planes R, G1, G2, B of an RGGB window at (row0, col0), in units of full scale.

    ``(raw − black) / (white − black)``, not clipped (clipping would bias the noise).
    """
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise ValueError(f"a raw window must be H × W with even sizes, got {raw.shape}")
    if row0 % 2 or col0 % 2:
        raise ValueError(f"window offset ({row0}, {col0}) is odd: not whole RGGB cells")
    if not white_level_dn > black_level_dn:
        raise ValueError(f"white level {white_level_dn} must exceed black level {black_level_dn}")
    scale = np.float32(1.0 / (white_level_dn - black_level_dn))
    x = (raw.astype(np.float32) - np.float32(black_level_dn)) * scale
    return np.stack([x[r::2, c::2] for r, c in PLANE_OFFSETS])


FULL_SCALE_TOLERANCE = 1e-6
"""A normalised sample this close to full scale is the white level itself (one DN is ~2.6e-4 of full scale)."""


def clipped_samples(planes: np.ndarray) -> np.ndarray:
    """Boolean mask of ``normalised_planes`` samples at or above the white level: censored observations (the true
    signal is somewhere above), which no Gaussian noise model describes."""
    return planes >= np.float32(1.0 - FULL_SCALE_TOLERANCE)


NOISE_BLOCK_PX = 16
NOISE_PERCENTILE = 10.0


@lru_cache(maxsize=1)
def _null_percentile() -> float:
    """The ``NOISE_PERCENTILE``-th percentile of the block MAD estimate for pure unit noise (seeded draw).

    Dividing by it removes the bias of picking the lowest blocks: with noise alone the estimator
    returns the noise σ.
    """
    rng = np.random.default_rng(0)
    blocks = rng.standard_normal((20000, NOISE_BLOCK_PX * NOISE_BLOCK_PX))
    med = np.median(blocks, axis=1, keepdims=True)
    return float(np.percentile(MAD_TO_SIGMA * np.median(np.abs(blocks - med), axis=1), NOISE_PERCENTILE))


def estimate_noise_sigma(planes: np.ndarray) -> float:
    """Robust σ of the white noise on the planes, from the diagonal Haar detail (a − b − c + d) / 2.

    The detail of noise alone has σ equal to the noise's; image detail adds to it where the coded
    image is sharp (far depths pass frequencies up to the plane's Nyquist). So the detail is
    cut into ``NOISE_BLOCK_PX``² blocks, each block gets a MAD estimate, and the
    ``NOISE_PERCENTILE``-th percentile over blocks and planes, divided by the same percentile for
    noise alone (``_null_percentile``), is returned: the flattest (most blurred or textureless)
    blocks, where the detail is noise. Under signal-dependent (photon) noise this is the noise of
    those blocks, a lower bound elsewhere.
    """
    per_block = []
    b = NOISE_BLOCK_PX
    for p in planes:
        h, w = (p.shape[0] // 2) * 2, (p.shape[1] // 2) * 2
        q = p[:h, :w]
        detail = (q[0::2, 0::2] - q[0::2, 1::2] - q[1::2, 0::2] + q[1::2, 1::2]) * 0.5
        hb, wb = detail.shape[0] // b, detail.shape[1] // b
        if hb == 0 or wb == 0:
            per_block.append(np.array([MAD_TO_SIGMA * np.median(np.abs(detail - np.median(detail)))]))
            continue
        blocks = detail[:hb * b, :wb * b].reshape(hb, b, wb, b).transpose(0, 2, 1, 3).reshape(hb * wb, b * b)
        med = np.median(blocks, axis=1, keepdims=True)
        per_block.append(MAD_TO_SIGMA * np.median(np.abs(blocks - med), axis=1))
    return float(np.percentile(np.concatenate(per_block), NOISE_PERCENTILE)) / _null_percentile()
