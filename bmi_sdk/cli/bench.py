"""`bmi bench TARGET`: error-against-run-time tables (targets live in bmi_sdk.bench)."""

from __future__ import annotations

import importlib
import pkgutil

from bmi_sdk import bench as bench_pkg


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="measure speed, memory and error against run time (results belong in docs/benchmarks.md)",
        description="Benchmarks. Each target prints a table; speed is measured here, never in tests.",
    )
    targets = parser.add_subparsers(dest="target", metavar="TARGET")
    for info in sorted(pkgutil.iter_modules(bench_pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{bench_pkg.__name__}.{info.name}")
        if hasattr(module, "register"):
            module.register(targets)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)
