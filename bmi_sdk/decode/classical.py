"""The classical decoder: depth, its 1σ and the all-in-focus image from one raw frame, with no network.

Steps (each in its own module):

1. ``bayer``: the raw frame's four colour planes. The raw noise (``frame_noise``): the frame's
   ``NoiseProfile`` (variance = scale · signal + offset, from the camera), a given σ, or a σ estimated
   from the picture; each window's noise variance follows its own mean signal.
2. Windows of ``window_px`` (full-resolution footprint) every ``stride_px``, on a grid anchored to
   the sensor: window centres sit at rows and columns k·stride − ½ of the frame. The grid is
   processed in blocks of ``block_windows``² windows; each block is one zone (θ, φ of its centre)
   whose kernels come from ``kernels.ZoneKernels``, or (``theta_step_deg``) each window reads the
   zones of a θ grid around its own θ, for a built camera whose kernels change within a block's 2°
   of field. Blocks whose pixels all lie outside the image circle are skipped. A frame's blocks are read
   on ``threads`` threads at once, each block's FFTs on one (the same result as one thread, bit for bit).
3. ``evidence``: a plane's windows holding a sample at the white level are scored from their other
   samples, under their taper ramped to zero at the clipped ones (a censored sample fits no noise
   model; ``clipped``, up to ``clipped_planes_per_frame`` pairs a frame; the report counts them); a
   plane left with too little of its taper gives no evidence, and windows left with none in every
   plane take their neighbours' 1/d (``fill_blind_windows``). A coarse pass over every
   ``coarse_step``-th candidate; the fine pass scores, for
   the whole block, the union of every window's best coarse candidate ± one coarse step, less the
   candidates the coarse pass scored (their scores are reused: both passes share the coarse pass's
   β grid, so their NLLs form one curve). The report counts the candidate evaluations done
   (coarse + fine) against the exhaustive count.
4. Refinement (parabola in 1/d) and the 1σ of 1/d. The Laplace σ_L is the likelihood's curvature
   times the taper's inflation (``evidence.taper_variance_inflation``): on data drawn from the
   model itself that is the estimate's real spread. On scenes it is too small (the Gaussian image
   prior is only a model: a window that mixes two depths, or a texture whose spectrum is not
   1/f², fits one candidate "confidently" and wrongly), so the reported σ is
   σ² = (a σ_L)² + (b s)² + c², s the spread (std) of 1/d over the 3 × 3 neighbouring windows
   (large across depth edges and in clutter), with (a, b, c) =
   (``sigma_laplace_scale``, ``sigma_spread_scale``, ``sigma_floor_inv_per_m``) fitted by maximum
   likelihood on scenes apart from the benchmark (``bmi bench decoder``).
   Pooling (``pooling``, ``pool_sigma_px`` > 0, the default): each window's whole curve (candidates neither pass
   scored interpolated, ``whole_curves``) adds its neighbours' curves, weighted by distance and colour likeness and
   each truncated at ``pool_truncate_nats``; the pooled curve's parabola gives 1/d. σ stays the window's own (its
   curvature and the spread of the windows' own reads): overlapping windows share pixels, so their curves are not
   independent evidence. A textureless window then reads its surface's depth (``bmi bench pooling``).
5. Optional confidence-weighted fill (``fill_windows`` > 0): 1/d is replaced by its
   inverse-variance weighted mean over a Gaussian neighbourhood, which gives textureless windows
   their neighbours' depth (off by default: on the benchmark it spreads the far background into
   small near objects, ``bmi bench decoder``).
6. 1/d and σ are interpolated bilinearly to every pixel; ``aif`` deconvolves each block with the
   kernels of its pixels' depths, on every ``aif_step``-th candidate (a deconvolution costs two
   FFTs per channel; neighbouring candidates' kernels differ little). The Wiener filter's noise is the
   sensor's plus a kernel-error term, ``aif_model_error`` × the block's mean signal: with the sensor's
   noise alone a noiseless frame is inverse-filtered, and every depth error rings (``bmi bench decoder``).
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from ..geometry import SensorGeometry
from ..model_io import raw_to_rgb, reflect_indices, window_cfa
from ..parallel import map_threads
from ..sensor import NoiseProfile, relative_illumination
from .aif import wiener_blend
from .bayer import clipped_samples, estimate_noise_sigma, normalised_planes
from .candidates import Candidates, inverse_depth_candidates
from .clipped import ClippedPairs, choose_clipped_planes, clipped_weights
from .evidence import (
    EXPONENT_PRIOR,
    SHARP_TEXTURE_RATIO,
    WEAK_TEXTURE_LOW_CYCLES,
    Evidence,
    gated_exponent,
    hann_taper,
    plane_nll,
    profile_exponent,
    taper_variance_inflation,
    texture_bands,
    window_spectra,
    windows_touching,
)
from .kernels import ZONE_STEP_DEG, ZoneKernels
from .pooling import pool_evidence, window_colour

NOISE_MODELS = ("profile",)  # ``frame_noise``; a manifest's classical_config names it
WINDOW_MODELS = ("tapered",)  # the taper-smoothed evidence model (``evidence``); a manifest names it too
EXPONENT_SCOPES = ("window", "pooled")  # where several slopes' texture exponent is profiled (``ClassicalConfig``)


def frame_noise(config: "ClassicalConfig", planes: np.ndarray, profile: NoiseProfile | None) -> tuple[NoiseProfile, str]:
    """The noise model the evidence uses, and where it came from.

    A given ``noise_sigma`` wins (constant σ); then the frame's own ``NoiseProfile`` (the camera's photon
    transfer: shot noise grows with the signal, so dark windows are cleaner than bright ones); a frame without
    one gets a constant σ estimated from its flattest blocks (``bayer.estimate_noise_sigma``), which image
    detail inflates on a sharp, textured frame.
    """
    if config.noise_sigma is not None:
        return NoiseProfile(0.0, float(config.noise_sigma) ** 2), "given"
    if profile is not None:
        return profile, "profile"
    return NoiseProfile(0.0, max(estimate_noise_sigma(planes), 1e-4) ** 2), "estimated"


MAX_CLIPPED_RAMP_SAMPLES = 64.0
"""The widest ramp around clipped samples ``ClassicalConfig`` takes (plane samples; two 64-px windows)."""
NOISE_SIGMA_MAX = 0.5
"""The largest constant raw noise σ (units of full scale) a ``ClassicalConfig`` takes: a σ of half the sensor's
range drowns any signal it can hold, and every window then reads its prior: one depth everywhere, every pixel
marked valid."""


MAX_SLOPE = 4.0
"""The steepest prior exponent a ``ClassicalConfig`` takes: a texture of power spectrum 1/f⁴ is already smoother than
any defocus the camera can tell from it."""

MAX_WEAK_TEXTURE_CONTRAST = 1.0
"""The largest ``ClassicalConfig.weak_texture_below``: a texture whose RMS equals its mean already fills the range a
non-negative signal allows, so no window is weaker than that."""

MAX_EXPONENT_GATE_NATS = 1e6
"""The largest ``ClassicalConfig.exponent_gate_nats``: a pool's NLL spans far fewer nats than this (its windows' curves
are truncated at ``pool_truncate_nats`` each), so a larger gate would change nothing."""


@dataclass(frozen=True)
class ClassicalConfig:
    """Accuracy knobs of the classical decoder (error against run time: ``bmi bench decoder``)."""

    window_px: int = 64
    stride_px: int = 16
    candidates: int = 48
    coarse_step: int = 4
    slopes: tuple = (2.0,)  # the prior's power exponents α (S ∝ 1/|f|^α); several (evenly spaced): α is profiled out
    #                         per window and candidate, one α for all planes (``evidence.profile_exponent``)
    exponent_scope: str = "window"  # with several slopes: "window", α profiled in each window's own NLL; "pooled",
    #                                 also each window's pooled curve is the neighbours' NLLs pooled at each slope, then
    #                                 α profiled (one α for the surface the pool holds; needs pooling)
    exponent_gate_nats: float = 0.0  # "pooled" only: a pool keeps α = 2 unless profiling α lowers its least pooled
    #                                  NLL by more than this (``evidence.gated_exponent``; 0: α profiled in every pool)
    block_windows: int = 16
    theta_step_deg: float | None = None  # None: a block's windows read its centre's zone; else each window reads
    #                                      the zones of a θ grid of this step around its own θ (``ZoneKernels.field_reads``)
    # σ model fitted by `bmi bench decoder` (seed 777, 12 tiles per region, the other defaults as here)
    sigma_laplace_scale: float = 1.0  # the fit's bound: the inflated curvature is already the spread
    sigma_spread_scale: float = 3.64
    sigma_floor_inv_per_m: float = 0.0234
    fill_windows: float = 0.0
    pool_sigma_px: float = 48.0  # 0: each window read alone; else its curve pools its neighbours' (``pooling``) within
    #                              a Gaussian of this radius, weighted by colour likeness and truncated per neighbour
    pool_colour_sigma: float = 0.4  # colour scale of the pooling weight (difference of log mean colour)
    pool_truncate_nats: float = 10.0  # the most a neighbour's curve counts against any depth
    aif_step: int = 4
    aif_model_error: float = 0.1  # the AiF's kernel is never exact (depth error, blend between candidates): its
    #                               Wiener filter counts (ε · block mean signal)² as noise besides the sensor's
    noise_sigma: float | None = None  # a given constant σ (units of full scale) overrides the frame's noise
    noise_model: str = "profile"  # the frame's NoiseProfile, else estimated from the picture (``frame_noise``)
    window_model: str = "tapered"  # the evidence model with the taper's smoothing (``evidence.folded_model``)
    exact_model_below: float = 0.0  # windows whose mean signal (fraction of white) is below this are scored with
    #                                 the exact expected periodogram (``evidence.expected_periodogram``); 0: none
    weak_texture_below: float = 0.0  # sharp windows whose texture contrast (``evidence.texture_bands``) is below this
    #                                  skip the bins within ``WEAK_TEXTURE_LOW_CYCLES`` of DC (``window_groups``); 0: none
    clipped_planes_per_frame: int = 2048  # a frame scores at most this many (window, plane) pairs holding samples
    #                                       at the white level with those samples left out (``clipped``); the rest,
    #                                       and every pair at 0, give no evidence
    clipped_ramp_samples: float = 8.0  # plane samples over which such a window's taper rises from 0 at a clipped
    #                                    sample (``clipped.clipped_weights``)
    threads: int | None = None  # blocks read at once (default: all cores; 1 on a one-thread Dask worker)

    def __post_init__(self):
        if self.window_px % 4 or self.window_px < 16:
            raise ValueError(f"window_px must be a multiple of 4 and >= 16, got {self.window_px}")
        if self.stride_px % 2 or self.stride_px < 2:
            raise ValueError(f"stride_px must be even and >= 2, got {self.stride_px}")
        if not self.aif_model_error >= 0:
            raise ValueError(f"aif_model_error must be >= 0, got {self.aif_model_error}")
        if not (self.pool_sigma_px >= 0 and self.pool_colour_sigma > 0 and self.pool_truncate_nats >= 0):
            raise ValueError(f"pooling needs pool_sigma_px >= 0, pool_colour_sigma > 0 and pool_truncate_nats >= 0, "
                             f"got {self.pool_sigma_px}, {self.pool_colour_sigma}, {self.pool_truncate_nats}")
        if self.block_windows < 1 or self.coarse_step < 1 or self.aif_step < 1:
            raise ValueError("block_windows, coarse_step and aif_step must be >= 1")
        numbers = all(isinstance(a, (int, float, np.integer, np.floating)) and not isinstance(a, bool)
                      for a in self.slopes)
        slopes = np.asarray(self.slopes, np.float64) if numbers and len(self.slopes) else np.zeros(0)
        if not len(slopes) or not np.all(np.isfinite(slopes)) or not np.all((slopes > 0) & (slopes <= MAX_SLOPE)):
            raise ValueError(f"slopes must be one or more prior exponents in (0, {MAX_SLOPE}], got {self.slopes!r}")
        if len(slopes) > 1 and not np.all(np.diff(slopes) > 0):
            raise ValueError(f"slopes must increase, got {self.slopes!r}")
        if len(slopes) > 2 and not np.allclose(np.diff(slopes), slopes[1] - slopes[0], rtol=1e-6, atol=1e-9):
            raise ValueError(f"slopes must be evenly spaced (a parabola refines the best one), got {self.slopes!r}")
        if self.theta_step_deg is not None and not (
                self.theta_step_deg > 0 and float(self.theta_step_deg / ZONE_STEP_DEG).is_integer()):
            raise ValueError(f"theta_step_deg must be a positive multiple of the zone step {ZONE_STEP_DEG}°, "
                             f"got {self.theta_step_deg}")
        if not 0.0 <= self.exact_model_below <= 1.0:
            raise ValueError(f"exact_model_below must lie in [0, 1] (a fraction of white), got {self.exact_model_below}")
        if not 0.0 <= self.weak_texture_below <= MAX_WEAK_TEXTURE_CONTRAST:
            raise ValueError(f"weak_texture_below must lie in [0, {MAX_WEAK_TEXTURE_CONTRAST:g}] (a texture contrast: "
                             f"RMS over mean), got {self.weak_texture_below}")
        if isinstance(self.clipped_planes_per_frame, bool) or not isinstance(self.clipped_planes_per_frame, int) \
                or self.clipped_planes_per_frame < 0:
            raise ValueError(f"clipped_planes_per_frame must be a whole number >= 0, got "
                             f"{self.clipped_planes_per_frame!r}")
        if not 0.0 <= self.clipped_ramp_samples <= MAX_CLIPPED_RAMP_SAMPLES:
            raise ValueError(f"clipped_ramp_samples must lie in [0, {MAX_CLIPPED_RAMP_SAMPLES}] (plane samples), got "
                             f"{self.clipped_ramp_samples}")
        if self.exponent_scope not in EXPONENT_SCOPES:
            raise ValueError(f"exponent_scope must be one of {EXPONENT_SCOPES}, got {self.exponent_scope!r}")
        if self.exponent_scope == "pooled" and not self.pool_sigma_px > 0:
            raise ValueError("exponent_scope 'pooled' profiles the exponent of the pooled curves: it needs pooling "
                             "(pool_sigma_px > 0, bmi infer's --pool-sigma-px)")
        if not 0.0 <= self.exponent_gate_nats <= MAX_EXPONENT_GATE_NATS:
            raise ValueError(f"exponent_gate_nats must lie in [0, {MAX_EXPONENT_GATE_NATS:g}] (nats), got "
                             f"{self.exponent_gate_nats}")
        if self.exponent_gate_nats > 0 and (self.exponent_scope != "pooled" or EXPONENT_PRIOR[0] not in self.slopes):
            raise ValueError(f"exponent_gate_nats gates the pooled exponent profile against the prior's α = "
                             f"{EXPONENT_PRIOR[0]:g}: it needs exponent_scope 'pooled' and {EXPONENT_PRIOR[0]:g} "
                             f"among the slopes, got {self.exponent_scope!r} and {self.slopes!r}")
        if self.window_model not in WINDOW_MODELS:
            raise ValueError(f"window_model must be one of {WINDOW_MODELS}, got {self.window_model!r}")
        if self.noise_model not in NOISE_MODELS:
            raise ValueError(f"noise_model must be one of {NOISE_MODELS}, got {self.noise_model!r}")
        if self.noise_sigma is not None and not 0 < self.noise_sigma <= NOISE_SIGMA_MAX:
            raise ValueError(f"noise_sigma must lie in (0, {NOISE_SIGMA_MAX}] (units of full scale), "
                             f"got {self.noise_sigma}")

    @property
    def exponent_per_pool(self) -> bool:
        """Whether each window's pooled curve has its texture exponent profiled (several slopes, ``exponent_scope``
        "pooled", pooling on): the decode then holds every slope's curves."""
        return self.exponent_scope == "pooled" and len(self.slopes) > 1 and self.pool_sigma_px > 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["slopes"] = list(self.slopes)
        return d


