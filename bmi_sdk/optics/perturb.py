"""A built lens that differs from its design: the hardware-error model and perturbed PSFs.

Six named errors (the paper's §4 list plus the sensor radius), each with its unit:

=========================  ======  ==============================================================
name                       unit    what it is
=========================  ======  ==============================================================
``psf_shift_px``  [x, y]   px      every PSF displaced from where the traced chief ray lands
                                   (x along +col, y along +row of the raw frame)
``psf_scale_pct``          %       PSF intensity I(r/s)/s², s = 1 + pct/100, about the chief ray,
                                   before the pixel box (a wavefront-scale error)
``decenter_um``   [x, y]   µm      the whole lens assembly displaced sideways relative to the
                                   sensor, in the sensor's (col, row) axes
``tilt_arcmin``   [x, y]   arcmin  the whole lens assembly turned about its centre (the stop),
                                   about the sensor's +col (x) and +row (y) axes, right-handed
                                   in the frame (col, row, light direction)
``stray_light_fraction``   1       diffuse veiling glare: PSF' = (1 − f)·PSF + f·G, G a
                                   pixel-integrated Gaussian of ``stray_light_spread_px`` (σ)
                                   centred on the chief ray
``sensor_radius_error_pct`` %      the sensor sphere's radius R(1 + pct/100) with its vertex
                                   (the on-axis point) where the design puts it
=========================  ======  ==============================================================

Decenter, tilt and sensor radius act *through the ray trace*: seen from the
lens, a decentred or tilted assembly is a displaced/rotated image surface
(``raytrace.ImagePose``), and a radius error is another image surface. They
change both where each spot lands (pixel positions are arc length on the
actual sensor sphere, ``landing_px``) and its focus across the field (the
sphere no longer follows the lens's curved focal surface). The image-plane
terms (shift, scale, glare) are operations on the exact kernel: the shift and
the scale move the exact transform's sample positions (``psf_from_pupil``'s
``offset_px`` and ``scale``), nothing is resampled.

Frames: the pupil code traces each object in the y–z plane (its
*meridional frame*), where a kernel's radial axis (+col of an unrotated
kernel) is lens −y and its sagittal axis (+row) lens +x. A spot at image
azimuth φ is that frame turned by φ; sensor-fixed vectors are turned by −φ
into it (``meridional_from_image``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from .prescription import Lens
from .psf import DEFAULT_GUARD, DEFAULT_OVERSAMPLE, psf_from_pupil
from .pupil import chief_points, fit_pupils
from .raytrace import ImagePose

PARAMETERS = ("psf_shift_px", "psf_scale_pct", "decenter_um", "tilt_arcmin", "stray_light_fraction",
              "sensor_radius_error_pct")
UNITS = {"psf_shift_px": "px", "psf_scale_pct": "%", "decenter_um": "um", "tilt_arcmin": "arcmin",
         "stray_light_fraction": "fraction of PSF energy", "sensor_radius_error_pct": "%"}
SIZES = {"psf_shift_px": 2, "psf_scale_pct": 1, "decenter_um": 2, "tilt_arcmin": 2, "stray_light_fraction": 1,
         "sensor_radius_error_pct": 1}
# The paper's ranges (§4 and its sensor-radius table): magnitudes for 2-D terms.
PAPER_RANGES = {"psf_shift_px": 0.5, "psf_scale_pct": 5.0, "decenter_um": 10.0, "tilt_arcmin": 1.0,
                "stray_light_fraction": 0.03, "sensor_radius_error_pct": 2.0}
DEFAULT_STRAY_SPREAD_PX = 8.0
VECTOR_NAMES = tuple(f"{n}[{i}]" if SIZES[n] == 2 else n for n in PARAMETERS for i in range(SIZES[n]))
"""Flat order of the nine numbers (``Perturbation.to_vector``)."""
ARCMIN_RAD = math.pi / (180.0 * 60.0)


@dataclass(frozen=True)
class Perturbation:
    """One set of hardware errors (see module doc); all zero is the design."""

    psf_shift_px: tuple = (0.0, 0.0)
    psf_scale_pct: float = 0.0
    decenter_um: tuple = (0.0, 0.0)
    tilt_arcmin: tuple = (0.0, 0.0)
    stray_light_fraction: float = 0.0
    sensor_radius_error_pct: float = 0.0
    stray_light_spread_px: float = DEFAULT_STRAY_SPREAD_PX

    def __post_init__(self):
        for name in PARAMETERS:
            v = np.atleast_1d(np.asarray(getattr(self, name), dtype=np.float64))
            if v.shape != (SIZES[name],) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} needs {SIZES[name]} finite number(s) in {UNITS[name]}, "
                                 f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(x) for x in v) if SIZES[name] == 2 else float(v[0]))
        if not -0.1 < self.stray_light_fraction < 1.0:
            # Physical glare is ≥ 0; a fitted value may fall below 0 by its noise and is kept (an honest estimate).
            raise ValueError(f"stray_light_fraction must lie in (-0.1, 1), got {self.stray_light_fraction}")
        if not self.psf_scale_pct > -50.0:
            raise ValueError(f"psf_scale_pct must be > -50 %, got {self.psf_scale_pct}")
        if not abs(self.sensor_radius_error_pct) < 50.0:
            raise ValueError(f"sensor_radius_error_pct must lie within ±50 %, got {self.sensor_radius_error_pct}")
        if not self.stray_light_spread_px > 0:
            raise ValueError(f"stray_light_spread_px must be > 0, got {self.stray_light_spread_px}")

    @property
    def is_design(self) -> bool:
        """No error at all (a glare spread without glare changes nothing): the lens as designed."""
        return not np.any(self.to_vector())

    @property
    def psf_shift_rc(self) -> np.ndarray:
        """(2,) ``psf_shift_px`` as a (row, col) offset in px, the order spot landings are held in."""
        return np.array([self.psf_shift_px[1], self.psf_shift_px[0]], dtype=np.float64)

    # -- conversions ----------------------------------------------------------
    def to_vector(self) -> np.ndarray:
        return np.concatenate([np.atleast_1d(getattr(self, n)) for n in PARAMETERS]).astype(np.float64)

    @classmethod
    def from_vector(cls, vector, stray_light_spread_px: float = DEFAULT_STRAY_SPREAD_PX) -> "Perturbation":
        v = np.asarray(vector, dtype=np.float64)
        if v.shape != (len(VECTOR_NAMES),):
            raise ValueError(f"a perturbation vector has {len(VECTOR_NAMES)} numbers {VECTOR_NAMES}, got {v.shape}")
        out, i = {}, 0
        for n in PARAMETERS:
            out[n] = tuple(v[i:i + 2]) if SIZES[n] == 2 else float(v[i])
            i += SIZES[n]
        return cls(**out, stray_light_spread_px=stray_light_spread_px)

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Perturbation":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown perturbation terms {sorted(unknown)}; known: {sorted(known)}")
        return cls(**d)

    def with_term(self, assignment: str) -> "Perturbation":
        """This perturbation with one ``name=value[,value]`` term set (the CLI's ``--simulate``)."""
        name, sep, text = assignment.partition("=")
        name = name.strip()
        if not sep or name not in PARAMETERS + ("stray_light_spread_px",):
            raise ValueError(f"expected NAME=VALUE with NAME one of {PARAMETERS}, got {assignment!r}")
        try:
            values = [float(x) for x in text.split(",")]
        except ValueError:
            raise ValueError(f"{name}: values must be numbers, got {text!r}") from None
        size = SIZES.get(name, 1)
        if len(values) != size:
            raise ValueError(f"{name} takes {size} value(s) in {UNITS.get(name, 'px')}, got {len(values)}")
        d = self.to_dict()
        d[name] = values if size == 2 else values[0]
        return Perturbation.from_dict(d)

    @classmethod
    def random(cls, rng: np.random.Generator, fraction: float = 1.0) -> "Perturbation":
        """Uniform within ``fraction`` × the paper's ranges (2-D terms uniform in the disc)."""
        def disc(r):
            rad, ang = r * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
            return (rad * math.cos(ang), rad * math.sin(ang))

        f = fraction
        return cls(psf_shift_px=disc(f * PAPER_RANGES["psf_shift_px"]),
                   psf_scale_pct=rng.uniform(-1, 1) * f * PAPER_RANGES["psf_scale_pct"],
                   decenter_um=disc(f * PAPER_RANGES["decenter_um"]),
                   tilt_arcmin=disc(f * PAPER_RANGES["tilt_arcmin"]),
                   stray_light_fraction=rng.uniform(0, 1) * f * PAPER_RANGES["stray_light_fraction"],
                   sensor_radius_error_pct=rng.uniform(-1, 1) * f * PAPER_RANGES["sensor_radius_error_pct"])


# -- frames -----------------------------------------------------------------
def _turn(v, phi_rad):
    """Turn 2-D vectors v (..., 2) by φ (broadcast against v[..., 0])."""
    c, s = np.cos(phi_rad), np.sin(phi_rad)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def meridional_from_image(vec_xy, phi_deg):
    """Sensor-plane vectors (col, row) → lens-frame transverse (x, y) of the entry at azimuth φ."""
    a = _turn(np.asarray(vec_xy, dtype=np.float64), -np.radians(np.asarray(phi_deg, dtype=np.float64)))
    return np.stack([a[..., 1], -a[..., 0]], axis=-1)


def image_from_meridional(vec_xy, phi_deg):
    """Inverse of :func:`meridional_from_image`: lens-frame (x, y) of the entry at φ → (col, row)."""
    v = np.asarray(vec_xy, dtype=np.float64)
    local = np.stack([-v[..., 1], v[..., 0]], axis=-1)  # (radial, sagittal) = (+col, +row) unrotated
    return _turn(local, np.radians(np.asarray(phi_deg, dtype=np.float64)))


def _rodrigues(r):
    """Rotation matrices exp([r]×) for rotation vectors r (..., 3)."""
    r = np.asarray(r, dtype=np.float64)
    angle = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    safe = np.where(angle > 0, angle, 1.0)
    a = np.where(angle > 0, np.sin(safe) / safe, 1.0)
    b = np.where(angle > 0, (1 - np.cos(safe)) / safe**2, 0.5)
    return np.eye(3) + a * k + b * (k @ k)


def perturbed_lens(lens: Lens, p: Perturbation) -> Lens:
    """The lens with the sensor radius error applied (vertex kept; R → R(1 + pct/100))."""
    if p.sensor_radius_error_pct == 0.0 or math.isinf(lens.image.radius_mm):
        return lens
    return lens.with_image_radius(lens.image.radius_mm * (1.0 + p.sensor_radius_error_pct / 100.0))


def sensor_pose(p: Perturbation, phi_deg) -> tuple[np.ndarray, np.ndarray]:
    """(offset_mm (n, 3), rotation (n, 3, 3)) of the image surface in each entry's meridional frame.

    Lens displaced by +d relative to the sensor ⇒ sensor displaced by −d seen
    from the lens; lens turned by +r ⇒ sensor turned by −r about the lens centre.
    """
    phi = np.atleast_1d(np.asarray(phi_deg, dtype=np.float64))
    d = meridional_from_image(np.broadcast_to(np.asarray(p.decenter_um) * 1e-3, phi.shape + (2,)), phi)
    offset = np.concatenate([-d, np.zeros(phi.shape + (1,))], axis=-1)
    r = meridional_from_image(np.broadcast_to(np.asarray(p.tilt_arcmin) * ARCMIN_RAD, phi.shape + (2,)), phi)
    rot = _rodrigues(-np.concatenate([r, np.zeros(phi.shape + (1,))], axis=-1))
    return offset, rot


def landing_px(lens: Lens, offset_mm, rotation, chief_point_mm, phi_deg, centre_px, pitch_um: float) -> np.ndarray:
    """(row, col) where chief points land on the (possibly displaced) sensor: arc length on its sphere / pitch.

    ``lens`` carries the sensor radius; ``centre_px`` (row, col) is the pixel on the sensor's vertex.
    """
    pose = ImagePose(np.asarray(offset_mm), np.asarray(rotation), lens.stop_z_mm)
    y = pose.to_nominal(np.asarray(chief_point_mm, dtype=np.float64))
    radius = lens.image.radius_mm
    z_img = lens.vertex_z_mm[-1]
    w_perp = np.hypot(y[..., 0], y[..., 1])
    if math.isinf(radius):
        factor = np.ones_like(w_perp)
    else:
        wz = (y[..., 2] - (z_img + radius)) * (-math.copysign(1.0, radius))  # along the centre→vertex direction
        alpha = np.arctan2(w_perp, wz)
        factor = np.where(w_perp > 1e-15, abs(radius) * alpha / np.where(w_perp > 1e-15, w_perp, 1.0), abs(radius) / wz)
    disp = image_from_meridional(factor[..., None] * y[..., :2], phi_deg) / (pitch_um * 1e-3)  # (col, row) px
    return np.stack([centre_px[0] + disp[..., 1], centre_px[1] + disp[..., 0]], axis=-1)


def glare_kernel(kernel_px: int, offset_px, spread_px: float) -> np.ndarray:
    """Unit-sum pixel-integrated Gaussian (σ = ``spread_px``) centred ``offset_px`` = (dx, dy) from the centre pixel."""
    from scipy.special import erf

    h = kernel_px // 2
    edges = np.arange(-h - 0.5, h + 1.0)

    def axis(c):
        cdf = 0.5 * (1 + erf((edges - c) / (math.sqrt(2) * spread_px)))
        return np.diff(cdf)

    g = np.outer(axis(-offset_px[1]), axis(-offset_px[0]))
    total = g.sum()
    return g / total if total > 0 else g


@dataclass
class SpotOptics:
    """Exact perturbed kernels of point sources and where their chief rays land."""

    kernels: np.ndarray  # (n, K, K) unit sum, on the pixel grid centred at ``centre_px``
    landing_px: np.ndarray  # (n, 2) (row, col): the traced chief ray + psf_shift_px
    chief_landing_px: np.ndarray  # (n, 2) the traced chief ray alone


def _spot_batch(field_deg, phi_deg, depth_m, wavelength_um):
    """(θ, φ, d, λ) of a batch of point sources as (n,) arrays, broadcast against θ."""
    theta = np.atleast_1d(np.asarray(field_deg, dtype=np.float64))
    n = len(theta)
    return theta, *(np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)) for x in (phi_deg, depth_m, wavelength_um))


