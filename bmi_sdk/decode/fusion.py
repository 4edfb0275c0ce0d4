"""Fusion of two depth reads of the same pixels, in log depth, with a weight fitted or inverse-variance.

The learned refinement (``--decoder learned``) returns a depth and a 1σ from its network; its classical
stage returned its own depth and 1σ from the camera's kernels. Neither read is better everywhere: the
network fills textureless windows and reads tile-scale clutter better, the physics reads large textured
surfaces better (docs/results.md, sessions 15 and 16). The learned decoder's output is their fusion:

    log d = p log d_a + (1 − p) log d_b,   r = p r_a + (1 − p) r_b,   σ = r d,

with r = σ / d each read's relative 1σ (the 1σ of its log depth to first order) and p read a's share,

    logit p = c₀ + c_a log r_a + c_b log r_b + c_g log(g + g₀) + c_v log(v_a + v₀),   g = |log d_a − log d_b|,

v_a the variation of read a around the pixel: for the classical read, the spread (std) of its log depth over
the 3 × 3 neighbouring windows of its final window grid (``classical.local_log_depth_variation``).

``INVERSE_VARIANCE`` (c = 0, −2, 2, 0) is p = r_b² / (r_a² + r_b²), the inverse-variance weight, exact for
Gaussian errors. The two reads' errors are not Gaussian: most pixels read far better than their σ and a
few far worse (docs/results.md, "Classical and learned decoders"), so how far the reads disagree (g) tells which one is off.
Neither σ nor g tells a large surface from tile-scale clutter, where the two reads disagree by as much
but the classical one is right on the surface and wrong in the clutter (docs/decoder.md, "Fusion"): v_a
does, and c_v (0 in weights fitted before it) lets the weight read it. How much each read's σ can be
trusted also changes with the frame's noise, so the coefficients may be fitted at several noise levels
and interpolated linearly in log σ_noise between them. A model's manifest may carry weights fitted to minimise the fused log error on scenes apart from every reported one
(``nn.fusion_fit``, ``bmi fit-fusion``); without them the fusion is the inverse-variance one.

The fused σ is the one the two reads would have if their errors were fully correlated (ρ = 1): the
network reads the classical stage's output, so the two errors are not independent, and for a weight
fixed in advance and any ρ ≤ 1 the fused error's spread is at most this
(p² r_a² + (1−p)² r_b² + 2ρ p(1−p) r_a r_b ≤ (p r_a + (1−p) r_b)²). The tests check that bound
against correlated draws; with a weight that reads g it is measured (``bmi eval``'s error/σ spread).

Where only one read is valid (finite, positive depth and σ), it is the output; where neither, NaN.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import expit

N_COEFFICIENTS = 5
"""c₀, c_a, c_b, c_g, c_v: the numbers of one noise level's row."""


