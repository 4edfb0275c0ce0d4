"""One object for a built camera: its lens, its hardware errors and its sensor geometry, with a content hash.

Every consumer that needs the camera's kernels (the classical decoder, ``bmi simulate --perturb``,
the evaluation's perturbed conditions) asks this object for a ``render.PsfMap``, so no consumer can
drop an error on the way:

* by default an ``exact``-mode map: kernels traced at every zone's own (θ, φ), the pupil turned to
  the azimuth before the pixel grid samples it. A camera's kernels are never a pixel-sampled
  kernel rotated by interpolation: the ``tensor`` mode's bilinear rotation smooths a sharp far
  kernel, and decoding a camera's frames (the simulated device renders exact kernels, as a lens
  does) with those smoothed models reads a 6 m plane at 50° with AbsRel 0.25 instead of 0.08
  (``bmi bench decoder``, "Exact kernels against rotated tensor kernels");
* ``mode="tensor"``: the design's rotated radial tensor (the paper's PSF map; what the benchmark
  renders with, so its decoders read its frames with the same kernels);
* with errors (a calibrated or simulated built camera) the kernels are traced through the
  perturbed lens (``optics.perturb``), each centred where the design's chief ray lands, so a
  kernel is displaced by exactly the built camera's landing error relative to the nominal
  pixel → field mapping the decoder and the point cloud use;
* its PSF tensor (``psf_tensor``): the design's, or one built with the camera's errors.

``sha256`` keys caches of anything derived from the camera (e.g. decoder kernels).

The runtime builds one per camera and passes it down: ``for_frame(frame, calibration)`` is the camera that
took a frame (the frame's lens and sensor geometry, a loaded ``calibration.io.Calibration``'s fitted errors
and id), and every decoder (``runtime.decoders.open_decoder``) reads its kernels, its rays and its lens from it.
A calibration file is read once (``calibration.io.load_calibration``) and each frame's camera is built from the
loaded file; nothing below re-reads it.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass, field, fields

import numpy as np

from .geometry import SensorGeometry
from .lenses import DEFAULT_LENS
from .optics.perturb import Perturbation


@dataclass(frozen=True)
class BuiltCamera:
    """A camera as built: ``lens_name`` + ``perturbation`` (hardware errors) + ``geometry``; ``lens`` is the lens
    object itself. Its identity (``to_dict``, ``sha256``) is the lens's name, the errors, the geometry and the
    calibration id."""

    lens_name: str = DEFAULT_LENS
    perturbation: Perturbation = field(default_factory=Perturbation)
    geometry: SensorGeometry | None = None
    calibration_id: str | None = None

    @property
    def is_nominal(self) -> bool:
        return self.perturbation.is_design

    @property
    def lens(self):
        """The design lens (``optics.Lens``) this camera was built to; its errors are ``perturbation``."""
        from .optics import get_lens

        return get_lens(self.lens_name)

    def sensor(self) -> SensorGeometry:
        """The sensor geometry (the lens's default sensor unless one was given)."""
        if self.geometry is not None:
            return self.geometry
        from .lenses import lens_geometry

        return lens_geometry(self.lens_name)

    def to_dict(self) -> dict:
        return {"lens": self.lens_name, "perturbation": self.perturbation.to_dict(),
                "geometry": self.sensor().to_dict(), "calibration_id": self.calibration_id}

    def sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()

    def psf_tensor(self):
        """The camera's PSF tensor on its lens profile's grid: the design's shared tensor, or one built with the
        camera's errors (along φ = 0; disk-cached under a key that includes them)."""
        from .lenses import lens_tensor
        from .optics import PsfTensor

        nominal = lens_tensor(self.lens_name)
        return nominal if self.is_nominal else PsfTensor(nominal.lens, nominal.spec, perturbation=self.perturbation)

    def psf_map(self, mode: str | None = None, centre_calibrated: bool = False, disk_cache: bool = False):
        """The camera's ``PsfMap``: exact mode unless ``mode`` says otherwise (module doc).

        ``centre_calibrated``: take the on-axis landing shift out of every kernel (for images whose
        optical centre was moved to the nominal one, as ``bmi eval`` renders its perturbed rows).
        ``disk_cache``: keep exact kernels in the PSF cache (``optics.tensor.default_cache_dir``), so a
        calibrated camera's second frame (or run) reads its zone kernels instead of tracing them.
        """
        from .optics.tensor import default_cache_dir
        from .render import PsfMap

        mode = mode or "exact"
        return PsfMap(self.psf_tensor(), self.sensor(), mode=mode,
                      centre_calibrated=centre_calibrated and not self.is_nominal,
                      cache_dir=default_cache_dir() if disk_cache else None)

    def render_zone_px(self, mode: str | None = None) -> int:
        """The largest render zone (px) over which this camera's kernels (``psf_map(mode)``, optical centre
        calibrated) change no more than the design's over its default 512-px zone (``render.zone_size``): 512 for
        the design, finer for a camera whose kernels change faster with θ (a sensor-radius error)."""
        return _render_zone_px(self, mode or "exact")

    def ray_geometry(self) -> SensorGeometry:
        """``traced_ray_geometry`` of this camera (memoised: a batch of frames traces it once)."""
        return traced_ray_geometry(self)

    @classmethod
    def from_calibration(cls, calibration, geometry: SensorGeometry | None = None) -> "BuiltCamera":
        """The camera a loaded ``calibration.io.Calibration`` describes (its fitted errors, lens and id)."""
        lens = calibration.doc.get("lens", {}).get("name") or DEFAULT_LENS
        return cls(lens_name=lens, perturbation=calibration.perturbation, geometry=geometry,
                   calibration_id=calibration.id)

    @classmethod
    def for_frame(cls, frame, calibration=None) -> "BuiltCamera":
        """The camera that took ``frame`` (a ``devices.RawFrame``): its lens (the frame's ``lens.name``, else
        ``DEFAULT_LENS``) and sensor geometry, with a loaded ``calibration``'s fitted errors and id when given."""
        if calibration is not None:
            return cls.from_calibration(calibration, geometry=frame.geometry)
        lens = (getattr(frame, "lens", None) or {}).get("name") or DEFAULT_LENS
        return cls(lens_name=lens, geometry=frame.geometry)


@functools.lru_cache(maxsize=16)
def _render_zone_px(camera: BuiltCamera, mode: str) -> int:
    from .render import DEFAULT_ZONE_PX
    from .render.zone_size import zone_px_for

    if camera.is_nominal:
        return DEFAULT_ZONE_PX
    return zone_px_for(camera.psf_map(mode, centre_calibrated=True),
                       _design_kernel_change(camera.lens_name, camera.geometry, mode))


@functools.lru_cache(maxsize=8)
def _design_kernel_change(lens_name: str, geometry: SensorGeometry | None, mode: str) -> float:
    """The design's kernel change over its default zone (``render.zone_size.kernel_change``): the same for every
    built camera of one lens, so traced once (sampled-camera training asks for it per pair)."""
    from .render import DEFAULT_ZONE_PX
    from .render.zone_size import kernel_change

    return kernel_change(BuiltCamera(lens_name, geometry=geometry).psf_map(mode), DEFAULT_ZONE_PX)


@functools.lru_cache(maxsize=8)
def traced_ray_geometry(camera: BuiltCamera, field_step_deg: float = 0.5, azimuths: int = 48) -> SensorGeometry:
    """The sensor geometry of the camera's chief rays: which object direction (θ, φ) each pixel sees.

    What the point cloud and ``depth_z`` use. The design camera's is its sensor geometry. A camera
    with decenter, tilt, PSF shift or a sensor-radius error images the scene elsewhere: its chief
    rays (587.6 nm, infinity, like the design table) are traced through the built lens
    (``optics.perturb.chief_landing_px``) on a (θ, φ) grid of ``field_step_deg`` × ``azimuths``. The
    optical centre moves to where the axis lands, the radial table is the azimuth mean of the
    landing distances from it, the sensor radius is the built one, and what the symmetric mapping
    leaves (a decenter moves a spot by d⊥/R: its sagittal and meridional shifts differ by up to
    2 px at 55° for 10 µm) is a ``DisplacedGeometry`` table. Glare and PSF scale move no ray.
    """
    base = camera.sensor()
    p = camera.perturbation
    if not (np.any(p.psf_shift_px) or np.any(p.decenter_um) or np.any(p.tilt_arcmin)
            or p.sensor_radius_error_pct != 0.0):
        return base
    import math

    from .geometry import DisplacedGeometry
    from .optics import get_lens
    from .optics.perturb import chief_landing_px, perturbed_lens

    lens = get_lens(camera.lens_name)
    theta = np.arange(0.0, base.max_field_deg + field_step_deg / 2, field_step_deg)
    phi = np.arange(azimuths) * (360.0 / azimuths)
    theta_grid, phi_grid = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    land = chief_landing_px(lens, p, theta_grid, phi_grid, math.inf, 0.5876, base.centre_px, base.pitch_um)
    land = land + p.psf_shift_rc
    by_field = land.reshape(len(theta), len(phi), 2)
    centre = by_field[0].mean(axis=0)
    radial_mm = np.hypot(*(by_field - centre).transpose(2, 0, 1)).mean(axis=1) * base.pitch_um * 1e-3
    radius = perturbed_lens(lens, p).image.radius_mm
    symmetric = SensorGeometry(width_px=base.width_px, height_px=base.height_px, pitch_um=base.pitch_um,
                               radius_mm=None if math.isinf(radius) else abs(radius), cx_px=float(centre[1]),
                               cy_px=float(centre[0]), max_field_deg=base.max_field_deg,
                               field_table_deg=tuple(theta.tolist()), radial_table_mm=tuple(radial_mm.tolist()))
    row, col = symmetric.pixel_of_field(theta_grid, phi_grid)
    residual = np.stack([land[:, 0] - row, land[:, 1] - col], axis=-1)
    return DisplacedGeometry(**{f.name: getattr(symmetric, f.name) for f in fields(SensorGeometry)},
                             displacement_step_deg=field_step_deg, displacement_phi_count=azimuths,
                             displacement_px=tuple(residual.ravel().tolist()))

