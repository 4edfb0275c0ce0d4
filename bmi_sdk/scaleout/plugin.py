"""The worker plugin behind ``fan_out``: per-worker state built once (a module of its own because it
subclasses ``distributed``'s ``WorkerPlugin``, and ``distributed`` is imported only when a scheduler is used)."""

from __future__ import annotations

from typing import Callable

from distributed.diagnostics.plugin import WorkerPlugin


class StatePlugin(WorkerPlugin):
    """Builds ``factory()`` once when a worker starts (or joins) and keeps it for that worker's tasks; first
    it undoes the nanny's malloc trimming (``malloc.relax_malloc_trimming``)."""

    def __init__(self, factory: Callable[[], object]):
        self.factory = factory
        self.state = None

    def setup(self, worker) -> None:
        from .malloc import relax_malloc_trimming

        relax_malloc_trimming()
        self.state = self.factory()

    def teardown(self, worker) -> None:
        close = getattr(self.state, "close", None)
        if callable(close):
            close()
        self.state = None


def run_on_worker(item, task, plugin_name: str):
    """Run ``task(state, item)`` with the state the plugin named ``plugin_name`` built on this worker."""
    from distributed import get_worker

    return task(get_worker().plugins[plugin_name].state, item)
