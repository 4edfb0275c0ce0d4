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
from ..decode import ClassicalConfig, ClassicalDecoder, inverse_depth_candidates
from .pipeline import frame_lens_name


@dataclass
class ClassicalResult:
    """A decoded frame (the fields ``write_outputs`` reads, plus the depth 1σ)."""

    aif: np.ndarray
    depth_m: np.ndarray
    depth_sigma_m: np.ndarray
    valid: np.ndarray
    stats: dict = field(default_factory=dict)

    def summary(self) -> dict:
        skipped = self.stats["candidate_evaluations_exhaustive"] - self.stats["candidate_evaluations"]
        return {"decoder": "classical", "valid_fraction": float(self.valid.mean()),
                "blocks_run": self.stats["blocks_run"], "blocks_skipped": self.stats["blocks_skipped"],
                "candidate_evaluations_skipped": int(skipped),
                "decoder_stats": self.stats, "timings_s": self.stats["timings_s"]}


def classical_decoder(camera: BuiltCamera, config: ClassicalConfig = ClassicalConfig()) -> ClassicalDecoder:
    """A decoder over ``camera``'s kernels at ``config.candidates`` depths spaced in 1/d."""
    psf_map = camera.psf_map()
    candidates = inverse_depth_candidates(psf_map.tensor.depth_m, config.candidates)
    return ClassicalDecoder(psf_map, candidates, config)


def decode_frame(decoder: ClassicalDecoder, frame, camera: BuiltCamera, progress: bool = False) -> ClassicalResult:
    """Decode a ``devices.RawFrame`` taken by ``camera`` (refused, naming why, when it cannot be)."""
    if not getattr(frame, "is_bmi", True):
        reason = (frame.source or {}).get("foreign_raw_reason", "not a BMI frame")
        raise ValueError(f"this raw frame is not from a BMI camera ({reason}); the decoder needs BMI captures")
    frame.check()
    lens = frame_lens_name(frame)
    if lens is not None and lens != camera.lens_name:
        raise ValueError(f"frame was taken through lens {lens!r}; the decoder's camera has {camera.lens_name!r}")
    if frame.roi.x_px % 2 or frame.roi.y_px % 2:
        raise ValueError(f"ROI offset ({frame.roi.x_px}, {frame.roi.y_px}) is odd: not whole RGGB cells")
    if frame.cfa != "RGGB":
        raise ValueError(f"the decoder reads RGGB sensors, the frame says {frame.cfa!r}")
    out = decoder.decode(frame.data, frame.black_level_dn, frame.white_level_dn, frame.geometry,
                         row0=frame.roi.y_px, col0=frame.roi.x_px, cfa=frame.cfa, progress=progress)
    stats = dict(out.stats, camera_sha256=camera.sha256(), calibration_id=camera.calibration_id)
    return ClassicalResult(out.aif, out.depth_m, out.depth_sigma_m, out.valid, stats)
