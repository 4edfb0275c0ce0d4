"""PSF for any pixel: from the radial tensor (paper §3.3) or exactly.

Two modes:

* ``exact`` (default): the pupil is traced at the pixel's own field angle and
  the transform is turned to its azimuth (``psf_from_pupil(rotation_deg=φ)``),
  at the sensor's pitch. No interpolation, no resampling of kernels.
* ``tensor``: PSF_map(c, h, w, d) = P_resize ∘ P_rot( Σ_θ W(θ) PSF(c, θ, d) )
  from the radial tensor, as in the paper. Fast, but rotating a pixel-sampled
  kernel cannot be exact: at F/1.79 the PSF's spectrum reaches ~4× past the
  pixel Nyquist frequency, so every interpolator errs on sharp (far-depth)
  kernels (L1 0.2–0.6 at 10 m and infinity against the exact kernel;
  ``bmi bench render``).

A built lens that differs from its design (``optics.perturb.Perturbation``:
decenter, tilt, sensor radius, PSF shift/scale, glare) is an ``exact``-mode
option: each monochromatic kernel is ``perturb.spot_kernels`` of the perturbed
lens at (θ, φ, depth, λ), sampled on the K × K grid centred on the pixel where
the *design* lens's traced chief ray of that (θ, φ, depth, λ) lands (the
convention of ``perturb.perturbed_kernels``). The renderer maps pixels to
fields with the nominal geometry, so each PSF appears displaced by exactly
(perturbed − design) chief-ray landing, and a zero perturbation is the
nominal kernel. The design landing is traced per entry, not taken from
``SensorGeometry.pixel_of_field``: a geometry holds one table (587.6 nm,
infinity; up to 0.5 px of lateral colour away), or the ideal R·θ mapping
(up to 24 px away), neither of which is part of the perturbation.

A tensor built with a perturbation (``PsfTensor(perturbation=…)``, e.g. a
calibration's corrected tensor) carries it: ``exact`` mode over it traces
those errors at every (θ, φ), and ``tensor`` mode rotates its φ = 0 kernels
like any tensor kernel. Given a nominal tensor, ``tensor`` mode refuses a
perturbation: a rotationally symmetric tensor cannot hold decenter or tilt at
every azimuth.

Tensor-mode details:

* θ interpolation between the two bracketing tensor fields, either linear
  or with the paper's inverse-square weights W ∝ 1/Δθ² (compared in
  ``bmi bench render``).
* Rotation: tensor kernels have their radial axis along +col; a pixel at
  azimuth φ (measured from +col towards +row, image coordinates) needs that
  axis along (cos φ, sin φ). OpenCV's bilinear warp, renormalised: of
  bilinear, bicubic and Lanczos it errs least on sharp kernels (measured
  against exact rotated PSFs) and makes no negative lobes; it moves a
  point-like kernel's centroid by up to ~0.07 px. (Forward splatting keeps
  centroids exactly but leaves a moiré of ±25 % on smooth kernels.)
  Multiples of 90° are exact (np.rot90).
* Resampling when the sensor pitch differs from the tensor's (area
  interpolation, renormalised); identity for the nominal 2 µm sensor.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
import warnings
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from ..geometry import SensorGeometry
from ..optics import spectral
from ..optics.perturb import (
    Perturbation,
    chief_landing_px,
    landing_px,
    perturbed_lens,
    sensor_pose,
    spot_kernels,
)
from ..optics.psf import psf_from_pupil
from ..optics.pupil import PupilFit, chief_points, fit_pupils
from ..optics.tensor import PsfCacheWarning, PsfTensor, usable_kernel_shard, write_kernel_shard

INTERPOLATIONS = ("linear", "inverse_square")


def rotate_kernel(kernel: np.ndarray, phi_deg: float) -> np.ndarray:
    """Rotate a (K, K) kernel so its +col axis points along azimuth φ (image coordinates, y down)."""
    turns = phi_deg / 90.0
    if abs(turns - round(turns)) < 1e-9:
        # +col → +row is a clockwise quarter turn on screen: np.rot90 with k = -1.
        return np.ascontiguousarray(np.rot90(kernel, k=-int(round(turns)) % 4))
    size = kernel.shape[-1]
    centre = ((size - 1) / 2.0, (size - 1) / 2.0)
    # cv2's positive angle turns counter-clockwise on screen; +col must turn clockwise by φ.
    matrix = cv2.getRotationMatrix2D(centre, -phi_deg, 1.0)
    out = cv2.warpAffine(kernel.astype(np.float32), matrix, (size, size), flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    total = out.sum()
    return out / total if total > 0 else out


def resampled_size(size: int, scale: float) -> int:
    """Odd kernel size after resampling by ``scale``."""
    return size if abs(scale - 1.0) < 1e-12 else max(1, int(round(size * scale)) | 1)


def resample_kernel(kernel: np.ndarray, scale: float) -> np.ndarray:
    """Resample a kernel by ``scale`` (output pixels per input pixel inverse: >1 enlarges), odd size kept."""
    if abs(scale - 1.0) < 1e-12:
        return kernel
    new = resampled_size(kernel.shape[-1], scale)
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    out = np.maximum(cv2.resize(kernel.astype(np.float32), (new, new), interpolation=interp), 0.0)
    return out / out.sum()


MODES = ("exact", "tensor")
FIT_MEMO_ENTRIES = 12288
"""Design pupil fits and chief points a map keeps (``PsfMap._design_fits``; ≤ 4.6 kB each, ≤ 57 MB in all): a
full frame's rings need ~9300 fits (111 θ × 28 candidates × 3 wavelengths)."""


