"""The package's extras (optional dependency groups) and the one-line error when one is missing.

``pip install bmi-sdk`` installs what decoding needs: raw frames (DNG I/O), the
ONNX runtime path, the classical decoder, the simulated camera and device
access, optics, simulation, and reading calibration files. The rest come as
extras (``pyproject.toml``; exact versions in ``constraints.txt``):

* ``[train]`` — torch, kornia, onnx (``torch.onnx.export`` needs it; so does
  the MAC count of ``bmi bench infer``), h5py (the NYU Depth V2 loader):
  ``bmi train``, model export;
* ``[calibrate]`` — jax, jaxlib, jaxopt and matplotlib (the fit's PNG report):
  the fit of ``bmi calibrate``. Reading a calibration file needs none of them;
* ``[scaleout]`` — dask[distributed]: ``--scheduler``;
* ``[plot]`` — matplotlib: ``bmi crlb --plot``, ``bmi demo``'s PSF gallery.

Code that needs an extra imports it where it is used, so nothing else pays for
it. ``needs_extra`` turns the ``ModuleNotFoundError`` of a module an extra
provides into ``MissingExtraError``, whose message names the extra to install;
the ``bmi`` command prints it as one line.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

EXTRA_OF_MODULE = {
    "torch": "train", "kornia": "train", "onnx": "train", "h5py": "train",
    "jax": "calibrate", "jaxlib": "calibrate", "jaxopt": "calibrate",
    "dask": "scaleout", "distributed": "scaleout",
    "matplotlib": "plot",  # also in [calibrate], for the fit's report
}
"""Top-level module → the extra that installs it (tests/test_extras.py checks it against pyproject.toml)."""


class MissingExtraError(ModuleNotFoundError):
    """A module of an extra is not installed; the message says which extra installs it and how."""

    def __init__(self, what: str, extra: str, module: str):
        super().__init__(f"{what} needs the [{extra}] extra: pip install 'bmi-sdk[{extra}]' "
                         f"(no module named {module!r})", name=module)
        self.what, self.extra = what, extra

    def __reduce__(self):
        """Pickled by its own arguments, so that it comes back intact from a Dask worker."""
        return type(self), (self.what, self.extra, self.name)


@contextlib.contextmanager
def needs_extra(what: str) -> Iterator[None]:
    """Context manager: a ``ModuleNotFoundError`` inside for a module of an extra becomes ``MissingExtraError``
    (``what`` names the feature that needs it). Any other missing module, a broken install or a bug, is
    raised unchanged, with its traceback; a ``MissingExtraError`` raised inside keeps its own, closer ``what``."""
    try:
        yield
    except MissingExtraError:
        raise
    except ModuleNotFoundError as exc:
        extra = EXTRA_OF_MODULE.get((exc.name or "").partition(".")[0])
        if extra is None:
            raise
        raise MissingExtraError(what, extra, exc.name) from None
