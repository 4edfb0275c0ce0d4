"""Built cameras drawn from the calibration's error prior and calibrated as a user calibrates one.

``bmi eval``'s ``built_camera_sampled`` condition decodes each such camera with the errors its calibration
*fitted*, not the ones it was built with: the numbers then carry the calibration's own error, as a user's
frames do. Each camera is

1. drawn: ``Perturbation.random`` (uniform within the paper's ranges: PSF shift ≤ 0.5 px, scale ≤ 5 %,
   decenter ≤ 10 µm, tilt ≤ 1′, stray light ≤ 3 %, sensor radius ≤ 2 %), seeded by (seed, camera index);
2. captured: the standard point-source target through the simulated device (``calibration.targets
   .simulate_captures``, the capture ``bmi calibrate --simulate`` takes; ~1.5 s);
3. fitted: ``calibration.extract.extract_spots`` and ``calibration.fit.fit_calibration`` with
   ``bmi calibrate``'s defaults (13 fit + 4 held-out sources, Levenberg–Marquardt, 4 relinearisations;
   median 33 s, up to ~150 s on 2 cores, docs/benchmarks.md "Recovery over random perturbations").

The fits are kept for the process (``sampled_cameras`` is memoised), so several scene scales share them.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from bmi_sdk.optics.perturb import Perturbation

SAMPLED_CAMERAS = 3
"""Cameras ``built_camera_sampled`` averages over by default (``bmi eval --cameras``)."""


@dataclass(frozen=True)
class SampledCamera:
    """One drawn camera: the errors it was built with, those its calibration fitted, and what the fit cost."""

    index: int
    truth: Perturbation
    fitted: Perturbation
    capture_s: float
    fit_s: float


def calibrate_sampled(index: int, seed: int, lens_name: str = "bmi_monocentric") -> SampledCamera:
    """Camera ``index`` of ``seed``: drawn from the prior, captured through the simulated device and fitted."""
    # Submodules, not the package: an editable install made before calibration/ had an __init__.py
    # resolves ``calibration`` as a namespace package outside the repository root.
    from calibration.extract import extract_spots
    from calibration.fit import fit_calibration
    from calibration.targets import CapturePlan, simulate_captures, standard_target

    truth = Perturbation.random(np.random.default_rng([seed, 31, index]))
    t0 = time.perf_counter()
    captures = simulate_captures(standard_target(), CapturePlan(), truth, seed=seed * 1000 + index,
                                 lens_name=lens_name)
    t1 = time.perf_counter()
    result = fit_calibration(extract_spots(captures), lens_name=lens_name)
    return SampledCamera(index, truth, result.estimate, t1 - t0, time.perf_counter() - t1)


@functools.lru_cache(maxsize=4)
def sampled_cameras(count: int, seed: int, lens_name: str = "bmi_monocentric") -> tuple[SampledCamera, ...]:
    """``count`` cameras of ``seed`` (``calibrate_sampled``), each fitted once per process."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"the number of sampled cameras must be a whole number >= 1, got {count!r}")
    return tuple(calibrate_sampled(i, seed, lens_name) for i in range(count))
