"""Calibration files: JSON (schema ``bmi-calibration/1``) + the corrected PSF tensor + a PNG report.

``write_calibration(path, result, captures)`` writes, each atomically,

* ``path`` (.json): schema, ``calibration_id``, device (serial, firmware,
  lens), the nominal tensor's identity hash, the captures' hash, every
  parameter as ``{"value", "sigma", "unit", "free"}`` under ``parameters``,
  fit statistics, residuals per capture and on held-out captures, rejected
  spots with reasons, degeneracies with advice, ``injected`` (simulations);
* ``<stem>.psf.npz`` + ``<stem>.psf.json``: the corrected PSF tensor
  (a ``PsfTensor`` built with the fitted errors: meridian φ = 0, see ``perturb.perturbed_kernels``);
* ``<stem>.png``: measured vs fitted PSFs and the residual map over the field.

``calibration_id`` is the first 16 hex digits of the SHA-256 of the file's
content without the id itself, so it changes whenever anything in it does.
``load_calibration`` checks the schema, the parameter block, the id and the
tensor's hash.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from bmi_sdk import __version__
from bmi_sdk.io_atomic import write_json
from bmi_sdk.json_files import read_json_object
from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens
from bmi_sdk.optics.perturb import PARAMETERS, SIZES, UNITS, VECTOR_NAMES, Perturbation

from .targets import CalibrationError

SCHEMA = "bmi-calibration/1"
DEFAULT_TENSOR_FIELDS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0)
DEFAULT_TENSOR_DEPTHS_M = (0.7, 1.5, 3.0, 10.0)


def _content_id(doc: dict) -> str:
    body = {k: v for k, v in doc.items() if k != "calibration_id"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()[:16]


@dataclass
class Calibration:
    """A loaded, validated calibration file."""

    path: Path
    doc: dict

    @property
    def id(self) -> str:
        return self.doc["calibration_id"]

    @property
    def perturbation(self) -> Perturbation:
        """The fitted hardware errors (build exact kernels at any (θ, φ) with ``perturb.spot_kernels``)."""
        values = {n: self.doc["parameters"][n]["value"] for n in PARAMETERS}
        return Perturbation(**values, stray_light_spread_px=self.doc["stray_light_spread_px"])

    def tensor(self):
        """The corrected PSF tensor, carrying the fitted errors (``PsfTensor.load`` checks its own hash too).

        The tensor's JSON names the errors an exact-mode map over it traces, and the npz hash does not
        cover that JSON: a tensor whose errors are not this file's fitted ones is refused.
        """
        path = self.path.parent / self.doc["corrected_tensor"]["file"]
        tensor = PsfTensor.load(path)
        fitted = None if self.perturbation.is_design else self.perturbation
        if tensor.perturbation != fitted:
            raise CalibrationError(f"{path}: built with {tensor.perturbation}, but {self.path.name} fitted {fitted}")
        return tensor


def write_calibration(path, result, captures, extraction=None, lens_name: str = "bmi_monocentric",
                      tensor_fields_deg=DEFAULT_TENSOR_FIELDS_DEG, tensor_depths_m=DEFAULT_TENSOR_DEPTHS_M,
                      report: bool = True, method: str = "lm") -> Calibration:
    """Write the calibration file, its corrected tensor and report (see module doc); returns it loaded."""
    path = Path(path)
    if path.suffix != ".json":
        raise CalibrationError(f"a calibration file ends in .json, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    lens = get_lens(lens_name)
    spec = TensorSpec(field_deg=tuple(tensor_fields_deg), depth_m=tuple(tensor_depths_m),
                      kernel_px=captures.plan.kernel_px)
    tensor = PsfTensor(lens, spec, use_cache=False, perturbation=result.estimate)
    tensor.ensure(range(len(spec.field_deg)), range(len(spec.depth_m)))
    tensor_path = tensor.save(path.with_name(path.stem + ".psf.npz"))
    tensor_meta = json.loads(tensor_path.with_suffix(".json").read_text())
    corr = [[None if v != v else float(v) for v in row] for row in result.correlation]
    doc = {
        "schema": SCHEMA,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "code_version": __version__,
        "device": {k: captures.device.get(k) for k in ("model", "serial", "firmware_version")},
        "lens": {"name": lens.name, "sha256": lens.sha256()},
        "nominal_tensor": {"lens_sha256": lens.sha256(), "spec_key": spec.cache_key(lens),
                           "note": "identity of the design tensor on the corrected tensor's grid (lens + spec hash)"},
        "captures": {"sha256": captures.sha256(), "folder": None if captures.folder is None else str(captures.folder),
                     "target": captures.target.to_dict(), "plan": captures.plan.to_dict()},
        "parameters": result.parameters(),
        "stray_light_spread_px": result.estimate.stray_light_spread_px,
        "fit": {"method": method, "chi2_reduced": result.chi2_reduced, "n_pixels": result.n_pixels,
                "n_parameters": result.n_parameters, "outer_iterations": result.outer_iterations,
                "inner_iterations": result.inner_iterations, "seconds": result.seconds,
                "correlation": {"names": list(VECTOR_NAMES), "matrix": corr}},
        "residuals": {"per_capture": result.per_capture, "held_out": result.held_out},
        "rejected": [] if extraction is None else [{"source": i, "reason": r} for i, r in extraction.rejected],
        "degeneracies": result.degeneracies,
        "corrected_tensor": {"file": tensor_path.name, "npz_sha256": tensor_meta["npz_sha256"],
                             "layout": "PsfTensor; perturbation applied along the meridian phi = 0 (+col)"},
    }
    if captures.injected is not None:
        doc["injected"] = captures.injected.to_dict()
    if report:
        from .report import write_report

        png = path.with_suffix(".png")
        write_report(png, result, doc)
        doc["report_png"] = png.name
    doc["calibration_id"] = _content_id(doc)
    write_json(path, doc)
    return load_calibration(path)


def load_calibration(path) -> Calibration:
    """Read and validate a calibration file (schema, parameters, id, corrected tensor hash)."""
    path = Path(path)
    try:
        doc = read_json_object(path, CalibrationError)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no such calibration file") from None
    if doc.get("schema") != SCHEMA:
        raise CalibrationError(f"{path}: schema {doc.get('schema')!r}, expected {SCHEMA!r}")
    for key in ("calibration_id", "device", "parameters", "captures", "nominal_tensor", "corrected_tensor",
                "stray_light_spread_px"):
        if key not in doc:
            raise CalibrationError(f"{path}: missing {key!r}")
    for key in ("device", "parameters", "corrected_tensor"):
        if not isinstance(doc[key], dict):
            raise CalibrationError(f"{path}: {key!r} is a JSON {type(doc[key]).__name__}, expected an object")
    params = doc["parameters"]
    for name in PARAMETERS:
        entry = params.get(name)
        if not isinstance(entry, dict) or set(entry) != {"value", "sigma", "unit", "free"}:
            raise CalibrationError(f"{path}: parameters.{name} must be {{value, sigma, unit, free}}, got {entry!r}")
        if entry["unit"] != UNITS[name]:
            raise CalibrationError(f"{path}: parameters.{name} unit {entry['unit']!r}, expected {UNITS[name]!r}")
        shape_ok = (isinstance(entry["value"], list) and len(entry["value"]) == 2) if SIZES[name] == 2 else \
            isinstance(entry["value"], (int, float))
        if not shape_ok:
            raise CalibrationError(f"{path}: parameters.{name} value must have {SIZES[name]} number(s)")
    extra = set(params) - set(PARAMETERS)
    if extra:
        raise CalibrationError(f"{path}: unknown parameters {sorted(extra)}")
    if _content_id(doc) != doc["calibration_id"]:
        raise CalibrationError(f"{path}: content does not match its calibration_id (file edited or corrupt)")
    tensor_file = path.parent / doc["corrected_tensor"]["file"]
    if not tensor_file.exists():
        raise CalibrationError(f"{path}: corrected tensor {tensor_file.name} is missing")
    if hashlib.sha256(tensor_file.read_bytes()).hexdigest() != doc["corrected_tensor"]["npz_sha256"]:
        raise CalibrationError(f"{tensor_file}: hash does not match the calibration file")
    calib = Calibration(path, doc)
    calib.perturbation  # validates the values (Perturbation checks ranges)
    return calib
