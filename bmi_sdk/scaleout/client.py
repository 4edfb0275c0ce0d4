"""A Dask client for a ``--scheduler`` value: a local cluster it owns, or a connection to a running scheduler."""

from __future__ import annotations

import contextlib
import sys
from typing import Iterator

from ..extras import needs_extra
from .scheduler import SchedulerSpec, parse_scheduler

LOCAL_CONNECT_TIMEOUT = "300s"
"""Connect/handshake timeout inside a local cluster: generous, because a loaded 2-core machine can take
tens of seconds to start a worker process; an unreachable remote scheduler keeps Dask's own default."""


def dashboard_address(client) -> str | None:
    """The scheduler's dashboard URL, or None when it runs none (the dashboard needs bokeh installed)."""
    services = client.scheduler_info().get("services", {})
    return client.dashboard_link if "dashboard" in services else None


@contextlib.contextmanager
def open_client(scheduler: str | SchedulerSpec | None, announce: bool = True) -> Iterator[object | None]:
    """Yield a ``distributed.Client`` for ``scheduler`` (None: yield None, the caller runs in-process).

    ``local:N`` starts a ``LocalCluster`` of N worker processes with one thread each (Dask's nanny sets
    OMP/MKL/OpenBLAS to one thread too), on a free dashboard port, and closes it on exit, also on error
    or Ctrl-C. ``tcp://…`` connects to a running scheduler and leaves it running. With ``announce`` the
    workers and the dashboard address (when there is one) are printed to stderr. Without Dask (the
    ``[scaleout]`` extra) a scheduler raises ``MissingExtraError`` naming it.
    """
    spec = parse_scheduler(scheduler) if not isinstance(scheduler, SchedulerSpec) else scheduler
    if spec is None:
        yield None
        return
    with needs_extra("--scheduler"):
        import dask
        from distributed import Client, LocalCluster

    with contextlib.ExitStack() as stack:
        if spec.is_local:
            stack.enter_context(dask.config.set({"distributed.comm.timeouts.connect": LOCAL_CONNECT_TIMEOUT,
                                                 "distributed.comm.timeouts.tcp": LOCAL_CONNECT_TIMEOUT}))
            cluster = stack.enter_context(LocalCluster(n_workers=spec.n_workers, threads_per_worker=1,
                                                       processes=True, dashboard_address=":0"))
            client = stack.enter_context(Client(cluster))
        else:
            try:
                client = stack.enter_context(Client(spec.address))
            except OSError as exc:
                raise OSError(f"cannot reach the Dask scheduler at {spec.address}: {exc}") from None
        if announce:
            workers = client.scheduler_info().get("workers", {})
            threads = sum(w.get("nthreads", 0) for w in workers.values())
            link = dashboard_address(client)
            print(f"dask: {spec} — {len(workers)} workers, {threads} threads"
                  + (f"; dashboard {link}" if link else "; no dashboard (install bokeh for one)"), file=sys.stderr)
        yield client


@contextlib.contextmanager
def scheduler_address(scheduler: str | SchedulerSpec | None, announce: bool = True) -> Iterator[str | None]:
    """For a job that opens several clients in turn: yield an address every one of them can use.

    ``local:N`` starts the cluster once (closed on exit) and yields its ``tcp://`` address; a ``tcp://``
    scheduler is yielded as it is; None stays None (in-process).
    """
    spec = parse_scheduler(scheduler) if not isinstance(scheduler, SchedulerSpec) else scheduler
    if spec is None or not spec.is_local:
        yield None if spec is None else spec.address
        return
    with open_client(spec, announce=announce) as client:
        yield client.scheduler_info()["address"]
