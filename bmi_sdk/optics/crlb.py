"""Cramér–Rao lower bound on depth from the traced PSFs (paper §3.2).

Model. One colour channel c of a sensor patch of N × N pixels sees
g_c = T(θ) · (s ⊛ h_c(d)) + n, with s the (grey, depth-invariant) scene, h_c
the channel's unit-sum PSF kernel at range d, ⊛ the circular convolution over
the patch (the patch is treated as periodic, which is what makes the
frequency-domain sum below exact), T(θ) the throughput and n white Gaussian
noise of standard deviation σ, independent between pixels and channels. The
Fisher information on d is then

    I(d) = (1/σ²) Σ_c Σ_x (T ∂(s ⊛ h_c)/∂d)²
         = (1/σ²) (1/N²) Σ_c Σ_{u,v} |S(u,v)|² |T ∂OTF_c(u,v; d)/∂d|²      (Parseval, numpy's DFT)

and σ_d ≥ I(d)^{-1/2} (the CRLB of an unbiased estimator).

Conventions, each a parameter of :class:`CrlbSettings` (defaults in brackets):

- **Scene spectrum** [amplitude |S(f)| ∝ f^{-0.8}, i.e. power |S|² ∝ f^{-1.6}]:
  the paper says "a natural image spectrum proportional to 1/f^0.8" and
  writes |S|² in its Eq. (7); we read 1/f^0.8 as the amplitude spectrum
  (``spectrum_kind="power"`` reads it as |S|² ∝ f^{-0.8}). f is the radial
  frequency in cycles per pixel on the N × N DFT grid.
- **Normalisation** [N = 256 px, RMS contrast 0.2 about a mean of 0.5]:
  |S_k|² = N⁴ c_rms² w_k / Σ_{k≠0} w_k (w_k the spectrum shape), so that a
  patch with that spectrum has standard deviation c_rms (Parseval). The DC
  term is set to zero: it carries the mean, and a unit-sum kernel's DC
  response is 1 at every depth, so ∂OTF(0)/∂d = 0 and the mean carries no
  depth information anyway. With this normalisation I(d) ∝ N² c_rms² / σ²:
  the absolute bound scales as 1/(N c_rms / σ); all ratios between lenses,
  fields and depths are independent of N, c_rms and σ.
- **Noise** [σ = (1/255)/√12 ≈ 1.13·10⁻³]: the uniform quantisation noise
  of 8 bits on a [0, 1] signal (the paper: "a fixed Gaussian noise floor
  corresponding to quantization at 8 bits").
- **Throughput** [T(θ) = cos θ]: multiplies the complex OTF, so I ∝ T².
  The same law is applied to both lenses, as the paper does.
- **PSF** [unit energy per channel, kernel pixel-integrated on the 2 µm
  grid, centred on the chief ray]: kernels from :func:`fit_pupils` +
  :func:`psf_from_pupil`, one representative wavelength per channel
  (656.3 / 587.6 / 486.1 nm). The OTF is the N × N DFT of the kernel
  zero-padded to the patch. Centring on the chief ray removes any shift of
  the image point with depth (parallax of a non-monocentric lens), which an
  unknown scene could not reveal. Channels are summed (three independent
  measurements of the same grey scene).
- **Derivative** [central difference in inverse depth u = 1/d with step
  δ = 0.01 m⁻¹]: ∂h/∂d = −u² ∂h/∂u ≈ u² (h(1/(u−δ)) − h(1/(u+δ))) / (2δ).
  Defocus W020 is nearly linear in 1/d, so the kernels are smooth in u and
  one step serves every depth (a step of 1 % of d would shrink the kernel
  change to the float32 round-off of the PSF transform at far ranges).
  Beyond d = 1/(2δ) the step shrinks to u/2 so that the far point stays
  finite. At d = ∞, ∂h/∂d = −u² ∂h/∂u = 0 exactly: the bound is infinite.
  The step was chosen by the convergence check in docs/crlb.md.

A depth where the kernels do not change gives I = 0 and an infinite bound
(``math.inf``), never NaN.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from . import spectral
from .prescription import Lens
from .psf import DEFAULT_GUARD, DEFAULT_OVERSAMPLE, psf_from_pupil
from .pupil import fit_pupils

QUANTISATION_SIGMA_8BIT = (1.0 / 255.0) / math.sqrt(12.0)
MIN_ENERGY_CAPTURED = 0.99
# Beyond about 1 km the traced pupil fits lose precision (fit residual 0.013 waves at 1 km, 2.5 at
# 10 km), which would swamp the kernel change across the stencil; finite depths stop here (the far
# stencil point is then at most 200 m, fit residual < 10⁻³ waves). d = ∞ is exact and allowed.
MAX_FINITE_DEPTH_M = 100.0
SPECTRUM_KINDS = ("amplitude", "power")


def cos_throughput(field_deg):
    """T(θ) = cos θ: the paper's throughput of an oblique pupil under a fixed exposure."""
    return np.cos(np.radians(np.asarray(field_deg, dtype=np.float64)))