def chief_landing_px(lens: Lens, p: Perturbation, field_deg, phi_deg, depth_m, wavelength_um, sensor_centre_px,
                     pitch_um: float = 2.0) -> np.ndarray:
    """(n, 2) (row, col) where the chief rays of point sources land through the perturbed lens: ``trace_spots``'
    landing (bit for bit) without its pupil fits, for callers that need only where spots land."""
    theta, phi, depth, lam = _spot_batch(field_deg, phi_deg, depth_m, wavelength_um)
    lens_p = perturbed_lens(lens, p)
    offset, rot = sensor_pose(p, phi)
    chief = chief_points(lens_p, theta, depth, lam, sensor_offset_mm=offset, sensor_rotation=rot)
    return landing_px(lens_p, offset, rot, chief, phi, sensor_centre_px, pitch_um)


def trace_spots(lens: Lens, p: Perturbation, field_deg, phi_deg, depth_m, wavelength_um, sensor_centre_px,
                pitch_um: float = 2.0, fit_grid: int = 20, fit_degree: int = 10):
    """Fitted pupils of point sources through the perturbed lens and their chief-ray landing (row, col) px."""
    theta, phi, depth, lam = _spot_batch(field_deg, phi_deg, depth_m, wavelength_um)
    lens_p = perturbed_lens(lens, p)
    offset, rot = sensor_pose(p, phi)
    fits = fit_pupils(lens_p, theta, depth, lam, grid=fit_grid, degree=fit_degree, sensor_offset_mm=offset,
                      sensor_rotation=rot)
    chief = np.stack([f.chief_point_mm for f in fits])
    return fits, landing_px(lens_p, offset, rot, chief, phi, sensor_centre_px, pitch_um), phi


