"""The ``--scheduler`` value: omitted (in-process), ``local:N`` (a local cluster) or ``tcp://HOST:PORT``."""

from __future__ import annotations

import os
from dataclasses import dataclass
from urllib.parse import urlsplit

HELP = ("run on Dask: local:N (a local cluster of N single-threaded worker processes) or tcp://HOST:PORT "
        "(a running scheduler; see docs/scale-out.md); default: in this process")


WORKERS_PER_CORE = 4
"""Most local workers per CPU core: each is a process with its own interpreter (~150 MB) that waits its turn
for a core; past a few per core they only add start-up time (local:100000 started processes for minutes
without a word)."""


def max_local_workers() -> int:
    """The most workers ``local:N`` starts on this machine (``WORKERS_PER_CORE`` per CPU core)."""
    return WORKERS_PER_CORE * (os.cpu_count() or 1)


@dataclass(frozen=True)
class SchedulerSpec:
    """Where tasks run: ``n_workers`` local processes, or the scheduler at ``address``."""

    n_workers: int | None = None
    address: str | None = None

    @property
    def is_local(self) -> bool:
        return self.n_workers is not None

    def __str__(self) -> str:
        return f"local:{self.n_workers}" if self.is_local else str(self.address)


def parse_scheduler(text: str | None) -> SchedulerSpec | None:
    """``None``/empty → None (in-process); ``local:N`` with 1 ≤ N ≤ ``max_local_workers()``; ``tcp://HOST:PORT``.
    Anything else: ValueError."""
    if text is None or not text.strip():
        return None
    text = text.strip()
    if text.startswith("local:"):
        count = text[len("local:"):]
        if not count.isdigit() or int(count) < 1:
            raise ValueError(f"--scheduler {text!r}: local:N needs a whole number of workers N ≥ 1")
        if int(count) > max_local_workers():
            raise ValueError(f"--scheduler {text!r}: local:N takes 1 … {max_local_workers()} workers here "
                             f"({WORKERS_PER_CORE} per CPU core); for more, run a Dask scheduler with workers on "
                             "other machines and give tcp://HOST:PORT")
        return SchedulerSpec(n_workers=int(count))
    parts = urlsplit(text)
    if parts.scheme == "tcp":
        try:
            host, port = parts.hostname, parts.port
        except ValueError:  # a port that is not a number or out of range
            host, port = None, None
        if host and port and not parts.path.strip("/") and not parts.query:
            return SchedulerSpec(address=f"tcp://{parts.netloc}")
    raise ValueError(f"--scheduler {text!r} is neither local:N nor tcp://HOST:PORT (e.g. local:2, tcp://10.0.0.5:8786)")


def add_scheduler_argument(parser) -> None:
    """Add ``--scheduler`` (validated when parsed: a bad value is a usage error naming the problem)."""

    def checked(text: str) -> str:
        import argparse

        try:
            parse_scheduler(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    parser.add_argument("--scheduler", default=None, type=checked, metavar="local:N|tcp://HOST:PORT", help=HELP)
