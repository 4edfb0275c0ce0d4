"""Run ``task(state, item)`` over many items, in this process or on Dask workers, with one progress bar.

``state`` is a factory for what a process needs before it can run a task and should build only once
(a loaded model, PSF kernels). In-process it is called once; on Dask a worker plugin calls it once on every
worker, including workers that join or restart during the run, and tasks find it there. Tasks and the
factory are pickled to the workers: module-level functions or picklable objects.

A worker that dies loses only its running tasks; the scheduler re-runs them on the other workers (up to
``distributed.scheduler.allowed-failures`` times, 3 by default; a task that keeps killing workers ends
the run with ``WorkerLostError``). Tasks must therefore be idempotent: write results under names that are
published once (``once.publish_once``) or overwritten atomically with identical content.
"""

from __future__ import annotations

import uuid
from typing import Callable, Sequence


class WorkerLostError(ChildProcessError):
    """A task kept killing the workers that ran it (out of memory, a crash in native code)."""


def _no_state():
    return None


def fan_out(task: Callable, items: Sequence, *, client=None, state: Callable[[], object] | None = None,
            desc: str = "tasks", unit: str = "task", sizes: Sequence[int] | None = None, progress: bool = True,
            on_result: Callable[[int, object], None] | None = None) -> list:
    """``[task(state, item) for item in items]``, run on ``client``'s workers (None: here, in order).

    One progress bar counts ``sizes[i]`` (default 1) per finished item; ``on_result(i, result)`` is called
    as each item finishes (completion order on a cluster). A task's exception ends the run: the remaining
    tasks are cancelled and the exception is raised here.
    """
    items = list(items)
    sizes = [1] * len(items) if sizes is None else list(sizes)
    bar = None
    if progress:
        from tqdm import tqdm

        where = "in-process" if client is None else f"{len(client.scheduler_info()['workers'])} Dask workers"
        bar = tqdm(total=sum(sizes), desc=f"{desc} ({where})", unit=unit)
    results: list = [None] * len(items)

    def finished(i: int, result) -> None:
        results[i] = result
        if on_result is not None:
            on_result(i, result)
        if bar is not None:
            bar.update(sizes[i])

    try:
        if client is None:
            local_state = (state or _no_state)()
            for i, item in enumerate(items):
                finished(i, task(local_state, item))
        else:
            _fan_out_dask(client, task, items, state or _no_state, desc, finished)
    finally:
        if bar is not None:
            bar.close()
    return results


def _fan_out_dask(client, task, items, state, desc, finished) -> None:
    from distributed import KilledWorker, as_completed

    from .plugin import StatePlugin, run_on_worker

    run_id = f"bmi-{desc.replace(' ', '-')}-{uuid.uuid4().hex[:8]}"
    client.register_plugin(StatePlugin(state), name=run_id)
    futures = client.map(run_on_worker, items, task=task, plugin_name=run_id,
                         key=[f"{run_id}-{i}" for i in range(len(items))], pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    try:
        for future in as_completed(futures):
            try:
                result = future.result()
            except KilledWorker as exc:
                raise WorkerLostError(f"{desc}: item {index[future.key]} killed every worker that ran it "
                                      f"({exc}); out of memory?") from None
            finished(index[future.key], result)
    finally:
        client.cancel(futures)
        client.unregister_worker_plugin(run_id)
