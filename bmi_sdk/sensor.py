"""The sensor model of the SDK: noise, relative illumination, Bayer mosaic, ADC.

One module, used by training (``add_gaussian_noise`` with the paper's σ values,
``adc_dn``) and by the simulated camera (``firmware_sim`` reads out frames
through ``SensorModel``); nothing else in the SDK re-implements these steps.

Two noise models, for two jobs:

* ``add_gaussian_noise``: the paper's training-time model, additive Gaussian
  noise of σ ∈ ``PAPER_NOISE_SIGMAS`` on linear [0, 1] signals.
* ``SensorModel``: a physical Poisson–Gaussian model for the simulated device.
  Irradiance in relative units [0, 1] at the sensor becomes a mean electron
  count ``irradiance × electrons_per_us × exposure_us``; photo-electrons are
  Poisson (shot noise) and clip at the full well; read noise is Gaussian in
  electrons; the ADC (``adc_dn``) multiplies by ``conversion_gain_dn_per_e ×
  analog_gain``, adds the black level, rounds and saturates at ``2**adc_bits − 1``.

So, for an unsaturated pixel with mean electron count μ, read noise σ_r and
total gain g = conversion_gain_dn_per_e × analog_gain (before rounding):
``E[DN] = black + g μ`` and ``Var[DN] = g² (μ + σ_r²)`` (+ 1/12 from rounding).

The RGGB mosaic keeps the phase of the *full sensor*: pixel (row, col) of the
full array sees R when both are even, B when both are odd, G otherwise, so a
window read out at an offset keeps its colours.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np

from bmi_sdk.geometry import SensorGeometry

PAPER_NOISE_SIGMAS = (0.0, 0.005, 0.01, 0.02, 0.05)
"""Additive Gaussian noise levels of the paper (on linear signals in [0, 1])."""

ADC_BITS = 12
"""Resolution of the simulated sensor's ADC."""
BLACK_LEVEL_DN = 256
"""Default black level: the offset the ADC adds so that dark noise below the mean is not clipped at 0."""
WHITE_LEVEL_DN = (1 << ADC_BITS) - 1
"""Saturation of the ADC at ``ADC_BITS`` (4095)."""

CFA_PATTERN = "RGGB"
# channel index (0 R, 1 G, 2 B) at (row % 2, col % 2) of the full sensor
_RGGB_CHANNEL = np.array([[0, 1], [1, 2]], dtype=np.intp)


