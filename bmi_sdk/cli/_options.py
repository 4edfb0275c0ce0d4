"""Checked option values for the `bmi` commands: a bad value is one line naming the option and its valid range.

The argparse types (``number``, ``whole``, ``SEED``) and ``OptionError`` live in ``bmi_sdk.option_values``, which the
benchmark targets share; here are the checks that need the project: output files and folders, and perturbations.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..option_values import OptionError


def check_output_file(option: str, path: str | os.PathLike, suffixes: tuple[str, ...]) -> Path:
    """Refuse, before any work, an output file whose name does not end in one of ``suffixes`` or whose folder
    cannot be written (missing folders are created, as the command would). Returns the path."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise OptionError(f"{option} {path}: name it *{' or *'.join(suffixes)}", option)
    check_writable_folder(option, path.parent, path)
    return path


def check_writable_folder(option: str, folder: str | os.PathLike, shown: str | os.PathLike | None = None) -> None:
    """Create ``folder`` if it is missing and refuse it, naming ``option`` and ``shown`` (default the folder),
    when it is not a folder this user can write into."""
    folder = Path(folder) if str(folder) else Path(".")
    shown = folder if shown is None else shown
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OptionError(f"{option} {shown}: cannot create the folder {folder} ({exc.strerror or exc})",
                          option) from None
    try:  # a real write: permission bits, a read-only mount and ACLs all answer here
        with tempfile.TemporaryFile(dir=folder, prefix=".bmi-write-check-"):
            pass
    except OSError as exc:
        raise OptionError(f"{option} {shown}: cannot write into the folder {folder} ({exc.strerror or exc})",
                          option) from None


PERTURBATION_LIMITS = {"psf_shift_px": 50.0, "psf_scale_pct": 50.0, "decenter_um": 1000.0, "tilt_arcmin": 60.0,
                       "stray_light_spread_px": 500.0}
"""Largest magnitude of each hardware error a command line may inject (``--perturb``, ``--simulate``): 50 to
100 times the paper's ranges (``optics.perturb.PAPER_RANGES``). A 1 mm decenter already moves the image
450 px; 10 mm sends the chief ray past the sensor. The other terms keep ``Perturbation``'s own bounds."""


def perturbation_option(option: str, terms: list[str], lens_name: str = "bmi_monocentric"):
    """The ``optics.perturb.Perturbation`` of ``option``'s ``NAME=VALUE`` terms, refused with ``OptionError``
    (naming the option, the term and its valid range) when a term is malformed, beyond
    ``PERTURBATION_LIMITS``, or sends a chief ray of 0–60° past the sensor."""
    import numpy as np

    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.optics import get_lens
    from bmi_sdk.optics.perturb import UNITS, Perturbation, trace_spots

    perturbation = Perturbation()
    for term in terms:
        try:
            perturbation = perturbation.with_term(term)
        except ValueError as exc:
            raise OptionError(f"{option} {term}: {exc}", option) from None
        name = term.partition("=")[0].strip()
        limit = PERTURBATION_LIMITS.get(name)
        magnitude = float(np.linalg.norm(np.atleast_1d(getattr(perturbation, name))))
        if limit is not None and magnitude > limit:
            raise OptionError(f"{option} {term}: |{name}| is at most {limit:g} {UNITS.get(name, 'px')} "
                              f"(the paper's errors are 50-100x smaller)", option)
    if perturbation.is_design:
        return perturbation
    fields_deg = np.repeat([0.0, 30.0, 60.0], 4)
    phi_deg = np.tile([0.0, 90.0, 180.0, 270.0], 3)
    try:  # where the chief rays land: milliseconds, and the render would need every one of them
        trace_spots(get_lens(lens_name), perturbation, fields_deg, phi_deg, 2.0, 0.5876, BMI_SENSOR.centre_px,
                    fit_grid=8, fit_degree=2)
    except ValueError as exc:  # RayTraceError: a chief ray blocked or past the image surface
        raise OptionError(f"{option} {' '.join(terms)}: with these errors no image forms ({exc}); "
                          "use smaller values", option) from None
    return perturbation