def spot_kernels(lens: Lens, p: Perturbation, field_deg, phi_deg, depth_m, wavelength_um, centre_px,
                 kernel_px: int, sensor_centre_px, pitch_um: float = 2.0, oversample: int = DEFAULT_OVERSAMPLE,
                 guard: float = DEFAULT_GUARD, fit_grid: int = 20, fit_degree: int = 10,
                 stray_light: bool = True, sample_offset_px=None) -> SpotOptics:
    """Monochromatic kernels of point sources (θ, φ, d, λ) seen through the perturbed lens, exactly.

    Each kernel is sampled on the K × K pixel grid whose centre pixel is
    ``centre_px`` (n, 2) (row, col) of the sensor, so the spot sits where the
    perturbed lens puts it (sub-pixel included). ``sample_offset_px`` (n, 2)
    (dx, dy) instead fixes the grid relative to the chief point (the fit's
    shape derivatives at a fixed spot position). ``stray_light`` False leaves
    out the glare term (the fit adds it in its own model).
    """
    fits, chief_land, phi = trace_spots(lens, p, field_deg, phi_deg, depth_m, wavelength_um, sensor_centre_px,
                                        pitch_um, fit_grid, fit_degree)
    n = len(fits)
    land = chief_land + p.psf_shift_rc
    if sample_offset_px is None:
        centre = np.broadcast_to(np.asarray(centre_px, dtype=np.float64), (n, 2))
        sample = np.stack([centre[:, 1] - land[:, 1], centre[:, 0] - land[:, 0]], axis=-1)  # (dx, dy)
    else:
        sample = np.broadcast_to(np.asarray(sample_offset_px, dtype=np.float64), (n, 2))
    scale = 1.0 + p.psf_scale_pct / 100.0
    kernels = np.empty((n, kernel_px, kernel_px))
    for i, fit in enumerate(fits):
        quarter = float(phi[i]) / 90.0
        if quarter == round(quarter):
            # Azimuths on the pixel axes: the separable (fast) transform in the kernel's own frame, then an
            # exact quarter turn; the sample offset turns with it.
            q = int(round(quarter)) % 4
            local = _turn(sample[i], -math.radians(90.0 * q))
            k = psf_from_pupil(fit, kernel_px, pitch_um, oversample, guard,
                               offset_px=(float(local[0]), float(local[1])), scale=scale).kernel
            k = np.rot90(k, k=-q)
        else:
            k = psf_from_pupil(fit, kernel_px, pitch_um, oversample, guard, rotation_deg=float(phi[i]),
                               offset_px=(float(sample[i, 0]), float(sample[i, 1])), scale=scale).kernel
        if stray_light and p.stray_light_fraction != 0:
            k = (1 - p.stray_light_fraction) * k + p.stray_light_fraction * glare_kernel(
                kernel_px, sample[i], p.stray_light_spread_px)
        kernels[i] = k
    return SpotOptics(kernels, land, chief_land)


