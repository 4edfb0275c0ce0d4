"""One object for a built camera: its lens, its hardware errors and its sensor geometry, with a content hash.

Every consumer that needs the camera's kernels (the classical decoder, ``bmi simulate --perturb``,
the evaluation's perturbed conditions) asks this object for a ``render.PsfMap``, so no consumer can
drop an error on the way:

* no errors (the design): a ``tensor``-mode map over the lens's shared, disk-cached PSF tensor
  (the paper's rotated radial tensor; fast, and what the benchmark renders with), or ``exact``;
* with errors (a calibrated or simulated built camera): an ``exact``-mode map whose kernels are
  traced through the perturbed lens at every (θ, φ) (``optics.perturb``), each centred where the
  design's chief ray lands, so a kernel is displaced by exactly the built camera's landing error
  relative to the nominal pixel → field mapping the decoder and the point cloud use.

``sha256`` keys caches of anything derived from the camera (e.g. decoder kernels).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from .geometry import SensorGeometry
from .optics.perturb import Perturbation


@dataclass(frozen=True)
class BuiltCamera:
    """A camera as built: ``lens_name`` + ``perturbation`` (hardware errors) + ``geometry``."""

    lens_name: str = "bmi_monocentric"
    perturbation: Perturbation = field(default_factory=Perturbation)
    geometry: SensorGeometry | None = None
    calibration_id: str | None = None

    @property
    def is_nominal(self) -> bool:
        return not np.any(self.perturbation.to_vector())

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

    def psf_map(self, mode: str | None = None, centre_calibrated: bool = False):
        """The camera's ``PsfMap``: tensor mode for the design, exact mode (perturbed lens) otherwise.

        ``centre_calibrated``: take the on-axis landing shift out of every kernel (for images whose
        optical centre was moved to the nominal one, as ``bmi eval`` renders its perturbed rows).
        """
        from .lenses import lens_tensor
        from .render import PsfMap

        mode = mode or ("tensor" if self.is_nominal else "exact")
        perturbation = None if self.is_nominal else self.perturbation
        return PsfMap(lens_tensor(self.lens_name), self.sensor(), mode=mode, perturbation=perturbation,
                      centre_calibrated=centre_calibrated and perturbation is not None)

    @classmethod
    def from_calibration(cls, calibration, geometry: SensorGeometry | None = None) -> "BuiltCamera":
        """The camera a ``calibration.io.Calibration`` describes (its fitted errors, lens and id)."""
        lens = calibration.doc.get("lens", {}).get("name") or "bmi_monocentric"
        return cls(lens_name=lens, perturbation=calibration.perturbation, geometry=geometry,
                   calibration_id=calibration.id)
