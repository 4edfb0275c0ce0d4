"""What this process has used so far: CPU seconds and peak resident memory.

A leaf module (standard library only) so that both the runtime, which puts
peak memory in every job report, and the benchmarks can measure without one
importing the other.
"""

from __future__ import annotations

import resource


def cpu_seconds() -> float:
    """CPU time of this process plus its finished child processes (workers of a pool)."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
