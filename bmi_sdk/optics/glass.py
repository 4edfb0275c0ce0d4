"""Refractive index of optical glasses from catalogue dispersion formulas.

Catalogues are JSON files (``bmi_sdk/data/glasses/*.json``) naming their
source. Supported formulas (λ in µm):

* ``schott``:    n² = A0 + A1 λ² + A2 λ⁻² + A3 λ⁻⁴ + A4 λ⁻⁶ + A5 λ⁻⁸
* ``sellmeier``: n² − 1 = Σ Bᵢ λ² / (λ² − Cᵢ)
* ``model``:     a glass known only by (nd, vd): two-term Cauchy n = a + b/λ²
  through nd at the d line with nF − nC = (nd − 1)/vd. Used for published
  prescriptions that list only nd/vd; accurate to a few 1e-4 across the visible.

Users add glasses with :func:`register_glass`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

LAMBDA_D_UM = 0.5875618
LAMBDA_F_UM = 0.4861327
LAMBDA_C_UM = 0.6562725


@dataclass(frozen=True)
class Glass:
    """One glass: its dispersion formula, coefficients and stated validity range."""

    name: str
    formula: str
    coefficients: dict = field(hash=False)
    valid_um: tuple[float, float] = (0.35, 1.1)
    source: str = ""

    def index(self, wavelength_um):
        """Refractive index at ``wavelength_um`` (scalar or array)."""
        lam = np.asarray(wavelength_um, dtype=np.float64)
        lo, hi = self.valid_um
        if not np.all(np.isfinite(lam)):
            raise ValueError(f"glass {self.name}: wavelength must be a finite number of µm, got {lam.min()}")
        if np.any(lam < lo) or np.any(lam > hi):
            raise ValueError(
                f"glass {self.name}: wavelength {lam.min():.4f}–{lam.max():.4f} µm outside the "
                f"formula's valid range {lo}–{hi} µm"
            )
        c = self.coefficients
        if self.formula == "schott":
            a = c["coefficients"]
            l2 = lam * lam
            n2 = a[0] + a[1] * l2 + a[2] / l2 + a[3] / l2**2 + a[4] / l2**3 + a[5] / l2**4
        elif self.formula == "sellmeier":
            l2 = lam * lam
            n2 = 1.0 + sum(b * l2 / (l2 - cc) for b, cc in zip(c["B"], c["C"]))
        elif self.formula == "model":
            nd, vd = c["nd"], c["vd"]
            b = (nd - 1.0) / vd / (LAMBDA_F_UM**-2 - LAMBDA_C_UM**-2)
            a = nd - b / LAMBDA_D_UM**2
            return a + b / (lam * lam)
        else:  # validated at load time
            raise ValueError(f"glass {self.name}: unknown formula {self.formula!r}")
        return np.sqrt(n2)


_REGISTRY: dict[str, Glass] = {}
_FORMULA_KEYS = {"schott": ("coefficients",), "sellmeier": ("B", "C"), "model": ("nd", "vd")}


def _glass_from_entry(name: str, entry: dict, source: str) -> Glass:
    formula = entry.get("formula")
    if formula not in _FORMULA_KEYS:
        raise ValueError(f"glass {name}: formula must be one of {sorted(_FORMULA_KEYS)}, got {formula!r}")
    missing = [k for k in _FORMULA_KEYS[formula] if k not in entry]
    if missing:
        raise ValueError(f"glass {name}: formula {formula} needs {missing}")
    valid = tuple(entry.get("valid_um", (0.35, 1.1)))
    return Glass(name=name.upper(), formula=formula, coefficients=dict(entry), valid_um=valid, source=source)


def _register_catalogue(data: dict) -> list[str]:
    source = data.get("source", "")
    names = []
    for name, entry in data["glasses"].items():
        glass = _glass_from_entry(name, entry, source)
        _REGISTRY[glass.name] = glass
        names.append(glass.name)
    return names


def register_glass(name: str, formula: str, valid_um=(0.35, 1.1), source: str = "user", **coefficients) -> Glass:
    """Add a user glass, e.g. ``register_glass("N-BK7", "sellmeier", B=[...], C=[...])``."""
    glass = _glass_from_entry(name, {"formula": formula, "valid_um": valid_um, **coefficients}, source)
    _REGISTRY[glass.name] = glass
    return glass


def _load_builtin() -> None:
    folder = resources.files("bmi_sdk") / "data" / "glasses"
    for item in folder.iterdir():
        if item.name.endswith(".json"):
            _register_catalogue(json.loads(item.read_text()))


def get_glass(name: str) -> Glass:
    """The glass called ``name`` (case-insensitive); a clear error if unknown."""
    if not _REGISTRY:
        _load_builtin()
    key = name.upper()
    if key not in _REGISTRY:
        raise ValueError(f"unknown glass {name!r}; known: {', '.join(sorted(_REGISTRY))} (add one with register_glass)")
    return _REGISTRY[key]


def refractive_index(material: str, wavelength_um):
    """Index of ``material`` ('air' is exactly 1: the lens is specified relative to air)."""
    if material.lower() in ("air", "vacuum"):
        return np.ones_like(np.asarray(wavelength_um, dtype=np.float64))
    return get_glass(material).index(wavelength_um)