@dataclass(frozen=True)
class FusionWeights:
    """The logistic weight of read a (module doc):
    logit p = c₀ + c_a log r_a + c_b log r_b + c_g log(g + g₀) + c_v log(v_a + v₀).

    (c₀, c_a, c_b, c_g, c_v) = (intercept, rel_sigma_a, rel_sigma_b, gap, variation_a) at ``noise_ref_sigma``,
    and ``noise_coefficients[k]`` at the noisier ``noise_levels[k]`` (σ, fraction of full scale, increasing): at a
    frame's noise they are interpolated linearly in log σ between the levels they were fitted at, and held
    below the least and above the most. A row of four numbers (weights fitted before c_v) has c_v = 0."""

    intercept: float
    rel_sigma_a: float
    rel_sigma_b: float
    gap: float = 0.0
    variation_a: float = 0.0
    gap_floor: float = 0.01  # log-depth gaps well under 1 % read as agreement
    variation_floor: float = 0.01  # log-depth variations well under 1 % read as a flat surface
    noise_ref_sigma: float = 0.005  # the standard noise
    noise_levels: tuple = ()
    noise_coefficients: tuple = ()

    def __post_init__(self):
        levels = tuple(self.noise_levels)
        table = tuple(tuple(row) for row in self.noise_coefficients)
        if len(table) != len(levels) or any(len(row) not in (4, N_COEFFICIENTS) for row in table):
            raise ValueError(f"fusion weight noise_coefficients holds {N_COEFFICIENTS} numbers (4 before "
                             f"variation_a) for each of the {len(levels)} noise_levels, "
                             f"got {[len(row) for row in table]}")
        table = tuple(row + (0.0,) * (N_COEFFICIENTS - len(row)) for row in table)
        object.__setattr__(self, "noise_levels", levels)
        object.__setattr__(self, "noise_coefficients", table)
        values = {k: getattr(self, k) for k in ("intercept", "rel_sigma_a", "rel_sigma_b", "gap", "variation_a",
                                                "gap_floor", "variation_floor", "noise_ref_sigma")}
        values.update({f"noise_levels[{i}]": v for i, v in enumerate(levels)})
        values.update({f"noise_coefficients[{i}][{j}]": v for i, row in enumerate(table) for j, v in enumerate(row)})
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"fusion weight {name} must be a finite number, got {value!r}")
        if self.gap_floor <= 0 or self.variation_floor <= 0 or self.noise_ref_sigma <= 0:
            raise ValueError(f"fusion weights need gap_floor, variation_floor and noise_ref_sigma > 0, got "
                             f"{self.gap_floor}, {self.variation_floor} and {self.noise_ref_sigma}")
        if any(b <= a for a, b in zip((self.noise_ref_sigma, *levels), levels)):
            raise ValueError(f"fusion weight noise_levels must rise above noise_ref_sigma {self.noise_ref_sigma}, "
                             f"got {list(levels)}")

    def to_dict(self) -> dict:
        return {**asdict(self), "noise_levels": list(self.noise_levels),
                "noise_coefficients": [list(row) for row in self.noise_coefficients]}

    @classmethod
    def from_dict(cls, data: dict) -> "FusionWeights":
        """The weights a manifest's ``fusion.weights`` holds, refusing unknown or missing keys by name."""
        if not isinstance(data, dict):
            raise ValueError(f"fusion weights are a JSON object, got {type(data).__name__}")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown fusion weight(s) {unknown}; known: {sorted(known)}")
        for key in ("noise_levels", "noise_coefficients"):
            value = data.get(key, ())
            if not isinstance(value, (list, tuple)) or (
                    key == "noise_coefficients" and not all(isinstance(row, (list, tuple)) for row in value)):
                raise ValueError(f"fusion weight {key} is a list{' of lists' if key == 'noise_coefficients' else ''}, "
                                 f"got {value!r}")
        try:
            return cls(**data)
        except TypeError as exc:
            raise ValueError(f"fusion weights {sorted(data)} lack some of {sorted(known)}") from exc

    def coefficients(self, noise_sigma: float | None = None) -> np.ndarray:
        """(c₀, c_a, c_b, c_g, c_v) at a frame's noise σ (fraction of full scale; None: at ``noise_ref_sigma``)."""
        base = np.array([self.intercept, self.rel_sigma_a, self.rel_sigma_b, self.gap, self.variation_a])
        if noise_sigma is None or not self.noise_levels:
            return base
        if not (math.isfinite(noise_sigma) and noise_sigma >= 0):
            raise ValueError(f"the fusion's noise σ must be a number ≥ 0, got {noise_sigma}")
        if noise_sigma <= self.noise_ref_sigma:  # a noise-free frame included: the reference weights
            return base
        log_levels = np.log([self.noise_ref_sigma, *self.noise_levels])
        table = np.array([base, *self.noise_coefficients])
        return np.array([np.interp(math.log(noise_sigma), log_levels, table[:, j]) for j in range(N_COEFFICIENTS)])

    @property
    def reads_variation(self) -> bool:
        """Whether the weight reads read a's variation at any noise level (``fuse_log_depth`` then needs it)."""
        return bool(self.variation_a) or any(row[4] for row in self.noise_coefficients)

    def share_a(self, rel_a: np.ndarray, rel_b: np.ndarray, log_gap: np.ndarray,
                noise_sigma: float | None = None, variation_a: np.ndarray | None = None) -> np.ndarray:
        """p, read a's share in each pixel's log depth, from both relative 1σs, |log d_a − log d_b|, read a's
        log-depth variation around the pixel (needed when ``reads_variation``) and the frame's noise σ."""
        c0, ca, cb, cg, cv = self.coefficients(noise_sigma)
        logit = c0 + ca * np.log(rel_a) + cb * np.log(rel_b)
        if cg:
            logit = logit + cg * np.log(log_gap + self.gap_floor)
        if cv:
            if variation_a is None:
                raise ValueError("these fusion weights read the classical read's log-depth variation; none was given")
            logit = logit + cv * np.log(np.nan_to_num(variation_a, nan=0.0) + self.variation_floor)
        return expit(logit)


