"""Benchmarks behind ``bmi bench TARGET``.

Each module here that defines ``register(subparsers)`` adds one target
(``bmi bench psf``, ``bmi bench render``…). Benchmarks print markdown tables;
with ``--json PATH`` they also write them as a JSON record (``record``: the
command, commit, date and machine with the tables), which
``tools/docs_tables.py`` turns into docs/benchmarks.md's sections. Nothing here
writes into the docs. Speed never lives in tests.
"""

from __future__ import annotations

import math
import time

from ..resources import cpu_seconds, peak_rss_mb  # noqa: F401  (the targets import them from here)
from .record import add_json_argument, check_record_path, markdown_tables, write_record


def markdown_table(header: list[str], rows: list[list]) -> str:
    def fmt(x):
        if isinstance(x, float):
            return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.0f}"
        return str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(x) for x in r) + " |" for r in rows]
    return "\n".join(lines)


def timed(fn, repeat: int = 1):
    """(result of the last call, best wall time in seconds over ``repeat`` calls)."""
    best = math.inf
    out = None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return out, best


def timed_cpu(fn):
    """(result, wall seconds, CPU seconds incl. finished children) of one call."""
    wall, cpu = time.perf_counter(), cpu_seconds()
    out = fn()
    return out, time.perf_counter() - wall, cpu_seconds() - cpu


def register_target(subparsers, name: str, help_text: str, description: str, section: str, run,
                    full: bool = True) -> None:
    """Add ``bmi bench NAME [--full] [--json PATH]`` printing ``run(full)`` (a markdown text; ``--json``: its tables
    as a record, ``emit``); ``full`` False: the target has no full-size measurement, takes no ``--full`` (argparse
    refuses it) and prints ``run()``. ``section`` names the docs/benchmarks.md section its record fills."""

    def handler(args) -> int:
        check_record_path(args.json, args.overwrite)
        emit(run(full=args.full) if full else run(), args.json, args.overwrite)
        return 0

    p = subparsers.add_parser(name, help=help_text, description=description)
    if full:
        p.add_argument("--full", action="store_true", help="also run the full-size measurement (minutes)")
    add_json_argument(p)
    p.set_defaults(handler=handler)


def emit(text: str, json_path=None, overwrite: bool = False) -> None:
    """Print a benchmark's markdown ``text``; with ``json_path`` also write its tables there as a record
    (``record.write_record``: an earlier one is replaced only with ``overwrite``)."""
    print(text)
    if json_path is not None:
        write_record(json_path, markdown_tables(text), overwrite=overwrite)