TEXTURE_EXPONENTS: dict[str, dict[str, Any]] = {
    "prior": {},
    "profiled": {"slopes": (1.6, 2.0, 2.4), "exact_model_below": 1.0, "exponent_scope": "pooled",
                 "exponent_gate_nats": 30.0},
}
"""What ``bmi infer --texture-exponent`` sets in a decoder's ``ClassicalConfig``. "prior": its own knobs (the texture's
power spectrum 1/f², the natural images' mean). "profiled": each pool's exponent α profiled over 1.6–2.4 where that
lowers its pooled NLL by more than 30 nats, on the exact model (the taper-smoothed model's approximations at the lowest
frequencies bias a profiled α); for scenes of large natural surfaces beyond about 3 m, whose exponents scatter about 2
(docs/decoder.md, "The texture's exponent")."""


def with_texture_exponent(config: ClassicalConfig, mode: str) -> ClassicalConfig:
    """``config`` with the knobs of ``TEXTURE_EXPONENTS[mode]`` (refused, naming the modes, for another ``mode``)."""
    if mode not in TEXTURE_EXPONENTS:
        raise ValueError(f"texture exponent {mode!r}: one of {', '.join(TEXTURE_EXPONENTS)}")
    return replace(config, **TEXTURE_EXPONENTS[mode])


