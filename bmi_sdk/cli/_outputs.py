"""Refusing to replace an earlier run's output files unless the user asks (``--overwrite``).

A command that writes named files (``bmi simulate``'s DNG, ``bmi calibrate``'s calibration) checks them all
before it starts its work: a rendered frame or a calibration of real captures is not lost to a repeated
command line, and a refusal costs no minutes of rendering or fitting. ``bmi infer`` refuses a folder of
earlier results the same way (``runtime.output_set``); ``bmi acquire`` never replaces a capture.
"""

from __future__ import annotations

from pathlib import Path


def refuse_existing(paths, what: str = "--out") -> None:
    """``FileExistsError`` naming every path of ``paths`` that exists (a file or a folder), unless none does."""
    existing = [str(p) for p in map(Path, paths) if p.exists()]
    if existing:
        raise FileExistsError(f"{', '.join(existing)} already exist{'s' if len(existing) == 1 else ''} (an earlier "
                              f"run?); pass --overwrite to replace {'it' if len(existing) == 1 else 'them'}, "
                              f"or choose another {what}")
