"""Model manifests: the SHA-256-checked identity card of a shipped ONNX model.

A model is one ``.onnx`` file with a ``<model>.manifest.json`` beside it
(``default.onnx`` → ``default.manifest.json``). The manifest says which bytes
are the model (``sha256``), how to call it (input/output names, channels,
size multiple, receptive field for tiling), and what optics it was trained
for: the lens, the PSF tensor's cache key and ``calibration_id`` (the
calibration whose PSF tensor it was trained on; ``None``, the nominal tensor,
for every model this SDK trains). ``decoder`` names the model's kind: ``cnn``
(the end-to-end network, the default when absent) or ``learned`` (the
refinement of the classical decoder). The runtime picks a model by its lens
and kind (``bmi_sdk.runtime.select_model``) and refuses any model whose bytes
do not match its manifest.

Schema ``bmi-model/1``; keys listed in ``REQUIRED_KEYS``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from .io_atomic import write_json
from .model_io import INPUT_CHANNELS, INPUT_NAME, OUTPUT_NAMES, SIGMA_OUTPUT_NAME, SIZE_MULTIPLE

SCHEMA = "bmi-model/1"
REQUIRED_KEYS = ("schema", "sha256", "file", "preset", "input_name", "output_names", "input_channels",
                 "size_multiple", "receptive_field_px", "lens", "psf_tensor_key", "calibration_id",
                 "training", "metrics")


class ModelError(ValueError):
    """A model file or its manifest is missing, corrupted, mismatched or of an unknown kind."""


def manifest_path(onnx_path: str | os.PathLike) -> Path:
    """``dir/name.onnx`` → ``dir/name.manifest.json``."""
    p = Path(onnx_path)
    return p.with_name(p.stem + ".manifest.json")


def file_sha256(path: str | os.PathLike, chunk_bytes: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            h.update(block)
    return h.hexdigest()


def write_manifest(onnx_path: str | os.PathLike, *, preset: str, receptive_field_px: int,
                   lens: str, psf_tensor_key: str | None, calibration_id: str | None = None,
                   training: dict | None = None, metrics: dict | None = None,
                   input_name: str = INPUT_NAME, output_names: tuple = OUTPUT_NAMES,
                   input_channels: int = INPUT_CHANNELS, size_multiple: int = SIZE_MULTIPLE,
                   **extra: Any) -> Path:
    """Hash ``onnx_path`` and write its manifest beside it (atomically); return the manifest path.

    ``receptive_field_px`` is the network's full receptive field in input pixels
    (the runtime's tile overlap is derived from it); ``lens`` the lens name;
    ``psf_tensor_key`` the cache key of the PSF tensor the training data was
    rendered with; ``calibration_id`` the calibration that tensor came from
    (``None``: nominal PSFs). ``training`` and ``metrics`` are free JSON dicts
    (config, data, validation errors). Extra keyword arguments are stored too.
    """
    onnx_path = Path(onnx_path)
    if not onnx_path.is_file():
        raise ModelError(f"no model file at {onnx_path}")
    if onnx_path.suffix != ".onnx":
        raise ModelError(f"model files end in .onnx, got {onnx_path.name}")
    if int(receptive_field_px) <= 0:
        raise ModelError(f"receptive_field_px must be > 0, got {receptive_field_px}")
    manifest = {
        "schema": SCHEMA, "sha256": file_sha256(onnx_path), "file": onnx_path.name, "preset": str(preset),
        "input_name": input_name, "output_names": list(output_names), "input_channels": int(input_channels),
        "size_multiple": int(size_multiple), "receptive_field_px": int(receptive_field_px),
        "lens": str(lens), "psf_tensor_key": psf_tensor_key, "calibration_id": calibration_id,
        "training": dict(training or {}), "metrics": dict(metrics or {}), **extra,
    }
    path = manifest_path(onnx_path)
    write_json(path, manifest)
    return path


def read_manifest(onnx_path: str | os.PathLike) -> dict:
    """The manifest of ``onnx_path``, schema- and key-checked but *not* hash-checked."""
    path = manifest_path(onnx_path)
    if not path.is_file():
        raise ModelError(f"unknown model {Path(onnx_path).name}: no manifest {path.name} beside it "
                         "(write one with bmi_sdk.model_manifest.write_manifest)")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelError(f"manifest {path} is not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict) or manifest.get("schema") != SCHEMA:
        got = manifest.get("schema") if isinstance(manifest, dict) else type(manifest).__name__
        raise ModelError(f"manifest {path} has schema {got!r}, expected {SCHEMA!r}")
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        raise ModelError(f"manifest {path} lacks {', '.join(missing)}")
    if manifest["file"] != Path(onnx_path).name:
        raise ModelError(f"manifest {path} describes {manifest['file']!r}, not {Path(onnx_path).name!r}")
    return manifest


def model_decoder(manifest: dict) -> str:
    """``cnn`` (the end-to-end network), ``learned`` (the refinement of the classical decoder) or ``evidence`` (the
    network over the classical evidence volume)."""
    return manifest.get("decoder", "cnn")


def _end_to_end_channels(manifest: dict) -> bool:
    return manifest["input_channels"] == INPUT_CHANNELS


def _refinement_channels(manifest: dict) -> bool:
    return isinstance(manifest["input_channels"], int) and manifest["input_channels"] > INPUT_CHANNELS \
        and isinstance(manifest.get("classical_config"), dict)


EVIDENCE_INPUT_NAME = "volume"
EVIDENCE_OUTPUT_NAMES = ("inv_depth", "sigma_inv", "logits")


EVIDENCE_SIGMA_SOURCES = ("network", "classical")
"""Where an evidence network's reported 1σ of each window's 1/d comes from (manifest ``sigma_source``, default
``network``): the network's ``sigma_inv`` output, or the classical stage's fitted σ model (``decode.classical``:
the own curve's curvature, the neighbouring windows' spread and a floor)."""


def _evidence_inputs(manifest: dict) -> bool:
    """An evidence network (``runtime.evidence``): the classical volume's 2 curves in, the candidates it was
    trained on, the classical knobs that made its volume and the colour scale of its upsampling."""
    cands = manifest.get("candidates_inv_depth_per_m")
    return manifest["input_channels"] == 2 and isinstance(cands, list) and len(cands) >= 3 \
        and isinstance(manifest.get("classical_config"), dict) \
        and isinstance(manifest.get("upsample_colour_sigma"), (int, float)) \
        and manifest.get("sigma_source", "network") in EVIDENCE_SIGMA_SOURCES


MODEL_CONTRACTS = {
    "cnn": (INPUT_NAME, [*OUTPUT_NAMES], _end_to_end_channels,
            f"{INPUT_NAME!r} × {INPUT_CHANNELS}, outputs {list(OUTPUT_NAMES)}"),
    "learned": (INPUT_NAME, [*OUTPUT_NAMES, SIGMA_OUTPUT_NAME], _refinement_channels,
                f"{INPUT_NAME!r} × ({INPUT_CHANNELS} + classical channels), a classical_config, outputs "
                f"{[*OUTPUT_NAMES, SIGMA_OUTPUT_NAME]}"),
    "evidence": (EVIDENCE_INPUT_NAME, [*EVIDENCE_OUTPUT_NAMES], _evidence_inputs,
                 f"{EVIDENCE_INPUT_NAME!r} × 2 curves over its candidates_inv_depth_per_m, a classical_config, an "
                 f"upsample_colour_sigma, a sigma_source of {list(EVIDENCE_SIGMA_SOURCES)} (default network), outputs "
                 f"{list(EVIDENCE_OUTPUT_NAMES)}"),
}
"""A manifest's ``decoder`` (the model's kind) → (its input's name, its outputs, the check of its inputs, the
contract in words)."""


def check_contract(manifest: dict, name: str) -> None:
    """Refuse a manifest whose I/O is not the contract of its kind (``MODEL_CONTRACTS``)."""
    decoder = model_decoder(manifest)
    if decoder not in MODEL_CONTRACTS:
        raise ModelError(f"model {name}: unknown decoder {decoder!r} in its manifest ({' or '.join(MODEL_CONTRACTS)})")
    input_name, outputs, channels_ok, expected = MODEL_CONTRACTS[decoder]
    if manifest["input_name"] != input_name or list(manifest["output_names"]) != outputs \
            or not channels_ok(manifest):
        raise ModelError(f"model {name} follows another I/O contract (input {manifest['input_name']!r}"
                         f" × {manifest['input_channels']}, outputs {manifest['output_names']}); this SDK expects "
                         f"{expected}")


def verify_model(onnx_path: str | os.PathLike) -> dict:
    """Check ``onnx_path`` against its manifest; return the manifest.

    Raises ``ModelError`` (a ``ValueError``) naming the problem: no model file,
    no manifest (unknown model), bad schema, manifest of another file, SHA-256
    mismatch (corrupted or replaced model), or an I/O contract other than
    ``bmi_sdk.model_io``'s.
    """
    onnx_path = Path(onnx_path)
    if not onnx_path.is_file():
        raise ModelError(f"no model file at {onnx_path}")
    manifest = read_manifest(onnx_path)
    digest = file_sha256(onnx_path)
    if digest != manifest["sha256"]:
        raise ModelError(f"model {onnx_path} does not match its manifest: SHA-256 {digest[:16]}… "
                         f"!= {str(manifest['sha256'])[:16]}… (corrupted or replaced file)")
    check_contract(manifest, onnx_path.name)
    if int(manifest["size_multiple"]) <= 0 or int(manifest["receptive_field_px"]) <= 0:
        raise ModelError(f"manifest of {onnx_path.name}: size_multiple and receptive_field_px must be > 0")
    return manifest
