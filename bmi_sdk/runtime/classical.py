"""The runtime side of the classical decoder: a camera's frames in, depth + 1σ + AiF out.

``classical_decoder(camera)`` builds a ``decode.ClassicalDecoder`` over the built camera's own
kernels (``BuiltCamera.psf_map``: the nominal tensor, or the calibrated camera's exact kernels),
and ``decode_frame`` checks a ``devices.RawFrame`` against that camera and decodes it. Nothing
is trained, so a calibration reaches the decoder as soon as its file is read.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..built_camera import BuiltCamera
from ..decode import ClassicalConfig, ClassicalDecoder, DecodeResult
from .pipeline import check_decodable


@dataclass
class ClassicalResult:
    """A decoded frame (the fields ``write_outputs`` reads, plus the depth 1σ)."""

    aif: np.ndarray
    depth_m: np.ndarray
    depth_sigma_m: np.ndarray
    valid: np.ndarray
    stats: dict = field(default_factory=dict)
    decoded: DecodeResult | None = None  # the decoder's whole result (window grids, evidence)

    def summary(self) -> dict:
        skipped = self.stats["candidate_evaluations_exhaustive"] - self.stats["candidate_evaluations"]
        return {"decoder": "classical", "valid_fraction": float(self.valid.mean()),
                "blocks_run": self.stats["blocks_run"], "blocks_skipped": self.stats["blocks_skipped"],
                "candidate_evaluations_skipped": int(skipped),
                "decoder_stats": self.stats, "timings_s": self.stats["timings_s"]}


def classical_decoder(camera: BuiltCamera, config: ClassicalConfig = ClassicalConfig()) -> ClassicalDecoder:
    """A decoder over ``camera``'s kernels at ``config.candidates`` depths spaced in 1/d (a calibrated camera's exact
    kernels kept in the disk cache: its next frame or run reads them)."""
    return ClassicalDecoder.for_psf_map(camera.psf_map(disk_cache=True), config)


def decode_frame(decoder: ClassicalDecoder, frame, camera: BuiltCamera, progress: bool = False) -> ClassicalResult:
    """Decode a ``devices.RawFrame`` taken by ``camera`` (refused, naming why, when it cannot be)."""
    check_decodable(frame, camera.lens_name, "the decoder's camera has", "the classical decoder")
    out = decoder.decode(frame.data, frame.black_level_dn, frame.white_level_dn, frame.geometry,
                         row0=frame.roi.y_px, col0=frame.roi.x_px, cfa=frame.cfa, progress=progress,
                         noise_profile=frame.noise_profile)
    stats = dict(out.stats, camera_sha256=camera.sha256(), calibration_id=camera.calibration_id)
    return ClassicalResult(out.aif, out.depth_m, out.depth_sigma_m, out.valid, stats, out)