@dataclass(frozen=True)
class CrlbSettings:
    """Every convention of the bound (module doc); defaults are the paper's or ours where it is silent."""

    patch_px: int = 256
    spectrum_exponent: float = 0.8
    spectrum_kind: str = "amplitude"
    rms_contrast: float = 0.2
    noise_sigma: float = QUANTISATION_SIGMA_8BIT
    inverse_step_per_m: float = 0.01
    channels: tuple = field(default_factory=lambda: tuple(tuple(c) for c in spectral.representative()))
    pitch_um: float = 2.0
    oversample: int = DEFAULT_OVERSAMPLE
    guard: float = DEFAULT_GUARD

    def __post_init__(self):
        if self.patch_px < 2:
            raise ValueError(f"patch_px must be ≥ 2, got {self.patch_px}")
        if self.spectrum_kind not in SPECTRUM_KINDS:
            raise ValueError(f"spectrum_kind must be one of {SPECTRUM_KINDS}, got {self.spectrum_kind!r}")
        for name in ("rms_contrast", "noise_sigma", "inverse_step_per_m", "pitch_um"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not math.isfinite(self.spectrum_exponent):
            raise ValueError(f"spectrum_exponent must be finite, got {self.spectrum_exponent}")


def scene_power_spectrum(patch_px: int, spectrum_exponent: float = 0.8, spectrum_kind: str = "amplitude",
                         rms_contrast: float = 0.2) -> np.ndarray:
    """|S_k|² on the N × N DFT grid (numpy's unnormalised forward DFT), DC set to zero.

    Shape w = f^{-2α} (``amplitude``: |S| ∝ f^{-α}) or f^{-α} (``power``),
    scaled so that (1/N⁴) Σ_k |S_k|² = rms_contrast², i.e. a patch with this
    spectrum has that standard deviation (Parseval).
    """
    if spectrum_kind not in SPECTRUM_KINDS:
        raise ValueError(f"spectrum_kind must be one of {SPECTRUM_KINDS}, got {spectrum_kind!r}")
    freq = np.fft.fftfreq(patch_px)
    f = np.hypot(freq[:, None], freq[None, :])
    power_exponent = 2.0 * spectrum_exponent if spectrum_kind == "amplitude" else spectrum_exponent
    shape = np.zeros_like(f)
    shape[f > 0] = f[f > 0] ** (-power_exponent)
    return patch_px**4 * rms_contrast**2 * shape / shape.sum()


def fisher_information(dkernel_per_m: np.ndarray, scene_power: np.ndarray, noise_sigma: float,
                       throughput=1.0) -> np.ndarray:
    """I(d) in m⁻² from kernel depth derivatives (..., C, K, K) in m⁻¹, summed over channels C.

    ``scene_power`` is |S_k|² on the N × N patch grid (N ≥ K); the kernel
    derivative is zero-padded to N × N before its DFT. ``throughput`` (scalar
    or broadcastable to the leading axes) scales the complex OTF.
    """
    dk = np.asarray(dkernel_per_m, dtype=np.float64)
    n = scene_power.shape[0]
    if scene_power.shape != (n, n):
        raise ValueError(f"scene_power must be square, got {scene_power.shape}")
    if dk.ndim < 3 or dk.shape[-1] > n or dk.shape[-2] > n:
        raise ValueError(f"kernel derivatives (..., C, K, K) must fit the {n}×{n} patch, got {dk.shape}")
    if not np.all(np.isfinite(dk)):
        raise ValueError("kernel derivatives contain non-finite values")
    spectrum = np.fft.fft2(dk, s=(n, n))
    per_channel = np.einsum("...uv,uv->...", spectrum.real**2 + spectrum.imag**2, scene_power) / n**2
    t = np.asarray(throughput, dtype=np.float64)
    return t**2 * per_channel.sum(axis=-1) / noise_sigma**2


def crlb_from_fisher_mm(fisher_per_m2) -> np.ndarray:
    """σ_d = I^{-1/2} in mm; infinite where I = 0 (no information), never NaN."""
    fisher = np.asarray(fisher_per_m2, dtype=np.float64)
    if np.any(np.isnan(fisher)) or np.any(fisher < 0):
        raise ValueError("Fisher information must be ≥ 0 and not NaN")
    with np.errstate(divide="ignore"):
        return np.where(fisher > 0, 1e3 / np.sqrt(np.where(fisher > 0, fisher, 1.0)), math.inf)


def depth_stencil(depth_m, inverse_step_per_m: float):
    """Central difference in inverse depth: (near_m, far_m, scale_per_m) with ∂h/∂d ≈ (h(far) − h(near))·scale.

    u = 1/d, step δ' = min(δ, u/2); near = 1/(u + δ'), far = 1/(u − δ'),
    scale = u²/(2δ'). For d = ∞ the derivative is exactly zero: near = far =
    ∞ and scale = 0.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if np.any(~(depth > 0)):
        raise ValueError(f"depth_m must be > 0 (math.inf allowed), got {depth.min()}")
    if not (math.isfinite(inverse_step_per_m) and inverse_step_per_m > 0):
        raise ValueError(f"inverse_step_per_m must be finite and > 0, got {inverse_step_per_m}")
    u = 1.0 / depth
    step = np.minimum(inverse_step_per_m, u / 2)
    finite = u > 0
    with np.errstate(divide="ignore"):
        near = np.where(finite, 1.0 / (u + step), math.inf)
        far = np.where(finite, 1.0 / np.where(finite, u - step, 1.0), math.inf)
    scale = np.where(finite, u * u / (2 * np.where(finite, step, 1.0)), 0.0)
    return near, far, scale


@dataclass
class CrlbPoint:
    """The bound at one (lens, θ, d)."""

    lens: str
    field_deg: float
    depth_m: float
    crlb_mm: float
    fisher_per_m2: float
    fisher_share_by_channel: list  # fraction of I from each channel (R, G, B)
    kernel_px: int
    energy_captured_min: float  # smallest kernel energy fraction among the kernels used

    def to_dict(self) -> dict:
        out = asdict(self)
        for key in ("depth_m", "crlb_mm"):
            if math.isinf(out[key]):
                out[key] = None  # JSON has no infinity; None means ∞ here (documented in the CLI)
        return out


def kernel_derivatives(lens: Lens, field_deg, depth_m, kernel_px: int, settings: CrlbSettings | None = None):
    """∂h_c/∂d (n, C, K, K) in m⁻¹ for n (θ, d) pairs, and the smallest energy captured per pair.

    All (θ, d±, λ) entries go through one :func:`fit_pupils` call. Raises
    ValueError if a traced kernel is not finite (a pupil fit that failed).
    """
    settings = settings or CrlbSettings()
    field_deg, depth_m = (np.atleast_1d(np.asarray(x, dtype=np.float64)).ravel()
                          for x in np.broadcast_arrays(field_deg, depth_m))
    too_far = np.isfinite(depth_m) & (depth_m > MAX_FINITE_DEPTH_M)
    if np.any(too_far):
        raise ValueError(f"finite depths beyond {MAX_FINITE_DEPTH_M:g} m are refused (the traced pupil fits lose "
                         f"precision for far objects), got {depth_m[too_far].max():g} m; use math.inf for infinity")
    near, far, scale = depth_stencil(depth_m, settings.inverse_step_per_m)
    lam_nm = spectral.wavelengths_nm(settings.channels)
    todo = np.nonzero(scale > 0)[0]
    entries = [(i, side, lam) for i in todo for side in (0, 1) for lam in lam_nm]
    n_ch = len(settings.channels)
    dk = np.zeros((len(field_deg), n_ch, kernel_px, kernel_px))
    energy = np.ones(len(field_deg))
    if not entries:
        return dk, energy
    idx = np.array([i for i, _, _ in entries])
    sides = np.array([s for _, s, _ in entries])
    fits = fit_pupils(lens, field_deg[idx], np.where(sides == 0, near[idx], far[idx]),
                      np.array([lam for _, _, lam in entries]) * 1e-3)
    mono = {}
    for (i, side, lam), fit in zip(entries, fits):
        psf = psf_from_pupil(fit, kernel_px, settings.pitch_um, settings.oversample, settings.guard)
        if not (np.all(np.isfinite(psf.kernel)) and math.isfinite(psf.energy_captured)):
            raise ValueError(f"{lens.name}: the traced PSF at {field_deg[i]}°, "
                             f"{(near if side == 0 else far)[i]:.4g} m, {lam} nm is not finite "
                             "(its pupil fit failed; the field may be vignetted at this range)")
        mono[i, side, lam] = psf.kernel
        energy[i] = min(energy[i], psf.energy_captured)
    near_k, far_k = (spectral.channel_kernels({lam: np.stack([mono[i, side, lam] for i in todo]) for lam in lam_nm},
                                              settings.channels) for side in (0, 1))
    dk[todo] = np.swapaxes(far_k - near_k, 0, 1) * scale[todo, None, None, None]
    return dk, energy


def crlb(lens: Lens, field_deg, depth_m, kernel_px: int, settings: CrlbSettings | None = None,
         throughput=cos_throughput) -> list[CrlbPoint]:
    """The bound at every (θ, d) pair (arguments broadcast); see the module doc for the model.

    ``throughput`` maps field angles in degrees to T(θ) (cos θ by default).
    """
    settings = settings or CrlbSettings()
    if kernel_px > settings.patch_px:
        raise ValueError(f"kernel_px {kernel_px} exceeds the {settings.patch_px} px patch")
    field_deg, depth_m = (np.atleast_1d(np.asarray(x, dtype=np.float64)).ravel()
                          for x in np.broadcast_arrays(field_deg, depth_m))
    if np.any(~np.isfinite(field_deg)) or np.any(field_deg < 0) or np.any(field_deg >= 90):
        raise ValueError(f"field_deg must lie in [0, 90), got {field_deg.tolist()}")
    dk, energy = kernel_derivatives(lens, field_deg, depth_m, kernel_px, settings)
    power = scene_power_spectrum(settings.patch_px, settings.spectrum_exponent, settings.spectrum_kind,
                                 settings.rms_contrast)
    t = np.asarray(throughput(field_deg), dtype=np.float64)
    by_channel = np.stack([fisher_information(dk[:, c:c + 1], power, settings.noise_sigma, t)
                           for c in range(dk.shape[1])], axis=1)
    fisher = by_channel.sum(axis=1)
    bound = crlb_from_fisher_mm(fisher)
    share = np.divide(by_channel, fisher[:, None], out=np.zeros_like(by_channel), where=fisher[:, None] > 0)
    return [CrlbPoint(lens=lens.name, field_deg=float(field_deg[i]), depth_m=float(depth_m[i]),
                      crlb_mm=float(bound[i]), fisher_per_m2=float(fisher[i]),
                      fisher_share_by_channel=[float(x) for x in share[i]], kernel_px=int(kernel_px),
                      energy_captured_min=float(energy[i]))
            for i in range(len(field_deg))]