UPSAMPLE_ROWS = 512
"""Rows of a frame taken from the window grid to pixels at a time (on the decoder's threads)."""


@dataclass
class DecodeResult:
    depth_m: np.ndarray            # H × W float32 range along each pixel's chief ray, NaN outside the image circle
    depth_sigma_m: np.ndarray      # H × W float32 1σ of depth_m, NaN outside
    aif: np.ndarray                # H × W × 3 float32 linear RGB (relative illumination undone), 0 outside
    valid: np.ndarray              # H × W bool
    grid_inv_depth: np.ndarray     # window grid 1/d (m⁻¹), NaN in skipped blocks
    grid_sigma_inv: np.ndarray     # window grid reported 1σ of 1/d (step 4)
    grid_sigma_laplace: np.ndarray  # window grid Laplace σ_L of 1/d
    grid_spread: np.ndarray        # window grid 3 × 3 spread of 1/d
    grid_evidence: np.ndarray      # window grid × coarse candidates: NLL − the window's minimum (NaN in skipped blocks)
    evidence_inv_depth_per_m: np.ndarray  # 1/d of the coarse candidates (the last axis of grid_evidence)
    stats: dict = field(default_factory=dict)
    # with pooling (``pool_sigma_px`` > 0): the cost volume over every candidate (``Candidates``), NaN in skipped blocks
    grid_curves: np.ndarray | None = None   # window grid × candidates: each window's own NLL − its minimum (nats)
    grid_pooled: np.ndarray | None = None   # window grid × candidates: the pooled curves (``pooling``)
    grid_colour: np.ndarray | None = None   # window grid × 3: log mean colour (``pooling.window_colour``)


