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

Importing the package changes no process-wide state: jax switches to float64
only inside the fit (``model.float64``), and jaxopt's "no longer maintained"
warning is silenced only around its import (``model._solver_module``).
"""

from bmi_sdk.optics.perturb import PARAMETERS, UNITS, Perturbation

from .extract import Extraction, Spot, extract_spots
from .fit import FitResult, fit_calibration
from .io import SCHEMA, Calibration, load_calibration, write_calibration
from .targets import (CalibrationError, CapturePlan, Captures, PointSource, PointSourceScene, Target,
                      load_captures, simulate_captures, standard_target)

__all__ = [
    "PARAMETERS", "UNITS", "Perturbation", "CalibrationError", "PointSource", "Target", "CapturePlan", "Captures",
    "PointSourceScene", "standard_target", "simulate_captures", "load_captures", "Extraction", "Spot",
    "extract_spots", "FitResult", "fit_calibration", "SCHEMA", "Calibration", "write_calibration",
    "load_calibration",
]
