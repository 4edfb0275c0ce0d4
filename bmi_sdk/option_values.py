"""Checked values of command-line options, shared by the `bmi` commands and the benchmark targets they register.

``number(...)`` and ``whole(...)`` are argparse ``type=`` callables: argparse prints
``bmi simulate: error: argument --field-deg: -20 is outside [0, 60] °`` and exits 2 before
the handler runs. A value that can only be judged inside the handler raises ``OptionError``, which
``bmi_sdk.cli.main`` also turns into exit 2. This module imports nothing of the project, so every layer that
registers options (``bmi_sdk.cli``, ``bmi_sdk.bench``) can use it.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


class OptionError(ValueError):
    """A command-line option's value is refused; ``option`` names it (``bmi`` exits 2, as for argparse)."""

    def __init__(self, message: str, option: str):
        super().__init__(message)
        self.option = option


def _num(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool, unit: str) -> str:
    left = "(-inf" if lo is None else f"{'(' if lo_open else '['}{_num(lo)}"
    right = "inf)" if hi is None else f"{_num(hi)}{')' if hi_open else ']'}"
    return f"{left}, {right}" + (f" {unit}" if unit else "")


def _check_range(value: float, text: str, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool,
                 unit: str, allow_inf: bool) -> None:
    valid = _range_text(lo, hi, lo_open, hi_open, unit)
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number; valid: {valid}")
    if math.isinf(value) and allow_inf and value > 0:
        return
    if lo is not None and (value < lo or (lo_open and value == lo)) or \
            hi is not None and (value > hi or (hi_open and value == hi)):
        raise argparse.ArgumentTypeError(f"{text} is outside {valid}")


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           unit: str = "", allow_inf: bool = False) -> Callable[[str], float]:
    """An argparse type: a float within [lo, hi] (open ends with ``lo_open``/``hi_open``; None: unbounded).
    NaN is always refused, +inf only with ``allow_inf`` (written ``inf``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number; valid: "
                                             f"{_range_text(lo, hi, lo_open, hi_open, unit)}") from None
        _check_range(value, text, lo, hi, lo_open, hi_open, unit, allow_inf)
        return value

    parse.__name__ = "number"
    return parse


def whole(lo: int | None = None, hi: int | None = None, *, unit: str = "", odd: bool = False,
          even: bool = False, multiple_of: int = 1) -> Callable[[str], int]:
    """An argparse type: a whole number within [lo, hi] (None: unbounded), odd or even, or a multiple of
    ``multiple_of``, when asked."""

    def parse(text: str) -> int:
        valid = _range_text(lo, hi, False, False, unit) + (", odd" if odd else ", even" if even else "") + \
            (f", a multiple of {multiple_of}" if multiple_of > 1 else "")
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number; valid: {valid}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi) or \
                (odd and value % 2 == 0) or (even and value % 2) or value % multiple_of:
            raise argparse.ArgumentTypeError(f"{text} is outside {valid}")
        return value

    parse.__name__ = "whole number"
    return parse


def whole_list(lo: int, hi: int, *, unit: str = "", multiple_of: int = 1) -> Callable[[str], list[int]]:
    """An argparse type: a comma list of one or more ``whole`` numbers, each within [lo, hi]."""
    one = whole(lo, hi, unit=unit, multiple_of=multiple_of)

    def parse(text: str) -> list[int]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"{text!r} is not a comma list of whole numbers")
        return [one(t) for t in items]

    parse.__name__ = "comma list"
    return parse


def size_hw(lo: int, hi: int, *, multiple_of: int = 1) -> Callable[[str], tuple[int, int]]:
    """An argparse type: a size written HxW (e.g. 512x768), each side a ``whole`` number within [lo, hi] px."""
    side = whole(lo, hi, unit="px", multiple_of=multiple_of)

    def parse(text: str) -> tuple[int, int]:
        parts = text.lower().split("x")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"{text!r} is not a size written HxW, e.g. 512x768")
        return side(parts[0]), side(parts[1])

    parse.__name__ = "size"
    return parse


SEED = whole(0, 2**32 - 1)
"""A noise or scene seed: NumPy's generators take 0 … 2³²−1 as a plain seed."""
