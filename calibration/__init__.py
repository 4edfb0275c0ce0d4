"""Hardware-error calibration of the BMI camera from point-source captures (issue 5).

    from calibration import (standard_target, CapturePlan, simulate_captures, load_captures,
                             extract_spots, fit_calibration, write_calibration, load_calibration)
    captures = simulate_captures(standard_target(), CapturePlan(), Perturbation(decenter_um=(10, 0)), seed=0)
    result = fit_calibration(extract_spots(captures))
    write_calibration("calib.json", result, captures)       # + calib.psf.npz (corrected tensor) + calib.png
    calib = load_calibration("calib.json")                  # validates schema and hashes
    calib.id, calib.perturbation, calib.tensor()             # what the runtime needs

The perturbation model itself lives in ``bmi_sdk.optics.perturb`` (re-exported
here as ``Perturbation``); docs/calibration.md describes the file format.

Only the fit needs jax and jaxopt (the ``[calibrate]`` extra): ``FitResult``
and ``fit_calibration`` are imported on first use (PEP 562), so reading and
validating a calibration file, and the runtime's calibrated camera
(``bmi infer --calibration``), work in a decode-only install. Without the
extra, the first use raises ``MissingExtraError`` naming it.

Importing the package changes no process-wide state: jax switches to float64
only inside the fit (``model.float64``), and jaxopt's "no longer maintained"
warning is silenced only around its import (``model._solver_module``).
"""

import importlib

from bmi_sdk.extras import needs_extra
from bmi_sdk.optics.perturb import PARAMETERS, UNITS, Perturbation

from .extract import Extraction, Spot, extract_spots
from .io import SCHEMA, Calibration, load_calibration, write_calibration
from .targets import (
    CalibrationError,
    CapturePlan,
    Captures,
    PointSource,
    PointSourceScene,
    Target,
    load_captures,
    simulate_captures,
    standard_target,
)

__all__ = [
    "PARAMETERS", "UNITS", "Perturbation", "CalibrationError", "PointSource", "Target", "CapturePlan", "Captures",
    "PointSourceScene", "standard_target", "simulate_captures", "load_captures", "Extraction", "Spot",
    "extract_spots", "FitResult", "fit_calibration", "SCHEMA", "Calibration", "write_calibration",
    "load_calibration",
]

_FIT_NAMES = ("FitResult", "fit_calibration")
"""Public names of the ``fit`` submodule, which imports jax."""


def __getattr__(name: str):
    """``FitResult`` / ``fit_calibration``, imported from ``fit`` on first use (it needs the [calibrate] extra)."""
    if name not in _FIT_NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    with needs_extra(f"calibration.{name}"):
        value = getattr(importlib.import_module(f"{__name__}.fit"), name)
    globals()[name] = value  # resolved once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_FIT_NAMES))