def perturbed_kernels(lens: Lens, spec, p: Perturbation, field_deg, depth_m) -> np.ndarray:
    """Kernels (C, n, K, K) float32 of the perturbed lens at n (θ, d) pairs on ``spec``'s grid, along φ = 0 (+col).

    What a ``PsfTensor`` built with ``perturbation=p`` holds. Each kernel is centred on the
    pixel where the *design* puts the chief ray of (θ, d, λ), so a renderer that maps pixels
    to fields with the nominal geometry gets the perturbed PSF where it really lands
    (sub-pixel offsets and the spot displacement of decenter, tilt and radius included, as
    long as they stay inside the kernel). Terms that break the lens's rotational symmetry
    (decenter, tilt, a shift) are exact on this meridian only; an exact-mode ``PsfMap``
    traces them at every azimuth. Both landings are traced from the same sensor centre, so
    the kernels do not depend on where the sensor's vertex pixel is.
    """
    from . import spectral

    theta = np.atleast_1d(np.asarray(field_deg, dtype=np.float64))
    depth = np.broadcast_to(np.asarray(depth_m, dtype=np.float64), theta.shape)
    origin_px = (0.0, 0.0)
    mono = {}
    for lam in spectral.wavelengths_nm(spec.channels):
        design_px = chief_landing_px(lens, Perturbation(), theta, 0.0, depth, lam * 1e-3, origin_px, spec.pitch_um)
        mono[lam] = spot_kernels(lens, p, theta, 0.0, depth, lam * 1e-3, design_px, spec.kernel_px, origin_px,
                                 spec.pitch_um, spec.oversample, spec.guard, spec.fit_grid, spec.fit_degree).kernels
    return spectral.channel_kernels(mono, spec.channels, clip_negative=True).astype(np.float32)
