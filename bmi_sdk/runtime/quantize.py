"""int8 post-training quantisation of a verified model (onnxruntime static QDQ, per-channel weights).

Activation ranges are calibrated on real network inputs (tiles of a frame,
built by the same preprocessing as inference), so the int8 model is judged on
the data it will see. The result gets its own manifest: the fp32 manifest's
fields (its I/O contract included: a learned refinement stays one, with its
classical channels, σ output, classical_config and fusion weights) plus
``quantization`` and ``source_sha256`` (the fp32 model's hash).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..model_io import INPUT_NAME
from ..model_manifest import verify_model, write_manifest


def quantize_int8(src: str | os.PathLike, dst: str | os.PathLike, calibration_inputs: list[np.ndarray]) -> Path:
    """Write an int8 QDQ copy of ``src`` to ``dst`` (+ manifest), calibrated on ``calibration_inputs``
    (1 × C × H × W, C the model's ``input_channels``: the inputs inference builds for it)."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quant_pre_process,
        quantize_static,
    )

    if not calibration_inputs:
        raise ValueError("int8 calibration needs at least one input tile")
    manifest = verify_model(src)
    channels = int(manifest["input_channels"])
    shapes = sorted({tuple(np.shape(x)) for x in calibration_inputs
                     if np.ndim(x) != 4 or np.shape(x)[:2] != (1, channels)})
    if shapes:
        raise ValueError(f"{Path(src).name} reads 1 × {channels} × H × W inputs; calibration inputs of shape "
                         f"{shapes}")
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._it = iter(calibration_inputs)

        def get_next(self):
            x = next(self._it, None)
            return None if x is None else {INPUT_NAME: np.ascontiguousarray(x, np.float32)}

    pre = dst.with_name(f".{dst.stem}.pre.onnx")
    tmp = dst.with_name(f".{dst.name}.tmp.onnx")
    try:
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(tmp), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        weight_type=QuantType.QInt8, activation_type=QuantType.QUInt8)
        os.replace(tmp, dst)
    finally:
        for p in (pre, tmp):
            p.unlink(missing_ok=True)
    keep = {k: v for k, v in manifest.items() if k not in ("schema", "sha256", "file")}
    keep["output_names"] = tuple(keep["output_names"])
    write_manifest(dst, **{**keep, "preset": f"{manifest['preset']}-int8"},
                   quantization={"kind": "static QDQ int8", "weights": "per-channel QInt8", "activations": "QUInt8",
                                 "calibration_tiles": len(calibration_inputs)},
                   source_sha256=manifest["sha256"])
    return dst
