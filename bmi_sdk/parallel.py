"""Map jobs here or in spawned single-threaded processes, in order, with one progress bar.

The PSF tensor's field angles, the render cache's shards and the refinement cache's decodes
are many independent numpy jobs: on a few cores, one process per core with one BLAS thread
each uses them better than BLAS threads on small transforms. ``map_jobs`` is that loop,
written once: serial for ``workers`` ≤ 1, else a spawn-context pool; results come back in
job order; a job's exception ends the run, and the pool (pending jobs cancelled) and the
bar are closed however the loop ends. ``state`` builds what every job of one process shares
(a decoder, a PSF tensor) once per process, as ``scaleout.fan_out``'s does per Dask worker.

Imports only the standard library, tqdm and threadpoolctl, so every layer (the optics included) may use it.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
from typing import Any, Callable, Iterator, Sequence

from threadpoolctl import threadpool_limits

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

_process_state: Any = None
"""In a pool's worker: what ``state()`` returned when the worker started."""


def spawn_single_threaded_pool(workers: int, initializer: Callable | None = None,
                               initargs: tuple = ()) -> cf.ProcessPoolExecutor:
    """A spawn-context process pool whose ``workers`` processes start (now) with one BLAS thread each."""
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=initializer, initargs=initargs)
        try:
            # Start every process now, while the environment says one thread: the pool spawns a process for a
            # submitted job only while none is idle, so all the warm-up jobs go in before any is awaited.
            for started in [pool.submit(int, 0) for _ in range(workers)]:
                started.result()
        except BaseException:  # an initializer that failed broke the pool: do not leave its processes behind
            pool.shutdown(cancel_futures=True)
            raise
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return pool


def _start_worker(state: Callable[[], Any] | None) -> None:
    global _process_state
    _process_state = state() if state is not None else None


def _run_in_worker(fn: Callable[[Any, Any], Any], job: Any) -> Any:
    return fn(_process_state, job)


def map_jobs(fn: Callable[[Any, Any], Any], jobs: Sequence, workers: int, *,
             state: Callable[[], Any] | None = None, desc: str = "jobs", unit: str = "job",
             sizes: Sequence[int] | None = None, progress: bool = True) -> Iterator:
    """Yield ``fn(state(), job)`` for each job, in order (``state()`` is None without ``state``).

    ``workers`` ≤ 1 runs the jobs here, one after the other; more runs them in that many spawned
    single-threaded processes (``fn``, ``state`` and the jobs must then pickle: module-level
    functions). ``state()`` runs once per process. The bar counts ``sizes[i]`` (default 1) per
    finished job.
    """
    jobs = list(jobs)
    sizes = [1] * len(jobs) if sizes is None else list(sizes)
    if len(sizes) != len(jobs):
        raise ValueError(f"{len(sizes)} sizes for {len(jobs)} jobs")
    if not jobs:
        return  # no bar, no pool, no state to build
    bar = None
    if progress:
        from tqdm import tqdm

        where = "in-process" if workers <= 1 else f"{workers} processes"
        bar = tqdm(total=sum(sizes), desc=f"{desc} ({where})", unit=unit)
    pool = None
    try:
        if workers <= 1:
            here = state() if state is not None else None
            results = (fn(here, job) for job in jobs)
        else:
            pool = spawn_single_threaded_pool(workers, _start_worker, (state,))
            results = pool.map(_run_in_worker, [fn] * len(jobs), jobs)
        for result, size in zip(results, sizes):
            if bar is not None:
                bar.update(size)
            yield result
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        if bar is not None:
            bar.close()


def map_threads(fn: Callable[[Any], Any], items: Sequence, threads: int, name: str = "worker") -> Iterator:
    """Yield ``(item, fn(item))`` for each item, in order, computed on ``threads`` threads of this process (numpy,
    scipy's FFT and OpenCV release the GIL in their loops). The items are all queued at once; when the loop ends early (an
    exception in ``fn``, a consumer that stops, Ctrl-C) the ones not yet started are cancelled, so that the error
    surfaces after at most the ``threads`` running ones instead of after every queued item.

    BLAS runs one thread per call meanwhile (process-wide, ``threadpoolctl``): the threads are the parallelism, and
    BLAS threads on top of them spin for the cores they hold (a full frame's decode takes 1.2× as long with them,
    its first frame 1.7×: docs/benchmarks.md). One BLAS thread also keeps every result the same to the last bit
    on any number of threads."""
    pool = cf.ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix=name)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            futures = [(item, pool.submit(fn, item)) for item in items]
            for item, future in futures:
                yield item, future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