class ClassicalDecoder:
    """Decode raw RGGB frames with the kernels of one ``PsfMap`` (nominal or calibrated camera)."""

    def __init__(self, psf_map, candidates: Candidates, config: ClassicalConfig = ClassicalConfig()):
        if psf_map.kernel_px > config.window_px:
            raise ValueError(f"{psf_map.kernel_px}-px kernels do not fit {config.window_px}-px windows")
        self.config = config
        self.candidates = candidates
        self.zones = ZoneKernels(psf_map, candidates, config.slopes, config.window_px)
        self.threads = config.threads or os.cpu_count() or 1
        # the tapered estimate scatters further than its likelihood's curvature says (``evidence``)
        self.laplace_inflation = np.sqrt(taper_variance_inflation(hann_taper(config.window_px // 2)))

    @classmethod
    def for_psf_map(cls, psf_map, config: ClassicalConfig = ClassicalConfig()) -> "ClassicalDecoder":
        """A decoder over ``psf_map``'s kernels at ``config.candidates`` depths spaced in 1/d on its depth grid."""
        return cls(psf_map, inverse_depth_candidates(psf_map.tensor.depth_m, config.candidates), config)

    def _block_threads(self, n_blocks: int) -> tuple[int, int]:
        """(block threads, FFT threads per block): a frame's blocks are read on ``threads`` threads at once, each
        block's transforms on one (a block's Python and numpy work between its transforms then no longer leaves a
        core idle); a window of one block runs its transforms on ``threads``."""
        workers = max(1, min(self.threads, n_blocks))
        return workers, (1 if workers > 1 else self.threads)

    # -- evidence ---------------------------------------------------------------------------------
    def _block_nll(self, spectra: list, models: np.ndarray, noise_vars: list, taper_energy: float,
                   clipped: list, grid_models: np.ndarray | None = None, low_cycles: int = 1) -> np.ndarray:
        """(slopes, windows, D) NLL summed over the planes at each prior slope (``evidence.profile_exponent`` profiles
        the slope out once every plane's evidence, clipped pairs' included, is in); ``models`` is
        ``ZoneKernels.models`` (planes, slopes, D, n, m), ``noise_vars`` each plane's per-window noise variance,
        ``clipped`` each plane's windows holding a sample at the white level: that plane gives them no evidence
        (a clipped plateau's sharp rim reads as a sharp kernel, confidently and wrongly). ``grid_models``: the
        models that place the β grid (``evidence.plane_nll``), default ``models``; ``low_cycles`` the cycles about DC the
        NLL skips (``evidence.rfft_multiplicity``)."""
        grid = models if grid_models is None else grid_models
        total: np.ndarray | None = None
        for p, power in enumerate(spectra):
            per_slope = np.stack([plane_nll(power, models[p, a], noise_vars[p], taper_energy, grid_model=grid[p, a],
                                            low_cycles_skipped=low_cycles)
                                  for a in range(models.shape[1])])
            per_slope[:, clipped[p]] = 0.0
            total = per_slope if total is None else total + per_slope
        if total is None:
            raise ValueError("_block_nll needs the spectra of at least one colour plane, got none")
        return total                                               # (slopes, windows, D)

    def _field_nll(self, spectra: list, reads: list, models: list, noise_vars: list, taper_energy: float,
                   clipped: list, grid_models: list | None = None, low_cycles: int = 1) -> np.ndarray:
        """(slopes, windows, D) NLL of a block's windows, each read with the zones ``ZoneKernels.field_reads`` gives it
        (``models`` one ``_block_nll`` model stack per read, ``grid_models`` the stacks that place each read's β
        grid): the weighted sum of the zones' NLLs, which is the NLL under the kernels interpolated to the
        window's θ to first order in the zones' spacing; ``low_cycles`` as ``_block_nll``'s."""
        grid_models = grid_models or [None] * len(reads)
        if len(reads) == 1:
            return self._block_nll(spectra, models[0], noise_vars, taper_energy, clipped, grid_models[0], low_cycles)
        total = np.zeros((models[0].shape[1], len(spectra[0]), models[0].shape[2]))
        for (_, idx, weight), zone_models, zone_grid in zip(reads, models, grid_models):
            pick = lambda planes: [p[idx] for p in planes]  # noqa: E731
            total[:, idx] += weight[:, None] * self._block_nll(pick(spectra), zone_models, pick(noise_vars),
                                                               taper_energy, pick(clipped), zone_grid, low_cycles)
        return total

    def decode(self, raw: np.ndarray, black_level_dn: float, white_level_dn: float, geometry: SensorGeometry,
               row0: int = 0, col0: int = 0, cfa: str = "RGGB", progress: bool = False,
               noise_profile: NoiseProfile | None = None, aif: bool = True) -> DecodeResult:
        """Decode an H × W RGGB window whose top-left pixel is (row0, col0) of the full sensor.

        ``noise_profile``: the frame's raw noise (``RawFrame.noise_profile``; ``frame_noise`` says when it is used).
        ``aif=False`` skips step 6's deconvolution (the result's ``aif`` is then zeros): for a caller that restores
        the AiF at another depth map (the evidence decoder) or needs the evidence alone (its training pairs).
        """
        cfg = self.config
        t_start = time.perf_counter()
        traced_before = self.zones.psf_map.kernels_traced
        models_before = self.zones.models_computed
        timings = dict.fromkeys(("planes_s", "evidence_s", "kernels_s", "pool_s", "fill_s", "upsample_s", "aif_s"),
                                0.0)
        height, width = raw.shape
        planes = normalised_planes(raw, black_level_dn, white_level_dn, row0, col0)
        noise, noise_source = frame_noise(cfg, planes, noise_profile)
        typical_sigma = float(np.sqrt(noise.variance(np.median(planes[:, ::8, ::8]))))  # reported only: a sample
        n = cfg.window_px // 2
        sp = cfg.stride_px // 2
        pad = n // 2
        def pad_planes(x):  # windows centred on the grid reach half a window (+ a stride) past the frame
            return np.stack([np.pad(p, ((pad, pad + sp), (pad, pad + sp)), mode="reflect") for p in x])

        padded = pad_planes(planes)
        clipped_mask = clipped_samples(planes)
        # most frames hold none: no padded mask then (a full frame's would be 54 MB)
        clipped_padded = pad_planes(clipped_mask) if clipped_mask.any() else None
        timings["planes_s"] = time.perf_counter() - t_start
        frame_valid = geometry.valid_mask(row0, col0, height, width)  # once: per block it cost ~10 % of a frame
        taper = hann_taper(n)
        taper_energy = float((taper ** 2).sum())
        grid_rows, grid_cols = window_grid_shape(cfg, height, width)
        chosen = weights_padded = None
        if clipped_padded is not None and cfg.clipped_planes_per_frame:
            weights_padded = np.stack([clipped_weights(c, cfg.clipped_ramp_samples) for c in clipped_padded])
            chosen = choose_clipped_planes(clipped_padded, weights_padded, n, sp, (grid_rows, grid_cols), taper,
                                           cfg.clipped_planes_per_frame)
        inv = np.full((grid_rows, grid_cols), np.nan)
        sig = np.full((grid_rows, grid_cols), np.nan)
        cand_inv = self.candidates.inv_depth_per_m
        n_cand = len(self.candidates)
        coarse = coarse_indices(n_cand, cfg.coarse_step)
        evidence = np.full((grid_rows, grid_cols, len(coarse)), np.nan, np.float32)
        blind = np.zeros((grid_rows, grid_cols), bool)  # windows clipped in every plane: no evidence of their own
        pooling = cfg.pool_sigma_px > 0
        if pooling:  # every window's whole curve and colour, for pooling once the grid is read
            curves = np.full((grid_rows, grid_cols, n_cand), np.nan, np.float32)
            colour = np.zeros((grid_rows, grid_cols, 3), np.float32)
        n_slopes = len(cfg.slopes)
        by_slope = cfg.exponent_per_pool
        if by_slope:  # and each slope's, less the window's least NLL over every slope and candidate
            slope_curves = np.full((grid_rows, grid_cols, n_slopes, n_cand), np.nan, np.float32)
        evaluations = {"full": 0, "done": 0}
        blocks = evidence_blocks(cfg, height, width)
        workers, fft_threads = self._block_threads(len(blocks))

        def read_block(block):
            """A block's reads (steps 2–4) and the seconds they took, or None for a block outside the image circle."""
            br, bc, nr, nc = block
            if not frame_valid[evidence_block_extent(cfg, block, height, width)].any():
                return None
            t0 = time.perf_counter()
            centre_row, centre_col = evidence_block_centre(cfg, block)
            zone = ZoneKernels.zone_at(geometry, row0 + centre_row, col0 + centre_col)
            reads = ZoneKernels.field_reads(geometry, row0 + (br + np.arange(nr)) * cfg.stride_px,
                                            col0 + (bc + np.arange(nc)) * cfg.stride_px, zone, cfg.theta_step_deg)
            window_reads = sum(len(idx) for _, idx, _ in reads)  # nr · nc, or more where windows blend zones
            ps = slice(br * sp, br * sp + (nr - 1) * sp + n), slice(bc * sp, bc * sp + (nc - 1) * sp + n)
            windows = [window_spectra(padded[p][ps], n, sp, taper, fft_threads) for p in range(4)]
            spectra = [w[0] for w in windows]
            noise_vars = [noise.variance(w[1]) for w in windows]
            clipped = ([windows_touching(clipped_padded[p][ps], n, sp) for p in range(4)] if clipped_padded is not None
                       else [np.zeros(nr * nc, bool)] * 4)
            kernels_s = 0.0
            block_chosen = None if chosen is None else chosen[:, br:br + nr, bc:bc + nc].reshape(4, -1)
            pairs = None
            if block_chosen is not None and block_chosen.any():
                def views(x):
                    return [np.lib.stride_tricks.sliding_window_view(x[p][ps], (n, n))[::sp, ::sp].reshape(-1, n, n)
                            for p in range(4)]

                pairs = ClippedPairs(views(padded), views(weights_padded), block_chosen, taper, self.zones.kernels,
                                     reads, cfg.slopes, noise)
            masked = np.zeros((4, nr * nc), bool) if pairs is None else pairs.scored
            # windows scored with the exact expected periodogram (dark ones, ``exact_model_below``) or the tapered
            # model, on every bin but DC's neighbours or, weakly textured (``weak_texture_below``), without the lowest
            # ring too; each group's β grid placed by its own windows and coarse models (one group without gates)
            groups = [(mask, exact, low, block_part(mask, spectra, noise_vars, clipped, reads))
                      for mask, exact, low in window_groups(windows, noise_vars, taper_energy, cfg) if mask.any()]
            coarse_nll = np.empty((n_slopes, nr * nc, len(coarse)))
            coarse_models = {}
            for mask, exact, low, (g_spectra, g_noise, g_clipped, g_reads) in groups:
                tm = time.perf_counter()
                coarse_models[exact, low] = [self.zones.models(z, coarse, exact) for z, _, _ in g_reads]
                kernels_s += time.perf_counter() - tm
                coarse_nll[:, mask] = self._field_nll(g_spectra, g_reads, coarse_models[exact, low], g_noise,
                                                      taper_energy, g_clipped, low_cycles=low)
            if pairs is not None:
                coarse_nll += pairs.nll(coarse)
            coarse_by_slope = coarse_nll
            coarse_nll = profile_exponent(coarse_nll, cfg.slopes)
            best = np.unique(coarse[np.argmin(coarse_nll, axis=1)])
            reach = np.arange(-cfg.coarse_step, cfg.coarse_step + 1)
            which = np.unique(np.clip(best[:, None] + reach[None, :], 0, n_cand - 1))
            # the fine pass scores only what the coarse pass has not, on the coarse pass's β grid, so that both
            # passes' NLLs are one curve (a grid placed by other candidates moves NLLs by tenths of a nat)
            fine = np.setdiff1d(which, coarse)
            nll = np.empty((nr * nc, len(which)))
            nll[:, np.isin(which, coarse)] = coarse_nll[:, np.isin(coarse, which)]
            nll_by_slope = np.empty((n_slopes, nr * nc, len(which)))
            nll_by_slope[:, :, np.isin(which, coarse)] = coarse_by_slope[:, :, np.isin(coarse, which)]
            if len(fine):
                fine_nll = np.empty((n_slopes, nr * nc, len(fine)))
                for mask, exact, low, (g_spectra, g_noise, g_clipped, g_reads) in groups:
                    tm = time.perf_counter()
                    models = [self.zones.models(z, fine, exact) for z, _, _ in g_reads]
                    kernels_s += time.perf_counter() - tm
                    fine_nll[:, mask] = self._field_nll(g_spectra, g_reads, models, g_noise, taper_energy, g_clipped,
                                                        coarse_models[exact, low], low)
                if pairs is not None:
                    fine_nll += pairs.nll(fine)
                nll_by_slope[:, :, np.isin(which, fine)] = fine_nll
                nll[:, np.isin(which, fine)] = profile_exponent(fine_nll, cfg.slopes)
            depth_b, sigma_b, _ = Evidence(nll.reshape(nr, nc, -1), cand_inv[which]).refine()
            return {"evidence": (coarse_nll - coarse_nll.min(axis=1, keepdims=True)).reshape(nr, nc, -1),
                    "clipped": int(np.logical_or.reduce(clipped).sum()), "masked": int(masked.any(axis=0).sum()),
                    "weak": sum(int(mask.sum()) for mask, _, low, _ in groups if low > 1),
                    "blind": np.logical_and.reduce([c & ~m for c, m in zip(clipped, masked)]).reshape(nr, nc),
                    "inv": 1.0 / depth_b, "sig": sigma_b * self.laplace_inflation,
                    "curves": (whole_curves(coarse, coarse_nll, which, nll, n_cand).reshape(nr, nc, -1)
                               if pooling else None),
                    "colour": window_colour([w[1] for w in windows]).reshape(nr, nc, 3) if pooling else None,
                    "slope_curves": (slope_whole_curves(coarse, coarse_by_slope, which, nll_by_slope, n_cand)
                                     .reshape(nr, nc, n_slopes, n_cand) if by_slope else None),
                    "full": window_reads * n_cand, "done": window_reads * (len(coarse) + len(fine)),
                    "evidence_s": time.perf_counter() - t0 - kernels_s, "kernels_s": kernels_s}

        skipped = windows_clipped = windows_masked = windows_weak = 0
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(blocks), unit="block", desc="evidence")
        for (br, bc, nr, nc), read in map_threads(read_block, blocks, workers, "evidence"):
            if bar is not None:
                bar.update()
            if read is None:
                skipped += 1
                continue
            cells = slice(br, br + nr), slice(bc, bc + nc)
            evidence[cells] = read["evidence"]
            windows_clipped += read["clipped"]
            windows_masked += read["masked"]
            windows_weak += read["weak"]
            blind[cells] = read["blind"]
            inv[cells] = read["inv"]
            sig[cells] = read["sig"]
            if pooling:
                curves[cells] = read["curves"]
                colour[cells] = read["colour"]
            if by_slope:
                slope_curves[cells] = read["slope_curves"]
            for key in ("full", "done"):
                evaluations[key] += read[key]
            for key in ("evidence_s", "kernels_s"):
                timings[key] += read[key]
        if bar is not None:
            bar.close()
        t0 = time.perf_counter()
        sigma_laplace = sig
        windows_profiled = int(np.isfinite(inv).sum()) if n_slopes > 1 else 0
        spread = local_spread(inv)  # the windows' own reads: how much they disagree is what the σ model was fitted on
        if pooling:
            pool = lambda c: pool_evidence(c, colour, cfg.pool_sigma_px / cfg.stride_px,  # noqa: E731
                                           cfg.pool_colour_sigma, cfg.pool_truncate_nats)
            if by_slope:  # one α per pool: each slope's curves pooled, then α profiled from the pooled NLLs
                pooled, profiled = gated_exponent(np.stack([pool(slope_curves[..., a, :]) for a in range(n_slopes)]),
                                                  cfg.slopes, cfg.exponent_gate_nats)
                windows_profiled = int((profiled & np.isfinite(inv)).sum())
                del slope_curves
            else:
                pooled = pool(curves)
            inv = np.where(np.isfinite(inv), 1.0 / Evidence(np.nan_to_num(pooled), cand_inv).refine()[0], np.nan)
        timings["pool_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        sig = np.sqrt((cfg.sigma_laplace_scale * sigma_laplace) ** 2 + (cfg.sigma_spread_scale * spread) ** 2
                      + cfg.sigma_floor_inv_per_m ** 2)
        inv, sig = fill_blind_windows(inv, sig, blind)
        inv, sig = confidence_fill(inv, sig, cfg.fill_windows)
        timings["fill_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        valid = frame_valid.copy()
        inv_px = np.empty((height, width), np.float32)
        depth = np.empty((height, width), np.float32)
        depth_sigma = np.empty((height, width), np.float32)

        def to_pixels(top: int) -> None:
            """Rows [top, top + UPSAMPLE_ROWS) of the per-pixel 1/d, validity, depth and its 1σ (step 6): any band of
            ``upsample_grid`` reads what the whole frame's interpolation reads there."""
            rows = slice(top, min(top + UPSAMPLE_ROWS, height))
            n_rows = rows.stop - top
            inv_px[rows] = upsample_grid(inv, cfg.stride_px, n_rows, width, top)
            sig_px = upsample_grid(sig, cfg.stride_px, n_rows, width, top)
            ok = valid[rows] & np.isfinite(inv_px[rows]) & (inv_px[rows] > 0)
            valid[rows] = ok
            depth[rows] = np.where(ok, 1.0 / np.where(ok, inv_px[rows], 1.0), np.nan)
            depth_sigma[rows] = np.where(ok, sig_px * depth[rows].astype(np.float64) ** 2, np.nan)

        for _ in map_threads(to_pixels, range(0, height, UPSAMPLE_ROWS), self.threads, "upsample"):
            pass
        timings["upsample_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        aif_rgb = (self._aif(raw, black_level_dn, white_level_dn, cfa, inv_px, valid, geometry, row0, col0, noise)
                   if aif else np.zeros((height, width, 3), np.float32))
        timings["aif_s"] = time.perf_counter() - t0
        timings["total_s"] = time.perf_counter() - t_start
        stats = {"decoder": "classical", "config": cfg.to_dict(), "noise_sigma": typical_sigma,
                 "noise_source": noise_source, "noise_profile": noise.to_dict(),
                 "candidates_depth_m": [round(float(d), 4) for d in self.candidates.depth_m],
                 "blocks_run": len(blocks) - skipped, "blocks_skipped": skipped,
                 "windows_with_clipped_samples": windows_clipped,
                 "windows_scored_without_clipped_samples": windows_masked,
                 "windows_without_evidence": int(blind.sum()),
                 "windows_exponent_profiled": windows_profiled,
                 "windows_weak_texture": windows_weak,  # scored without their lowest ring (``window_groups``)
                 "candidate_evaluations": evaluations["done"],
                 "candidate_evaluations_exhaustive": evaluations["full"],
                 "kernel_sets_computed": self.zones.kernel_sets_computed,
                 "models_computed": self.zones.models_computed - models_before,  # 0: all from memory or disk
                 "kernel_sets_traced": self.zones.psf_map.kernels_traced - traced_before,  # 0: all from cache
                 "timings_s": timings}
        volume = (curves, pooled, colour) if pooling else (None, None, None)
        return DecodeResult(depth, depth_sigma, aif_rgb, valid, inv, sig, sigma_laplace, spread, evidence,
                            cand_inv[coarse], stats, *volume)

    # -- all-in-focus -----------------------------------------------------------------------------
    def restore_aif(self, raw: np.ndarray, black_level_dn: float, white_level_dn: float, geometry: SensorGeometry,
                    depth_m: np.ndarray, prior_aif: np.ndarray | None, noise: NoiseProfile, row0: int = 0, col0: int = 0,
                    cfa: str = "RGGB", out: np.ndarray | None = None, aif_step: int | None = None) -> np.ndarray:
        """Another decoder's AiF (``prior_aif``, H × W × 3 linear RGB, relative illumination undone) made consistent
        with an H × W raw window through this decoder's kernels at ``depth_m`` (H × W, NaN where invalid): the
        Wiener step of ``aif`` with that AiF as the image model's mean, block by block (``aif.wiener_blend``).
        ``noise``: the frame's raw noise as the decoder used it (``DecodeResult.stats["noise_profile"]``).
        0 where ``depth_m`` is invalid. H × W × 3 float32, written into ``out`` when given (an array of that shape
        and type whose values are no longer needed, not ``prior_aif``: blocks read their neighbours' prior).
        ``aif_step``: blur and deconvolve on every n-th candidate (default: the config's ``aif_step``).
        ``prior_aif`` None: the plain Wiener AiF at ``depth_m`` (step 6 at another decoder's depth map)."""
        if prior_aif is not None and prior_aif.shape != raw.shape + (3,):
            raise ValueError(f"restore_aif needs an H × W × 3 prior AiF over the {raw.shape} raw window, got "
                             f"{prior_aif.shape}")
        if depth_m.shape != raw.shape:
            raise ValueError(f"restore_aif needs an H × W depth over the {raw.shape} raw window, got {depth_m.shape}")
        if out is not None and (out.shape != raw.shape + (3,) or out.dtype != np.float32 or out is prior_aif):
            raise ValueError("restore_aif writes into an H × W × 3 float32 array other than the prior AiF")
        valid = np.isfinite(depth_m) & (depth_m > 0)
        inv_px = np.full(depth_m.shape, np.nan, np.float32)  # in float32 throughout: a full frame's is 108 MB
        np.divide(np.float32(1.0), depth_m, out=inv_px, where=valid)
        return self._aif(raw, black_level_dn, white_level_dn, cfa, inv_px, valid, geometry, row0, col0, noise,
                         prior_aif, out, aif_step)

    def _aif(self, raw, black, white, cfa, inv_px, valid, geometry, row0, col0, noise: NoiseProfile,
             prior_aif: np.ndarray | None = None, out: np.ndarray | None = None,
             aif_step: int | None = None) -> np.ndarray:
        """The AiF of the frame's valid pixels at 1/d ``inv_px``: the Wiener estimate of each block (mean 0), or, with
        ``prior_aif`` (H × W × 3, relative illumination undone), that image pulled to the raw frame (``restore_aif``);
        into ``out`` when given; on every ``aif_step``-th candidate (default the config's)."""
        cfg = self.config
        height, width = raw.shape
        halo = self.zones.psf_map.kernel_px + 8
        halo += halo % 2
        if out is None:
            out = np.zeros((height, width, 3), np.float32)
        else:
            out[...] = 0.0
        n_cand = len(self.candidates)
        aif_cands = coarse_indices(n_cand, aif_step or cfg.aif_step)
        cand_inv = self.candidates.inv_depth_per_m[aif_cands]
        blocks = aif_blocks(cfg, height, width)
        workers, fft_threads = self._block_threads(len(blocks))

        def restore_block(block):
            """The AiF of one block's core (core h × w × 3), or None for a block outside the image circle."""
            r, r1, c, c1 = block
            core_valid = valid[r:r1, c:c1]
            if not core_valid.any():
                return None
            rows = reflect_indices(r - halo, fft_span_px(r1 - r, halo), height)
            cols = reflect_indices(c - halo, fft_span_px(c1 - c, halo), width)
            window = raw[np.ix_(rows, cols)]
            rgb = raw_to_rgb(window, black, white, window_cfa(cfa, row0 + r - halo, col0 + c - halo))
            centre_row, centre_col = aif_block_centre(cfg, block, height, width)
            zone = ZoneKernels.zone_at(geometry, row0 + centre_row, col0 + centre_col)
            median_inv = np.nanmedian(inv_px[r:r1, c:c1][core_valid])
            inv_core = np.where(core_valid, inv_px[r:r1, c:c1], median_inv)
            core = (slice(halo, halo + r1 - r), slice(halo, halo + c1 - c))
            signal = float(np.mean(rgb[core]))
            block_sigma = float(np.sqrt(noise.variance(signal) + (cfg.aif_model_error * signal) ** 2))
            prior = prior_inv = None
            if prior_aif is not None:  # the prior in the raw frame's units, over the whole window
                r_lo, c_lo = int(rows.min()), int(cols.min())
                window_falloff = relative_illumination(geometry, row0 + r_lo, col0 + c_lo, int(rows.max()) - r_lo + 1,
                                                       int(cols.max()) - c_lo + 1)[np.ix_(rows - r_lo, cols - c_lo)]
                prior = prior_aif[np.ix_(rows, cols)] * window_falloff[..., None]
                prior_inv = inv_px[np.ix_(rows, cols)]
                prior_inv = np.where(np.isfinite(prior_inv), prior_inv, median_inv)
            aif = wiener_blend(rgb, inv_core, cand_inv, lambda idx, z=zone: self.zones.kernels(z, aif_cands[idx]),
                               block_sigma, core, fft_threads, prior, prior_inv)
            falloff = relative_illumination(geometry, row0 + r, col0 + c, r1 - r, c1 - c)
            return np.where(core_valid[..., None] & (falloff[..., None] > 0),
                            aif / np.maximum(falloff, 1e-6)[..., None], 0.0)

        for (r, r1, c, c1), restored in map_threads(restore_block, blocks, workers, "aif"):
            if restored is not None:
                out[r:r1, c:c1] = restored
        return out

    def frame_zones(self, geometry: SensorGeometry, height: int, width: int, row0: int = 0,
                    col0: int = 0) -> dict[tuple[float, float], np.ndarray]:
        """{zone: candidate indices} whose kernels decoding an H × W window at (row0, col0) can ask for: every
        candidate at each evidence block's zone, the AiF's candidates at each AiF block's zone, for the blocks
        that reach into the image circle (what ``runtime.classical.warm_kernels`` traces ahead of a frame).
        Each window's own θ (``theta_step_deg``) reads further zones, which this does not list."""
        cfg = self.config
        frame_valid = geometry.valid_mask(row0, col0, height, width)
        wanted: dict[tuple[float, float], set] = {}
        every = range(len(self.candidates))
        for block in evidence_blocks(cfg, height, width):
            if frame_valid[evidence_block_extent(cfg, block, height, width)].any():
                centre_row, centre_col = evidence_block_centre(cfg, block)
                wanted.setdefault(ZoneKernels.zone_at(geometry, row0 + centre_row, col0 + centre_col),
                                  set()).update(every)
        aif_cands = coarse_indices(len(self.candidates), cfg.aif_step)
        for block in aif_blocks(cfg, height, width):
            r, r1, c, c1 = block
            if frame_valid[r:r1, c:c1].any():
                centre_row, centre_col = aif_block_centre(cfg, block, height, width)
                wanted.setdefault(ZoneKernels.zone_at(geometry, row0 + centre_row, col0 + centre_col),
                                  set()).update(aif_cands.tolist())
        return {zone: np.array(sorted(idx)) for zone, idx in sorted(wanted.items())}


def window_groups(windows: list, noise_vars: list, taper_energy: float, config: ClassicalConfig
                  ) -> list[tuple[np.ndarray, bool, int]]:
    """[(window mask, exact, low cycles)]: how each of a block's windows (``evidence.window_spectra`` of the four
    planes, with their noise variances) is scored.

    exact: with the exact expected periodogram (``evidence.expected_periodogram``) rather than the tapered model,
    where a window's mean signal, the mean of R, G (the two G planes' mean) and B as a fraction of white, is below
    ``config.exact_model_below`` (0: none is). Low cycles: the cycles about DC its NLL skips,
    ``evidence.WEAK_TEXTURE_LOW_CYCLES`` where its texture is weak and sharp (``evidence.texture_bands``: contrast
    below ``config.weak_texture_below``, 0: none is, and sharpness at least ``evidence.SHARP_TEXTURE_RATIO``), else 1.
    A weakly textured window's lowest frequencies hold, besides its own faint texture, whatever else lies in it (a
    brighter neighbour's defocused light, a surface's shading or edge); none of that follows the window's stationary
    model, and with the texture faint it outweighs the texture there. A strongly defocused window also shows little
    texture at 3–6 cycles, but its blur empties the band above as well, and there the lowest ring is the evidence of
    its depth: it keeps every bin (docs/decoder.md, step 2)."""
    r, g1, g2, b = (np.asarray(w[1], np.float64) for w in windows)
    dark = (r + 0.5 * (g1 + g2) + b) / 3.0 < config.exact_model_below
    weak = np.zeros_like(dark)
    if config.weak_texture_below > 0:
        contrast, sharpness = texture_bands([w[0] for w in windows], [w[1] for w in windows], noise_vars,
                                            taper_energy)
        weak = (contrast < config.weak_texture_below) & (sharpness >= SHARP_TEXTURE_RATIO)
    return [(~dark & ~weak, False, 1), (dark & ~weak, True, 1), (~dark & weak, False, WEAK_TEXTURE_LOW_CYCLES),
            (dark & weak, True, WEAK_TEXTURE_LOW_CYCLES)]


def block_part(mask: np.ndarray, spectra: list, noise_vars: list, clipped: list, reads: list
               ) -> tuple[list, list, list, list]:
    """(spectra, noise variances, clipped flags, zone reads) of a block's windows ``mask`` selects, the reads'
    window indices renumbered within the selection (``ZoneKernels.field_reads``); the block itself when it selects
    every window."""
    if mask.all():
        return spectra, noise_vars, clipped, reads
    pick = lambda planes: [np.asarray(p)[mask] for p in planes]  # noqa: E731
    position = np.cumsum(mask) - 1
    part_reads = [(zone, position[idx[mask[idx]]], weight[mask[idx]]) for zone, idx, weight in reads
                  if mask[idx].any()]
    return pick(spectra), pick(noise_vars), pick(clipped), part_reads


def window_grid_shape(config: ClassicalConfig, height: int, width: int) -> tuple[int, int]:
    """Rows and columns of an H × W frame's window grid (windows a stride apart, reaching past the last pixel)."""
    return -(-height // config.stride_px) + 1, -(-width // config.stride_px) + 1


def evidence_blocks(config: ClassicalConfig, height: int, width: int) -> list[tuple[int, int, int, int]]:
    """(first window row, first window column, window rows, window columns) of each block of an H × W frame's
    window grid: ``block_windows``² windows a stride apart, the first centred on pixel 0."""
    grid_rows, grid_cols = window_grid_shape(config, height, width)
    step = config.block_windows
    return [(br, bc, min(step, grid_rows - br), min(step, grid_cols - bc))
            for br in range(0, grid_rows, step) for bc in range(0, grid_cols, step)]


def evidence_block_extent(config: ClassicalConfig, block: tuple, height: int, width: int) -> tuple[slice, slice]:
    """The pixels an evidence block's windows cover, clipped to the H × W frame."""
    br, bc, nr, nc = block
    half = config.window_px // 2
    return (slice(max(br * config.stride_px - half, 0), min((br + nr - 1) * config.stride_px + half, height)),
            slice(max(bc * config.stride_px - half, 0), min((bc + nc - 1) * config.stride_px + half, width)))


def evidence_block_centre(config: ClassicalConfig, block: tuple) -> tuple[float, float]:
    """(row, col) frame pixel of an evidence block's centre: its zone's field position."""
    br, bc, nr, nc = block
    return (br + (nr - 1) / 2) * config.stride_px, (bc + (nc - 1) / 2) * config.stride_px


def aif_blocks(config: ClassicalConfig, height: int, width: int) -> list[tuple[int, int, int, int]]:
    """(r, r1, c, c1) of the AiF's blocks: squares of a window block's pixel size (``block_windows`` strides)."""
    size = config.block_windows * config.stride_px
    return [(r, min(r + size, height), c, min(c + size, width))
            for r in range(0, height, size) for c in range(0, width, size)]


def aif_block_centre(config: ClassicalConfig, block: tuple, height: int, width: int) -> tuple[float, float]:
    """(row, col) frame pixel of an AiF block's zone: the centre of the evidence block over the same pixels (the two
    grids share their origin and block size), so the AiF deconvolves with kernels the evidence pass traced for its
    zone (at the defaults ``aif_step`` = ``coarse_step``: the coarse pass's candidates) instead of tracing zones of its
    own on a camera's first frame. A whole block's is 7.5 px from its middle; the zone step is ~31 px."""
    r, _, c, _ = block
    grid_rows, grid_cols = window_grid_shape(config, height, width)
    br, bc = r // config.stride_px, c // config.stride_px
    return evidence_block_centre(config, (br, bc, min(config.block_windows, grid_rows - br),
                                          min(config.block_windows, grid_cols - bc)))


def fft_span_px(core_px: int, halo_px: int) -> int:
    """Rows (or columns) of a block's AiF window: its core, ``halo_px`` before it and at least as many after,
    grown to an even length the FFT factors well (a 256-px core with a 50-px halo is 356 = 4 × 89 px, whose
    transforms take 2.3× as long as 360's). More halo only adds mirrored context beyond the core."""
    span = sfft.next_fast_len(core_px + 2 * halo_px, real=True)
    while span % 2:  # whole Bayer quads
        span = sfft.next_fast_len(span + 1, real=True)
    return span


def coarse_indices(n_candidates: int, coarse_step: int) -> np.ndarray:
    """Indices of the coarse pass's candidates: every ``coarse_step``-th one and the last."""
    return np.unique(np.r_[np.arange(0, n_candidates, coarse_step), n_candidates - 1])


def whole_curves(coarse: np.ndarray, coarse_nll: np.ndarray, which: np.ndarray, nll: np.ndarray,
                 n_candidates: int, relative: bool = True) -> np.ndarray:
    """(windows, n_candidates) NLL less each window's minimum over every candidate (float32; ``relative`` False: the
    NLL itself, float64), from a block's two passes:
    the coarse pass's ``coarse_nll`` (windows, len(coarse)) and the fine pass's ``nll`` (windows, len(which)), one
    curve on one β grid; candidates neither pass scored are interpolated linearly between the scored ones (they lie
    away from every window's best, where the curve is smooth and pooling truncates it)."""
    scored = np.union1d(coarse, which)
    values = np.empty((len(nll), len(scored)))
    values[:, np.isin(scored, coarse)] = coarse_nll
    values[:, np.isin(scored, which)] = nll
    pos = np.interp(np.arange(n_candidates), scored, np.arange(len(scored)))
    lo = np.minimum(np.floor(pos).astype(int), len(scored) - 1)
    hi = np.minimum(lo + 1, len(scored) - 1)
    frac = pos - lo
    full = values[:, lo] * (1.0 - frac) + values[:, hi] * frac
    return (full - full.min(axis=1, keepdims=True)).astype(np.float32) if relative else full


def slope_whole_curves(coarse: np.ndarray, coarse_by_slope: np.ndarray, which: np.ndarray, nll_by_slope: np.ndarray,
                       n_candidates: int) -> np.ndarray:
    """(windows, slopes, n_candidates) float32 ``whole_curves`` of each slope's NLLs (slopes, windows, ·), less each
    window's least NLL over every slope and candidate, so that the slopes' curves stay comparable (``exponent_scope``
    "pooled")."""
    n_slopes, n_windows, _ = nll_by_slope.shape
    full = np.stack([whole_curves(coarse, coarse_by_slope[a], which, nll_by_slope[a], n_candidates, relative=False)
                     for a in range(n_slopes)], axis=1)
    return (full - full.min(axis=(1, 2), keepdims=True)).astype(np.float32)


def local_spread(inv: np.ndarray) -> np.ndarray:
    """Standard deviation of the finite 1/d values in each window's 3 × 3 neighbourhood (0 when alone)."""
    ok = np.isfinite(inv)
    x = np.where(ok, inv, 0.0)
    n = ndimage.uniform_filter(ok.astype(np.float64), 3, mode="nearest")
    safe = np.where(n > 0, n, 1.0)
    mean = ndimage.uniform_filter(x, 3, mode="nearest") / safe
    mean_sq = ndimage.uniform_filter(x * x, 3, mode="nearest") / safe
    return np.where(ok, np.sqrt(np.maximum(mean_sq - mean ** 2, 0.0)), np.nan)


def local_log_depth_variation(inv: np.ndarray) -> np.ndarray:
    """Spread (std) of log depth over each window's 3 × 3 neighbourhood of a window grid of 1/d (NaN where a
    window has no read): near 0 on a surface larger than the neighbourhood (±1 stride), large where windows
    straddle depth edges, as in tile-scale clutter. The learned decoder's fusion reads it (``fusion``)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return local_spread(np.log(np.where(inv > 0, inv, np.nan)))


def log_depth_variation_px(result: DecodeResult, stride_px: int, row0: int = 0,
                           height: int | None = None) -> np.ndarray:
    """``local_log_depth_variation`` of a decode's final window grid, interpolated (``upsample_grid``) to the
    pixels of its rows [row0, row0 + height) (default: all), every column; float32, NaN where no window reads."""
    rows, width = result.depth_m.shape
    height = rows - row0 if height is None else height
    return upsample_grid(local_log_depth_variation(result.grid_inv_depth), stride_px, height, width, row0, 0)


def confidence_fill(inv: np.ndarray, sig: np.ndarray, radius_windows: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-variance weighted Gaussian pooling of 1/d over the window grid (module doc, step 5).

    Each window's own estimate keeps its full weight 1/σ²; its neighbours enter with weight
    g · 1/σ² (g a Gaussian of ``radius_windows``, 0 at the centre), so the pooled value moves
    only where the window is unsure relative to its neighbours. The pooled σ is
    1 / sqrt(Σ weights), inflated by the spread of the pooled values (neighbours that
    disagree, e.g. across a depth edge, do not make a window more certain).
    """
    if radius_windows <= 0:
        return inv, sig
    ok = np.isfinite(inv) & np.isfinite(sig) & (sig > 0)
    w = np.where(ok, 1.0 / np.where(ok, sig, 1.0) ** 2, 0.0)
    x = np.where(ok, inv, 0.0)
    size = int(2 * np.ceil(2 * radius_windows) + 1)
    g = cv2.getGaussianKernel(size, radius_windows)
    g = g @ g.T
    g[size // 2, size // 2] = 0.0
    nb_w = ndimage.convolve(w, g, mode="nearest")
    nb_wx = ndimage.convolve(w * x, g, mode="nearest")
    nb_wxx = ndimage.convolve(w * x * x, g, mode="nearest")
    tot_w = w + nb_w
    safe = np.where(tot_w > 0, tot_w, 1.0)
    mean = (w * x + nb_wx) / safe
    spread = np.maximum((w * x * x + nb_wxx) / safe - mean ** 2, 0.0)
    pooled_sig = np.sqrt(1.0 / safe + spread)
    keep = tot_w > 0
    return np.where(keep, mean, np.nan), np.where(keep, np.minimum(pooled_sig, np.where(ok, sig, np.inf)), np.nan)


BLIND_FILL_WINDOWS = 2.0
"""Gaussian radius (windows) over which a window clipped in every plane borrows its neighbours' 1/d."""


def fill_blind_windows(inv: np.ndarray, sig: np.ndarray, blind: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1/d and σ of windows with no evidence (``blind``: clipped in every plane) pooled from their neighbours with
    evidence (``confidence_fill``: inverse-variance weights, σ inflated by the neighbours' disagreement). Blind
    windows beyond the pooling's reach keep their flat evidence's result: any depth, with a σ of ~10⁶."""
    if not blind.any():
        return inv, sig
    pooled, pooled_sig = confidence_fill(np.where(blind, np.nan, inv), np.where(blind, np.nan, sig),
                                         BLIND_FILL_WINDOWS)
    take = blind & np.isfinite(pooled)
    return np.where(take, pooled, inv), np.where(take, pooled_sig, sig)


def fill_grid(grid: np.ndarray) -> np.ndarray:
    """A window grid as float32 whose NaN samples (skipped blocks) take their nearest finite neighbour's value, so
    interpolation does not spread NaN into valid pixels next to the image-circle border. A float32 grid without
    NaN is returned as it is (``FeatureTiles`` fills its grids once and upsamples them per tile)."""
    g = np.asarray(grid, np.float32)
    bad = ~np.isfinite(g)
    if bad.any() and not bad.all():
        idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
        g = g[tuple(idx)]
    return g


def upsample_grid(grid: np.ndarray, stride_px: int, height: int, width: int, row0: int = 0,
                  col0: int = 0) -> np.ndarray:
    """Bilinear interpolation of a window grid (sample k at frame pixel k·stride − ½) to the H × W pixels whose
    top-left is frame pixel (row0, col0), after ``fill_grid``. Any part of a frame reads the values the whole
    frame's interpolation gives there (the sample positions are multiples of 1/32 px, exact in OpenCV's fixed
    point), which lets the learned decoder make its channels tile by tile (``features.FeatureTiles``)."""
    g = fill_grid(grid)
    if not np.isfinite(g).any():
        return np.full((height, width), np.nan, np.float32)
    scale = 1.0 / stride_px
    matrix = np.array([[scale, 0.0, (col0 + 0.5) * scale], [0.0, scale, (row0 + 0.5) * scale]], np.float32)
    return cv2.warpAffine(g, matrix, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)