class PsfMap:
    """Kernels for arbitrary (θ, φ, depth index); depths are the tensor's grid (see module doc).

    ``perturbation`` (``exact`` mode only): the hardware errors of a built lens; ``None`` or all
    zero is the design, and its kernels are bit-identical to a map without one. A tensor
    built with errors carries them (``tensor.perturbation``); naming other errors is refused.
    ``cache_dir`` (``exact`` mode): keep the exact kernels on disk there, under ``exact_key`` (a full frame's
    ~7700 kernel sets take a minute or more of its first decode: ``bmi bench frame``, docs/benchmarks.md).
    ``centre_calibrated``: the camera's optical centre is known (as ``bmi calibrate``
    measures it), so the on-axis spot displacement of the perturbation, a shift of
    the whole image, is taken out of every kernel; what remains is the
    field-dependent displacement and the change of PSF shape.
    """

    def __init__(self, tensor: PsfTensor, geometry: SensorGeometry, interpolation: str = "linear",
                 mode: str = "exact", perturbation: Perturbation | None = None, centre_calibrated: bool = False,
                 cache_dir: str | os.PathLike | None = None):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {interpolation!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if perturbation is not None and perturbation.is_design:
            perturbation = None
        carried = tensor.perturbation
        if perturbation is not None and carried is not None and perturbation != carried:
            raise ValueError(f"the tensor was built with {carried}, not {perturbation}: one camera per map")
        if perturbation is not None and carried is None and mode != "exact":
            raise ValueError("a perturbation needs psf_mode='exact': the PSF tensor is rotationally symmetric "
                             "and cannot hold decenter or tilt at every azimuth")
        if mode == "exact" and not tensor.reproducible:
            raise ValueError(f"tensor {tensor.key} holds given kernels, which cannot be traced: use mode='tensor'")
        perturbation = perturbation or carried
        self.tensor = tensor
        self.geometry = geometry
        self.interpolation = interpolation
        self.mode = mode
        self.perturbation = perturbation
        self.centre_calibrated = centre_calibrated
        self.scale = tensor.spec.pitch_um / geometry.pitch_um
        self.field_deg = np.asarray(tensor.spec.field_deg, dtype=np.float64)
        self._exact: dict[tuple, np.ndarray] = {}
        # (chief only, θ, depth index, λ nm) → the design's pupil fit, or its chief point (``_design_fits``)
        self._fits: OrderedDict[tuple, PupilFit | np.ndarray] = OrderedDict()
        self._axis_shift: dict[tuple, np.ndarray] = {}  # (depth index, λ nm) → image shift (``_image_shift_px``)
        self._lock = threading.Lock()  # around the memos' bookkeeping (see ``kernel_sets``)
        self.exact_cache_dir = None if cache_dir is None or mode != "exact" else Path(cache_dir) / self.exact_key()
        self._zones_read: set[tuple] = set()
        self.disk_writable = True  # False once a shard write failed (a full or read-only disk): kernels stay in memory
        self.kernels_traced = 0  # exact (θ, φ, depth) kernel sets traced here, not read from memory or disk

    def __getstate__(self) -> dict:
        """Pickled (to scale-out workers) without its lock and the pupil-fit memo (cheap to rebuild, tens of MB)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_lock", "_fits")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _fits=OrderedDict(), _lock=threading.Lock())

    def exact_key(self) -> str:
        """Identity of this map's exact kernels: the tensor's (lens, errors, spec), the errors named here, the
        sensor geometry and the centre convention; names the disk cache of its zone kernels."""
        identity = {"shards": "sparse", "tensor": self.tensor.key, "geometry": self.geometry.to_dict(),
                    "perturbation": None if self.perturbation is None else self.perturbation.to_dict(),
                    "centre_calibrated": bool(self.centre_calibrated and self.perturbation is not None)}
        return "exact-" + hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:20]

    def _zone_path(self, key: tuple) -> Path:
        return self.exact_cache_dir / f"theta{key[0]:+010.5f}_phi{key[1]:+011.5f}.npz"

    def _read_zone(self, key: tuple) -> None:
        """Take a field position's cached exact kernels (once; a shard failing its checks is recomputed)."""
        with self._lock:
            if self.exact_cache_dir is None or key in self._zones_read:
                return
            self._zones_read.add(key)
        shape = (self.n_channels, len(self.tensor.spec.depth_m), self.kernel_px, self.kernel_px)
        shard = usable_kernel_shard(self._zone_path(key), shape, stacklevel=4, sparse=True)
        if shard is None:
            return
        psf, filled, _, depth_index = shard
        for n, j in enumerate(depth_index):
            if filled[:, n].all():
                # a copy: a view would keep the shard
                self._exact.setdefault(key + (int(j),), _frozen(psf[:, n].copy()))

    def _write_zone(self, key: tuple) -> None:
        """A sparse shard of the depths this field position holds (a full frame has ~430 zones, each needing ~20
        of the grid's depths: writing the whole grid would take 4× the disk). A cache it cannot write to (full or
        read-only disk) is named once in a ``PsfCacheWarning`` and not written again: the kernels stay in memory."""
        if not self.disk_writable:
            return
        held = sorted(j for j in range(len(self.tensor.spec.depth_m)) if key + (j,) in self._exact)
        psf = np.stack([self._exact[key + (j,)] for j in held], axis=1)
        path = self._zone_path(key)
        try:
            write_kernel_shard(path, psf, np.ones(psf.shape[:2], dtype=bool), np.asarray(held))
        except OSError as exc:
            self.disk_writable = False
            warnings.warn(f"cannot write the PSF cache at {path.parent} ({exc}); this camera's kernels stay in memory "
                          f"only", PsfCacheWarning, stacklevel=3)

    @property
    def n_channels(self) -> int:
        return len(self.tensor.spec.channels)

    @property
    def kernel_px(self) -> int:
        return resampled_size(self.tensor.spec.kernel_px, self.scale)

    def _exact_sets(self, theta_deg: float, phi_deg: float, depth_indices: np.ndarray) -> list[np.ndarray]:
        """[(C, K, K) per depth] traced at exactly (θ, φ) (through the perturbed lens if any), memoised per (θ, φ,
        depth) as read-only arrays and, with a ``cache_dir``, on disk: one shard per (θ, φ) holding the depths computed
        so far."""
        key = (round(float(theta_deg), 6), round(float(phi_deg), 6))
        self._read_zone(key)
        missing = [int(j) for j in depth_indices if key + (int(j),) not in self._exact]
        if missing:
            kernels = self._trace(theta_deg, phi_deg, missing)
            for n, dj in enumerate(missing):
                self._exact[key + (dj,)] = _frozen(kernels[:, n].copy())  # contiguous, and alone: no view keeps the rest
            with self._lock:
                self.kernels_traced += len(missing)
            if self.exact_cache_dir is not None:
                self._write_zone(key)
        return [self._exact[key + (int(j),)] for j in depth_indices]

    def _trace(self, theta_deg: float, phi_deg: float, depth_indices: list[int]) -> np.ndarray:
        """(C, len(depth_indices), K, K) float32 kernels traced at exactly (θ, φ), nothing memoised but pupil fits."""
        spec = self.tensor.spec
        lam_nm = spectral.wavelengths_nm(spec.channels)
        theta = float(np.clip(theta_deg, 0.0, self.field_deg[-1]))
        if self.perturbation is None:
            fits = self._design_fits(theta, depth_indices, lam_nm)
            flat = [psf_from_pupil(fit, self.kernel_px, self.geometry.pitch_um, spec.oversample, spec.guard,
                                   rotation_deg=float(phi_deg)).kernel for fit in fits]
        else:
            flat = self._perturbed_mono(theta, float(phi_deg), depth_indices, lam_nm)
        by_depth = np.asarray(flat).reshape(len(depth_indices), len(lam_nm), self.kernel_px, self.kernel_px)
        mono = {lam: by_depth[:, m] for m, lam in enumerate(lam_nm)}
        kernels = spectral.channel_kernels(mono, spec.channels, clip_negative=self.perturbation is not None)
        return kernels.astype(np.float32)

    def _design_fits(self, theta_deg: float, depth_indices: list[int], lam_nm, chief_only: bool = False) -> list:
        """Fitted pupils of the design lens at field θ, one per (depth, wavelength), depth-major; ``chief_only``:
        instead, the points where the design's chief rays meet the sensor (``pupil.chief_points``, (3,) mm each),
        which place a built lens's kernels (``_perturbed_mono``).

        The design is rotationally symmetric, so a pupil fit depends on θ alone and every zone on the same θ
        ring (a frame has ~4–6 zones per ring) turns the same fits (``psf_from_pupil(rotation_deg=φ)``) or lands
        the same chief rays. They are memoised, least recently used first out beyond ``FIT_MEMO_ENTRIES``, and the
        missing ones traced in one batch."""
        spec = self.tensor.spec
        keys = [(chief_only, round(float(theta_deg), 6), j, float(lam)) for j in depth_indices for lam in lam_nm]
        with self._lock:
            found = {key: self._fits[key] for key in keys if key in self._fits}
        missing = [key for key in keys if key not in found]
        if missing:  # traced outside the lock: another field position's trace goes on meanwhile
            depth_m = np.asarray(spec.depth_m)[[key[2] for key in missing]]
            wavelength_um = np.array([key[3] for key in missing]) * 1e-3
            if chief_only:
                fits = list(chief_points(self.tensor.lens, theta_deg, depth_m, wavelength_um))
            else:
                fits = fit_pupils(self.tensor.lens, theta_deg, depth_m, wavelength_um, grid=spec.fit_grid,
                                  degree=spec.fit_degree)
            found.update(zip(missing, fits))
        with self._lock:
            for key in keys:
                self._fits[key] = found[key]
                self._fits.move_to_end(key)
            while len(self._fits) > FIT_MEMO_ENTRIES:
                self._fits.popitem(last=False)
        return [found[key] for key in keys]

    def _perturbed_mono(self, theta_deg: float, phi_deg: float, depth_indices: list[int], lam_nm) -> np.ndarray:
        """(n, K, K) kernels of the perturbed lens at each (depth, wavelength), depth-major, each centred where the
        design's chief ray lands (module doc)."""
        spec, lens, pitch_um = self.tensor.spec, self.tensor.lens, self.geometry.pitch_um
        d_grid, l_grid = np.meshgrid(np.asarray(spec.depth_m)[depth_indices], lam_nm, indexing="ij")
        depth_m, wavelength_um = d_grid.ravel(), l_grid.ravel() * 1e-3
        theta = np.full(len(depth_m), theta_deg)
        centre_px = self.geometry.centre_px
        # The design's chief rays (one θ ring's, memoised), landed at φ as chief_landing_px lands them; the design's
        # sensor pose is the identity at every φ.
        design = Perturbation()
        chief = np.stack(self._design_fits(theta_deg, depth_indices, lam_nm, chief_only=True))
        phi = np.full(len(depth_m), phi_deg)
        design_px = landing_px(perturbed_lens(lens, design), *sensor_pose(design, phi), chief, phi, centre_px,
                               pitch_um)
        if self.centre_calibrated:
            design_px = design_px + self._image_shift_px(depth_indices, lam_nm)  # the image centre moves with the spot
        return spot_kernels(lens, self.perturbation, theta, phi_deg, depth_m, wavelength_um, design_px,
                            self.kernel_px, centre_px, pitch_um, spec.oversample, spec.guard, spec.fit_grid,
                            spec.fit_degree).kernels

    def _image_shift_px(self, depth_indices: list[int], lam_nm) -> np.ndarray:
        """(n, 2) (row, col) shift of the whole image per (depth, wavelength), depth-major: where the built lens's
        on-axis spot lands (``psf_shift_px`` included) less where the design's does. A calibrated optical centre
        takes it out of every kernel (``centre_calibrated``).

        An on-axis source is one point at every azimuth, so its landing is the same for every zone: it is traced
        once per (depth, wavelength) at φ = 0 and memoised."""
        keys = [(j, float(lam)) for j in depth_indices for lam in lam_nm]
        with self._lock:
            missing = sorted({key for key in keys if key not in self._axis_shift})
        if missing:
            spec, lens, pitch_um, centre_px = self.tensor.spec, self.tensor.lens, self.geometry.pitch_um, \
                self.geometry.centre_px
            depth_m = np.asarray(spec.depth_m)[[key[0] for key in missing]]
            wavelength_um = np.array([key[1] for key in missing]) * 1e-3
            axis = np.zeros(len(missing))
            axis_design = chief_landing_px(lens, Perturbation(), axis, 0.0, depth_m, wavelength_um, centre_px, pitch_um)
            axis_built = chief_landing_px(lens, self.perturbation, axis, 0.0, depth_m, wavelength_um, centre_px,
                                          pitch_um)
            with self._lock:
                self._axis_shift.update(zip(missing, axis_built + self.perturbation.psf_shift_rc - axis_design))
        return np.stack([self._axis_shift[key] for key in keys])

    def _bracket(self, theta_deg: float):
        """Tensor indices and weights for θ (clamped to the tensor's field range)."""
        grid = self.field_deg
        t = float(np.clip(theta_deg, grid[0], grid[-1]))
        i = int(np.clip(np.searchsorted(grid, t) - 1, 0, len(grid) - 2))
        lo, hi = grid[i], grid[i + 1]
        if t <= lo:
            return [i], [1.0]
        if t >= hi:
            return [i + 1], [1.0]
        if self.interpolation == "linear":
            f = (t - lo) / (hi - lo)
            return [i, i + 1], [1.0 - f, f]
        w_lo, w_hi = 1.0 / (t - lo) ** 2, 1.0 / (hi - t) ** 2
        return [i, i + 1], [w_lo / (w_lo + w_hi), w_hi / (w_lo + w_hi)]

    def ensure(self, theta_deg, depth_indices) -> None:
        """Make the tensor entries that these fields and depths need available (batched; tensor mode)."""
        if self.mode == "exact":
            return
        self.tensor.ensure(self.field_indices(theta_deg), depth_indices)

    def field_indices(self, theta_deg) -> list[int]:
        """The tensor's field indices whose kernels make the kernels at these θ (°): each θ's bracketing pair."""
        return sorted({i for t in np.atleast_1d(theta_deg) for i in self._bracket(float(t))[0]})

    def kernel_sets(self, theta_deg: float, phi_deg: float, depth_indices) -> list[np.ndarray]:
        """[(C, K, K) float32 unit-sum kernels per depth index] for one field position. In exact mode they are this
        map's own memoised arrays (read-only), so a caller that keeps them (``decode.ZoneKernels``) holds no second
        copy: a full frame's exact kernels are ~0.2 GB. Threads may ask for *different* field positions at once
        (each traces its own; the memos' bookkeeping is locked); the same position at once is the caller's to
        serialise (``decode.ZoneKernels`` locks per zone), or both threads trace it. Tensor mode serves one caller at
        a time."""
        depth_indices = np.atleast_1d(np.asarray(depth_indices, dtype=int))
        if self.mode == "exact":
            return self._exact_sets(theta_deg, phi_deg, depth_indices)
        with self._lock:  # the tensor fills its entries on first use, one caller at a time
            k = self.kernels(theta_deg, phi_deg, depth_indices)
        return [k[:, n] for n in range(k.shape[1])]

    def kernels(self, theta_deg: float, phi_deg: float, depth_indices) -> np.ndarray:
        """(C, n_depths, K, K) float32 unit-sum kernels for one field position (a new array)."""
        depth_indices = np.atleast_1d(np.asarray(depth_indices, dtype=int))
        if self.mode == "exact":
            return np.stack(self._exact_sets(theta_deg, phi_deg, depth_indices), axis=1)
        idx, w = self._bracket(theta_deg)
        self.tensor.ensure(idx, depth_indices)
        base = sum(wi * self.tensor.data[:, i][:, depth_indices] for i, wi in zip(idx, w))
        out = np.empty((base.shape[0], base.shape[1], self.kernel_px, self.kernel_px), dtype=np.float32)
        for c in range(base.shape[0]):
            for j in range(base.shape[1]):
                k = resample_kernel(base[c, j], self.scale)
                out[c, j] = rotate_kernel(k, phi_deg) if not math.isclose(phi_deg, 0.0, abs_tol=1e-12) else k / k.sum()
        return out


def _frozen(kernel: np.ndarray) -> np.ndarray:
    """``kernel`` made read-only: a memoised kernel is handed to callers as it is (``PsfMap.kernel_sets``)."""
    kernel.flags.writeable = False
    return kernel
