"""Decoding raw frames: a raw frame in, all-in-focus RGB, range map (+ 1σ), point cloud and report out.

    from bmi_sdk.runtime import BuiltCamera, open_decoder, run_job
    decoder = open_decoder(BuiltCamera.for_frame(frame))       # DEFAULT_DECODER, built once for the camera
    decoded = decoder.decode(frame)                            # DecodedFrame: aif, depth_m, depth_sigma_m, valid
    run_job("frame.dng", "out/")                               # the `bmi infer` job: files + report.json

Design and the calibration hook: docs/runtime.md.
"""

from ..built_camera import BuiltCamera
from ..model_io import reflect_indices
from .decoders import DECODERS, DEFAULT_DECODER, DecodedFrame, Decoder, DecoderOptions, open_decoder
from .export import export_model, measure_receptive_field
from .job import run_job
from .model import DEFAULT_MODEL, MODELS_DIR, Model, choose_providers, count_macs, select_model, session_options
from .outputs import depth_preview, write_frame_outputs, write_outputs, write_ply, write_report
from .pipeline import InferenceResult, check_frame, infer_frame, infer_raw
from .quantize import quantize_int8
from .tiling import TilePlan

__all__ = [
    "BuiltCamera", "open_decoder", "Decoder", "DecodedFrame", "DecoderOptions", "DECODERS", "DEFAULT_DECODER",
    "Model", "select_model", "session_options", "choose_providers", "count_macs", "DEFAULT_MODEL", "MODELS_DIR",
    "infer_frame", "infer_raw", "check_frame", "InferenceResult", "TilePlan", "reflect_indices",
    "write_outputs", "write_frame_outputs", "write_ply", "write_report", "depth_preview",
    "run_job", "export_model", "measure_receptive_field", "quantize_int8",
]
