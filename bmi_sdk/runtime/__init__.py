"""Tiled ONNX inference: a raw frame in, all-in-focus RGB, range map, point cloud and report out.

    from bmi_sdk.runtime import Model, infer_frame, run_job
    model = Model("bmi_sdk/models/default.onnx", tile_px=512)   # SHA-256 checked against its manifest
    result = infer_frame(model, frame)                          # devices.RawFrame (camera or load_raw)
    run_job("frame.dng", "out/")                                # the `bmi infer` job: files + report.json

Design and the calibration hook: docs/runtime.md.
"""

from ..model_io import reflect_indices
from .export import export_model, measure_receptive_field
from .job import load_model_for, run_job
from .model import DEFAULT_MODEL, MODELS_DIR, Model, choose_providers, count_macs, select_model, session_options
from .outputs import depth_preview, write_frame_outputs, write_outputs, write_ply, write_report
from .pipeline import InferenceResult, check_frame, infer_frame, infer_raw
from .quantize import quantize_int8
from .tiling import TilePlan

__all__ = [
    "Model", "select_model", "session_options", "choose_providers", "count_macs", "DEFAULT_MODEL", "MODELS_DIR",
    "infer_frame", "infer_raw", "check_frame", "InferenceResult", "TilePlan", "reflect_indices",
    "write_outputs", "write_frame_outputs", "write_ply", "write_report", "depth_preview",
    "run_job", "load_model_for", "export_model", "measure_receptive_field", "quantize_int8",
]