INVERSE_VARIANCE = FusionWeights(0.0, -2.0, 2.0)
"""p = r_b² / (r_a² + r_b²): the fusion of a model whose manifest carries no fitted weights."""


def _read_ok(depth_m: np.ndarray, sigma_m: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth_m) & np.isfinite(sigma_m) & (depth_m > 0) & (sigma_m > 0)


def fuse_log_depth(depth_a_m: np.ndarray, sigma_a_m: np.ndarray, depth_b_m: np.ndarray, sigma_b_m: np.ndarray,
                   weights: FusionWeights = INVERSE_VARIANCE, noise_sigma: float | None = None,
                   variation_a: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth_m, sigma_m, weight_a) of the fusion (module doc) of reads a and b, arrays of one shape, with
    ``weights`` at the frame's noise σ (fraction of full scale; None: the weights' reference noise) and read a's
    log-depth variation ``variation_a`` (same shape; needed by weights that read it, NaN read as 0).

    ``weight_a`` is p, the share read a has in each pixel's log depth (1 where only a is valid, 0 where only
    b is, NaN where neither): its mean says how much of a frame each read decided.
    """
    shapes = {np.shape(x) for x in (depth_a_m, sigma_a_m, depth_b_m, sigma_b_m)
              + (() if variation_a is None else (variation_a,))}
    if len(shapes) != 1:
        raise ValueError(f"the two reads' depth and sigma maps must have one shape, got {sorted(shapes)}")
    ok_a, ok_b = _read_ok(depth_a_m, sigma_a_m), _read_ok(depth_b_m, sigma_b_m)
    both = ok_a & ok_b
    safe_a, safe_b = np.where(ok_a, depth_a_m, 1.0), np.where(ok_b, depth_b_m, 1.0)
    rel_a = np.where(ok_a, sigma_a_m, 1.0) / safe_a
    rel_b = np.where(ok_b, sigma_b_m, 1.0) / safe_b
    log_a, log_b = np.log(safe_a), np.log(safe_b)
    share = weights.share_a(rel_a, rel_b, np.abs(log_a - log_b), noise_sigma, variation_a)
    weight_a = np.where(both, share, np.where(ok_a, 1.0, 0.0))
    log_depth = weight_a * log_a + (1.0 - weight_a) * log_b
    depth = np.exp(log_depth)
    sigma = (weight_a * rel_a + (1.0 - weight_a) * rel_b) * depth
    none = ~(ok_a | ok_b)
    dtype = np.result_type(depth_a_m, depth_b_m)
    depth, sigma, weight_a = (np.where(none, np.nan, x).astype(dtype, copy=False) for x in (depth, sigma, weight_a))
    return depth, sigma, weight_a