def add_gaussian_noise(signal: np.ndarray, sigma: float, rng: np.random.Generator, clip: bool = True) -> np.ndarray:
    """The paper's noise: ``signal + N(0, σ²)`` per sample, float32, clipped to [0, 1] by default."""
    if not sigma >= 0:
        raise ValueError(f"noise sigma must be >= 0, got {sigma}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError("rng must be a numpy.random.Generator (randomness only through a passed generator)")
    x = np.asarray(signal, dtype=np.float32)
    out = x + rng.standard_normal(x.shape, dtype=np.float32) * np.float32(sigma) if sigma > 0 else x.copy()
    return np.clip(out, 0.0, 1.0, out=out) if clip else out


def adc_dn(signal: np.ndarray, dn_per_unit: float, black_level_dn: int, white_level_dn: int) -> np.ndarray:
    """The ADC: ``signal × dn_per_unit + black_level_dn`` rounded to the nearest DN (ties to even) and clipped
    to [0, white_level_dn], as uint16.

    float32 arithmetic throughout. The simulated camera feeds it electrons
    (``dn_per_unit`` = conversion gain × analog gain, ``SensorModel.adc``);
    training feeds it a [0, 1] signal that spans black to white
    (``dn_per_unit`` = white − black, ``nn.data.simulate_raw``).
    """
    if not 0 <= black_level_dn < white_level_dn:
        raise ValueError(f"black_level_dn must be in [0, {white_level_dn}), got {black_level_dn}")
    dn = np.asarray(signal, dtype=np.float32) * np.float32(dn_per_unit)
    dn += np.float32(black_level_dn)
    np.rint(dn, out=dn)
    np.clip(dn, 0, white_level_dn, out=dn)
    return dn.astype(np.uint16)


def bayer_mosaic(rgb: np.ndarray, row0: int = 0, col0: int = 0) -> np.ndarray:
    """H×W×3 → H×W: keep, at each pixel, the channel the RGGB filter passes there.

    ``row0, col0`` is the window's offset on the full sensor (the CFA phase).
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"bayer_mosaic needs an H×W×3 image, got shape {rgb.shape}")
    h, w, _ = rgb.shape
    out = np.empty((h, w), dtype=rgb.dtype)
    for dr in (0, 1):
        for dc in (0, 1):
            ch = _RGGB_CHANNEL[(row0 + dr) % 2, (col0 + dc) % 2]
            out[dr::2, dc::2] = rgb[dr::2, dc::2, ch]
    return out


def cfa_channel_map(height: int, width: int, row0: int = 0, col0: int = 0) -> np.ndarray:
    """H×W channel index (0 R, 1 G, 2 B) of an RGGB window at (row0, col0)."""
    rows = (np.arange(row0, row0 + height) % 2)[:, None]
    cols = (np.arange(col0, col0 + width) % 2)[None, :]
    return _RGGB_CHANNEL[rows, cols]


def relative_illumination(geometry: SensorGeometry, row0: int, col0: int, height: int, width: int,
                          step_px: float = 0.01) -> np.ndarray:
    """cos θ falloff of a monocentric lens (its pupil compresses by cos θ off axis), 0 outside the image circle.

    θ is the object-space field angle that ``geometry`` assigns to each pixel's
    radial distance. Since the falloff depends on that distance only, it is
    tabulated through ``geometry`` every ``step_px`` of radius and looked up
    (nearest entry: error ≤ ½ step × dθ/dr, about 1e-6 at the default), which
    makes a full frame ~10× cheaper than per-pixel trigonometry. The table reaches
    the sensor's farthest corner and is made once per geometry (``_falloff_table``):
    the classical decoder asks for a falloff per AiF block (432 on a full frame). H×W float32.
    """
    cy, cx = geometry.centre_px
    mm_per_px = geometry.pitch_um * 1e-3
    dy = ((np.arange(row0, row0 + height) - cy) * mm_per_px).astype(np.float32)[:, None]
    dx = ((np.arange(col0, col0 + width) - cx) * mm_per_px).astype(np.float32)[None, :]
    radial_mm = np.hypot(dy, dx)
    step_mm = step_px * mm_per_px
    corner_mm = float(np.hypot(max(cy, geometry.height_px - 1 - cy), max(cx, geometry.width_px - 1 - cx))) * mm_per_px
    table = _falloff_table(geometry, step_mm, max(corner_mm, float(radial_mm.max())))
    radial_mm *= np.float32(1 / step_mm)
    return table[np.rint(radial_mm).astype(np.intp)]


@functools.lru_cache(maxsize=8)
def _falloff_table(geometry: SensorGeometry, step_mm: float, reach_mm: float) -> np.ndarray:
    """cos θ (0 outside the image circle) at radii 0, step, 2·step, … past ``reach_mm`` (float32, read-only). The
    entries are start + k·step whatever the reach, so a table reaching further holds the same values."""
    table_mm = np.arange(0.0, reach_mm + 2 * step_mm, step_mm)
    theta_deg = geometry.field_deg_from_radial_mm(table_mm)
    inside = np.isfinite(theta_deg) & (theta_deg <= geometry.max_field_deg)
    table = np.where(inside, np.cos(np.radians(np.where(inside, theta_deg, 0.0))), 0.0).astype(np.float32)
    table.flags.writeable = False
    return table


@dataclass(frozen=True)
class NoiseProfile:
    """Raw noise as a function of signal: Var[x] = ``scale`` · x + ``offset`` for the normalised signal
    x = (DN − black) / (white − black) (the DNG ``NoiseProfile`` tag's convention, DNG 1.4 spec, tag 51041).

    ``scale`` carries the shot noise (Poisson: variance ∝ mean), ``offset`` the read noise, the ADC's
    rounding (1/12 DN²) and, for the paper's additive model, its σ². One pair for all colour planes
    (the simulated sensor applies one gain to every CFA colour).
    """

    scale: float
    offset: float

    def __post_init__(self):
        for name in ("scale", "offset"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"NoiseProfile.{name} must be finite and >= 0, got {value}")
        if self.scale == 0 and self.offset == 0:
            raise ValueError("NoiseProfile: scale and offset are both 0 (a noiseless raw frame has no profile)")

    @classmethod
    def additive(cls, sigma: float, white_level_dn: int = WHITE_LEVEL_DN,
                 black_level_dn: int = BLACK_LEVEL_DN) -> "NoiseProfile":
        """The paper's model as ``nn.data.simulate_raw`` applies it: N(0, σ²) on x, then rounding to whole DN."""
        span = float(white_level_dn - black_level_dn)
        return cls(0.0, float(sigma) ** 2 + 1.0 / (12.0 * span ** 2))

    def variance(self, signal) -> np.ndarray:
        """Noise variance at normalised signal ``signal`` (negative signals count as 0)."""
        return self.scale * np.maximum(np.asarray(signal, dtype=np.float64), 0.0) + self.offset

    def to_dict(self) -> dict:
        return {"scale": self.scale, "offset": self.offset}


@dataclass(frozen=True)
class SensorModel:
    """Photon-transfer parameters of the simulated BMI sensor (2 µm pixels, 12-bit ADC).

    ``electrons_per_us`` is the photo-electron rate of a pixel at irradiance 1.0
    (relative units, quantum efficiency included); with the defaults, irradiance
    1.0 fills the well in 10 ms. ``poisson_exact_below_e``: shot noise is drawn
    exactly from a Poisson law below this mean and from its Gaussian limit
    N(μ, μ) above it (skewness 1/√μ ≤ 0.1 there), which is ~6× faster on a
    full frame; both regimes have the analytic mean and variance.
    """

    full_well_e: float = 6000.0
    read_noise_e: float = 2.0
    conversion_gain_dn_per_e: float = 0.64
    electrons_per_us: float = 0.6
    adc_bits: int = ADC_BITS
    poisson_exact_below_e: float = 100.0
    additive_sigma: float | None = None  # the paper's model: N(0, σ²) on the [0, 1] signal instead of shot + read noise

    def __post_init__(self):
        for name in ("full_well_e", "conversion_gain_dn_per_e", "electrons_per_us"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SensorModel.{name} must be > 0, got {getattr(self, name)}")
        if not self.read_noise_e >= 0:
            raise ValueError(f"SensorModel.read_noise_e must be >= 0, got {self.read_noise_e}")
        if not 8 <= self.adc_bits <= 16:
            raise ValueError(f"SensorModel.adc_bits must be in 8..16, got {self.adc_bits}")
        if self.additive_sigma is not None and not self.additive_sigma >= 0:
            raise ValueError(f"SensorModel.additive_sigma must be >= 0, got {self.additive_sigma}")

    @property
    def white_level_dn(self) -> int:
        return (1 << self.adc_bits) - 1

    def to_dict(self) -> dict:
        return asdict(self)

    def noise_profile(self, analog_gain: float, exposure_us: float, black_level_dn: int) -> NoiseProfile:
        """The raw noise of a frame read out at ``analog_gain`` and ``exposure_us`` (module doc's photon transfer).

        With g = conversion gain × analog gain (DN per electron) and span W = white − black, an unsaturated
        pixel of mean μ electrons has x = g μ / W and Var[x] = (g² (μ + σ_r²) + 1/12) / W², so
        scale = g / W and offset = (g² σ_r² + 1/12) / W². The additive model (``additive_sigma``) adds
        σ · full-scale electrons instead of shot and read noise: scale 0.
        """
        if not analog_gain > 0:
            raise ValueError(f"analog_gain must be > 0, got {analog_gain}")
        if not exposure_us > 0:
            raise ValueError(f"exposure_us must be > 0, got {exposure_us}")
        span = float(self.white_level_dn - black_level_dn)
        if not span > 0:
            raise ValueError(f"black_level_dn must be below the white level {self.white_level_dn}, got {black_level_dn}")
        g = self.conversion_gain_dn_per_e * analog_gain
        if self.additive_sigma is not None:
            sigma_dn = self.additive_sigma * self.electrons_per_us * exposure_us * g
            return NoiseProfile.additive(sigma_dn / span, self.white_level_dn, black_level_dn)
        return NoiseProfile(g / span, ((g * self.read_noise_e) ** 2 + 1.0 / 12.0) / span ** 2)

    # -- the chain, step by step -------------------------------------------
    def mean_electrons(self, irradiance: np.ndarray, exposure_us: float) -> np.ndarray:
        """Mean photo-electrons per pixel for a linear irradiance (relative units) and exposure."""
        if not exposure_us > 0:
            raise ValueError(f"exposure_us must be > 0, got {exposure_us}")
        irr = np.asarray(irradiance, dtype=np.float32)
        return np.maximum(irr, 0.0) * np.float32(self.electrons_per_us * exposure_us)

    def electrons(self, mean_e: np.ndarray, rng: np.random.Generator, full_scale_e: float | None = None) -> np.ndarray:
        """Shot noise + full-well clip + read noise: float32 electrons (may be < 0 from read noise).

        With ``additive_sigma`` set, the paper's model instead: mean + σ·full_scale_e·N(0, 1),
        ``full_scale_e`` being the electrons of irradiance 1.0 at the exposure (the [0, 1] signal's 1).
        """
        mean_e = np.asarray(mean_e, dtype=np.float32)
        if self.additive_sigma is not None:
            scale = np.float32(self.additive_sigma * (full_scale_e or self.full_well_e))
            out = mean_e + scale * rng.standard_normal(mean_e.shape, dtype=np.float32) if scale > 0 else mean_e.copy()
            return np.minimum(out, np.float32(self.full_well_e), out=out)
        exact = mean_e < self.poisson_exact_below_e
        out = mean_e + np.sqrt(mean_e) * rng.standard_normal(mean_e.shape, dtype=np.float32)
        if exact.any():
            out[exact] = rng.poisson(mean_e[exact]).astype(np.float32)
        np.minimum(out, np.float32(self.full_well_e), out=out)
        if self.read_noise_e > 0:
            out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(self.read_noise_e)
        return out

    def adc(self, electrons: np.ndarray, analog_gain: float, black_level_dn: int) -> np.ndarray:
        """Electrons → uint16 DN through ``adc_dn`` at this sensor's conversion gain × ``analog_gain``."""
        if not analog_gain > 0:
            raise ValueError(f"analog_gain must be > 0, got {analog_gain}")
        return adc_dn(electrons, self.conversion_gain_dn_per_e * analog_gain, black_level_dn, self.white_level_dn)

    def expose_mosaic(self, mosaic_irradiance: np.ndarray, exposure_us: float, analog_gain: float,
                      black_level_dn: int, rng: np.random.Generator) -> np.ndarray:
        """H×W irradiance already filtered by the CFA → H×W uint16 raw DN (the whole chain)."""
        mean_e = self.mean_electrons(mosaic_irradiance, exposure_us)
        return self.adc(self.electrons(mean_e, rng, self.electrons_per_us * exposure_us), analog_gain, black_level_dn)
