"""Benchmarks behind ``bmi bench TARGET``.

Each module here that defines ``register(subparsers)`` adds one target
(``bmi bench psf``, ``bmi bench render``…). Benchmarks print markdown tables;
with ``--write-docs`` they replace their own section of docs/benchmarks.md,
headed by the exact command that made it. Speed never lives in tests.
"""

from __future__ import annotations

import math
import platform
import re
import sys
import time
from pathlib import Path

from ..io_atomic import write_bytes
from ..resources import cpu_seconds, peak_rss_mb  # noqa: F401  (the targets import them from here)

DOCS = Path(__file__).resolve().parents[2] / "docs" / "benchmarks.md"


def machine_line() -> str:
    import os

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"load average {load} when written (wall times on a shared machine scale with it; CPU times do not)")


def markdown_table(header: list[str], rows: list[list]) -> str:
    def fmt(x):
        if isinstance(x, float):
            return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.0f}"
        return str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(x) for x in r) + " |" for r in rows]
    return "\n".join(lines)


def update_section(title: str, body: str, path: Path = DOCS) -> None:
    """Write a bench's generated text into the ``## title`` section of docs/benchmarks.md, atomically.

    The text sits between two comment lines naming the title, and only what lies between them is replaced:
    notes and dated measurements written by hand in the same section are kept (``--write-docs`` once
    replaced the whole section, and with it every dated record). A section written before the markers gets
    the generated text at its top, above what it held; a missing section is appended.
    """
    command = "bmi " + " ".join(a for a in sys.argv[1:] if a != "--write-docs")
    begin, end = f"<!-- generated: {title} -->", f"<!-- end generated: {title} -->"
    block = f"{begin}\nMade by `{command}` on {machine_line()}.\n\n{body.strip()}\n{end}\n"
    text = path.read_text() if path.exists() else "# Benchmarks\n\nEvery number here comes from the command above it.\n"
    generated = re.compile(rf"^{re.escape(begin)}\n.*?^{re.escape(end)}\n", re.S | re.M)
    heading = re.compile(rf"^## {re.escape(title)}\n\n?", re.M)
    if generated.search(text):
        text = generated.sub(lambda _: block, text, count=1)
    elif heading.search(text):
        text = heading.sub(lambda m: f"## {title}\n\n{block}\n", text, count=1)
    else:
        text = text.rstrip("\n") + f"\n\n## {title}\n\n{block}"
    write_bytes(path, text.encode())


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
    """Add ``bmi bench NAME [--full] [--write-docs]`` printing ``run(full)`` (a markdown text); ``full`` False: the
    target has no full-size measurement, takes no ``--full`` (argparse refuses it) and prints ``run()``."""

    def handler(args) -> int:
        text = run(full=args.full) if full else run()
        print(text)
        if args.write_docs:
            update_section(section, text)
        return 0

    p = subparsers.add_parser(name, help=help_text, description=description)
    if full:
        p.add_argument("--full", action="store_true", help="also run the full-size measurement (minutes)")
    p.add_argument("--write-docs", action="store_true", help=f"replace the '{section}' section of docs/benchmarks.md")
    p.set_defaults(handler=handler)
