"""bmi_sdk.parallel.map_jobs: results in job order, the same here and in spawned processes, per-process state,
and a failing job that ends the run with its own exception and a pool that accepts no more work.

Jobs are built-in operators (``fn(state, job)`` = ``operator.mul(3, job)``), so spawned processes can
unpickle them without importing this test module.
"""

from __future__ import annotations

import functools
import operator
import os

import pytest

from bmi_sdk import parallel

THREE = functools.partial(int, 3)
"""The per-process state: a picklable zero-argument callable returning 3."""


def test_results_come_in_job_order_and_equal_here_and_in_processes():
    jobs = [5, 0, 7, 2, 9, 4, 1]
    expected = [3 * j for j in jobs]
    serial = list(parallel.map_jobs(operator.mul, jobs, 1, state=THREE, progress=False))
    pooled = list(parallel.map_jobs(operator.mul, jobs, 2, state=THREE, progress=True, desc="test",
                                    sizes=[2] * len(jobs)))
    assert serial == expected and pooled == expected


def test_without_state_fn_gets_none_and_no_jobs_run_nothing():
    assert list(parallel.map_jobs(operator.is_, [None, 1], 1, progress=False)) == [True, False]
    assert list(parallel.map_jobs(operator.mul, [], 2, state=THREE)) == []
    with pytest.raises(ValueError, match="2 sizes for 1 jobs"):
        list(parallel.map_jobs(operator.mul, [1], 1, sizes=[1, 1]))


def test_a_failing_job_raises_its_error_and_shuts_the_pool_down(monkeypatch):
    pools = []

    def recording_pool(*args, **kwargs):
        pools.append(spawn(*args, **kwargs))
        return pools[-1]

    spawn = parallel.spawn_single_threaded_pool
    monkeypatch.setattr(parallel, "spawn_single_threaded_pool", recording_pool)
    results = parallel.map_jobs(operator.truediv, [1, 2, 0, 4], 2, state=THREE, progress=False)
    assert next(results) == 3.0
    with pytest.raises(ZeroDivisionError):
        list(results)
    with pytest.raises(RuntimeError, match="shutdown"):
        pools[0].submit(int, 0)
    # a consumer that stops early closes the pool too
    early = parallel.map_jobs(operator.mul, [1, 2, 3], 2, state=THREE, progress=False)
    assert next(early) == 3
    early.close()
    with pytest.raises(RuntimeError, match="shutdown"):
        pools[1].submit(int, 0)


def test_the_pools_processes_start_with_one_blas_thread_and_leave_the_environment_alone(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    pool = parallel.spawn_single_threaded_pool(1)
    try:
        seen = pool.submit(os.getenv, "OMP_NUM_THREADS").result()  # read in the worker
    finally:
        pool.shutdown()
    assert seen == "1"
    assert os.environ["OMP_NUM_THREADS"] == "7" and "MKL_NUM_THREADS" not in os.environ


@pytest.mark.skipif(not os.path.exists("/proc/self/environ"), reason="reads each worker's environment from /proc")
def test_every_process_of_a_pool_starts_while_the_environment_says_one_thread(monkeypatch):
    """A spawn pool starts a process for a job only while no worker is idle; the pool must start all of its
    processes before it restores the environment, or a later one runs BLAS on every core beside the others."""
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    pool = parallel.spawn_single_threaded_pool(2)
    try:
        pids = list(pool._processes)  # the processes running when the pool is handed over
        environments = [open(f"/proc/{pid}/environ", "rb").read().split(b"\0") for pid in pids]
    finally:
        pool.shutdown()
    assert len(pids) == 2
    assert all(b"OPENBLAS_NUM_THREADS=1" in env for env in environments)
    assert "OPENBLAS_NUM_THREADS" not in os.environ


def test_map_threads_keeps_order_and_a_failure_cancels_what_has_not_started():
    """Items come back in order with their results; an item that raises ends the loop with its error, and the items
    queued behind it never run (a Ctrl-C or an error inside a frame's 432 blocks must not wait for all of them)."""
    import threading
    import time

    started = []
    lock = threading.Lock()

    def slow_square(x):
        with lock:
            started.append(x)
        if x == 3:
            raise ValueError("item 3 is bad")
        time.sleep(0.01)
        return x * x

    assert list(parallel.map_threads(slow_square, [5, 0, 7], 2)) == [(5, 25), (0, 0), (7, 49)]
    started.clear()
    with pytest.raises(ValueError, match="item 3 is bad"):
        for _ in parallel.map_threads(slow_square, list(range(3, 200)), 2):
            pass
    assert len(started) < 20
