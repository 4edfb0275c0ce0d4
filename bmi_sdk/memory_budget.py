"""Refuse work whose memory, estimated from its arguments, would not fit: before allocating, with the numbers.

A PSF with ``--oversample 1001`` needs ~24 GB and an inference tile of
100000 px 224 GiB: left to run, the first wakes the kernel's OOM killer
(which may take other processes with it) and the second dies with a NumPy
traceback. Callers estimate their peak from the arguments (formulas measured
in docs/reliability.md) and call ``check_fits`` first; a command-line option
that sizes an allocation (``bmi simulate --size``) calls ``check_allocation``,
whose one-line refusal names the option and its value.

The limit is 4 GiB or 75 % of the memory available now (``MemAvailable``),
whichever is less, or ``BMI_MAX_MEMORY_MB`` when set. No PSF or tile the SDK
uses comes near 4 GiB (a full-frame ``bmi infer`` peaks at 1.6 GB); past it
a request is a typo or needs a deliberate ``BMI_MAX_MEMORY_MB``.
"""

from __future__ import annotations

import math
import os
import time

ENV_LIMIT = "BMI_MAX_MEMORY_MB"
AVAILABLE_SHARE = 0.75
DEFAULT_CAP_BYTES = 4 * 2**30


class MemoryBudgetError(ValueError):
    """The estimated memory of a request exceeds the limit; nothing was allocated.

    ``option`` is the command-line option that asked for it (``check_allocation``), None otherwise: the
    ``bmi`` command exits 2 for an error that names an option, as for any other bad option value.
    """

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


AVAILABLE_MAX_AGE_S = 0.5
"""How long a reading of the memory available stands: a camera's first frame checks ~20 000 PSFs of a few MB
each, and reading ``/proc/meminfo`` costs ~0.1 ms, 6 % of such a PSF."""
_available_reading: tuple[float, int | None] = (-math.inf, None)  # (time.monotonic() read at, bytes)


def _available_bytes() -> int | None:
    """The memory available now (``MemAvailable``), read again when the last reading is ``AVAILABLE_MAX_AGE_S``
    old; None when the system does not say."""
    global _available_reading
    now = time.monotonic()
    read_at, available = _available_reading
    if now - read_at > AVAILABLE_MAX_AGE_S:
        available = _read_available_bytes()
        _available_reading = (now, available)
    return available


def _read_available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def limit_bytes() -> tuple[int, str]:
    """(limit in bytes, where it comes from)."""
    text = os.environ.get(ENV_LIMIT)
    if text:
        try:
            mb = float(text)
        except ValueError:
            raise MemoryBudgetError(f"{ENV_LIMIT}={text!r} is not a number of MB") from None
        return int(mb * 2**20), f"{ENV_LIMIT}={text}"
    available = _available_bytes()
    if available is None or available * AVAILABLE_SHARE >= DEFAULT_CAP_BYTES:
        return DEFAULT_CAP_BYTES, "the default cap"
    return int(available * AVAILABLE_SHARE), f"{AVAILABLE_SHARE:.0%} of the {available / 2**30:.1f} GiB available"


def _over_limit(estimate_bytes: float) -> str | None:
    """"more than the L GiB limit (where L comes from)" when ``estimate_bytes`` exceeds the limit (or is not a
    number), None when it fits."""
    limit, source = limit_bytes()
    if estimate_bytes <= limit:
        return None
    return f"more than the {limit / 2**30:.1f} GiB limit ({source}; {ENV_LIMIT} sets it)"


def check_fits(estimate_bytes: float, what: str, hint: str = "") -> None:
    """Raise ``MemoryBudgetError`` when ``estimate_bytes`` exceeds ``limit_bytes()``; ``what`` names the request."""
    over = _over_limit(estimate_bytes)
    if over:
        raise MemoryBudgetError(f"{what} needs about {estimate_bytes / 2**30:.1f} GiB, {over}"
                                + (f"; {hint}" if hint else ""))


def check_allocation(option: str, value: object, estimate_bytes: float, hint: str = "") -> None:
    """Refuse a command-line option whose value would allocate more than ``limit_bytes()``, before allocating.

    One line names the option, its value, the estimate and the limit, e.g. ``--size 100000 needs about
    112.0 GiB, more than the 4.0 GiB limit (the default cap; BMI_MAX_MEMORY_MB sets it); hint``. The error
    carries ``option``. A NaN estimate is refused too (an option value no formula can size).
    """
    over = _over_limit(estimate_bytes)
    if over:
        raise MemoryBudgetError(f"{option} {value} needs about {estimate_bytes / 2**30:.1f} GiB, {over}"
                                + (f"; {hint}" if hint else ""), option=option)
