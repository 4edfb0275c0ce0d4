"""Scale-out on Dask distributed: the ``--scheduler`` option of ``bmi infer``, ``bmi train``, ``bmi eval`` and
``bmi bench``.

    with open_client("local:2") as client:        # or "tcp://HOST:8786", or None for in-process
        for item, result in fan_out(task, items, client=client, state=factory, desc="frames"):
            ...

* ``scheduler`` — parse ``local:N`` / ``tcp://HOST:PORT`` (``parse_scheduler``) and add the option to a parser;
* ``client`` — a ``LocalCluster`` of N single-threaded worker processes, or a connection to a running scheduler
  (``scheduler_address``: one local cluster for a job that connects several times);
* ``fanout`` — run ``task(state, item)`` over items, serially or on the workers, with one progress bar; the
  per-process ``state`` (a loaded model, PSF kernels) is built once per worker by a worker plugin;
* ``once`` — publish a file under its final name at most once (re-run tasks never write a result twice);
* ``malloc`` — undo the nanny's glibc memory trimming, which doubles the CPU time of these jobs.

``distributed`` is imported only when a scheduler is asked for. How to run on a real cluster: docs/scale-out.md.
"""

from .client import open_client, scheduler_address
from .fanout import WorkerLostError, fan_out
from .once import publish_once
from .scheduler import SchedulerSpec, add_scheduler_argument, parse_scheduler

__all__ = ["open_client", "scheduler_address", "fan_out", "WorkerLostError", "publish_once", "SchedulerSpec", "parse_scheduler",
           "add_scheduler_argument"]
