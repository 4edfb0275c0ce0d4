"""Scale-out on Dask (bmi_sdk.scaleout): the --scheduler values, many frames decoded on a local cluster equal
to their serial decodes byte for byte, one model load per process, the training cache rendered on a cluster
equal to the serial cache, resumed after a crash, and complete after a worker is killed mid-run.

Everything runs on tiny inputs (ROI frames of 64×96 px, 16-px crops) and local clusters of single-threaded
worker processes that fixtures always close. Waits poll for a state, never sleep a fixed time.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from bmi_sdk.scaleout import SchedulerSpec, fan_out, open_client, parse_scheduler, publish_once

OUTPUT_FILES = ("aif.npy", "depth.npy", "aif.png", "aif_preview.png", "depth_mm.png", "depth_preview.png",
                "points.ply")
PATIENCE_S = 600.0
"""How long a poll may wait for a cluster to reach a state: only a safety net against a hung test; a loaded
2-core machine is slow, never that slow."""


def _wait_for(condition, what: str):
    deadline = time.monotonic() + PATIENCE_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.05)


# -- the option ---------------------------------------------------------------------------------------

def test_scheduler_values_parse_and_bad_ones_are_named():
    assert parse_scheduler(None) is None and parse_scheduler("") is None
    assert parse_scheduler("local:2") == SchedulerSpec(n_workers=2) and str(parse_scheduler("local:2")) == "local:2"
    assert parse_scheduler("tcp://10.0.0.5:8786") == SchedulerSpec(address="tcp://10.0.0.5:8786")
    for bad in ("local:0", "local:two", "local:", "tcp://host", "tcp://host:port", "10.0.0.5:8786", "http://h:1",
                "tcp://h:1/x"):
        with pytest.raises(ValueError, match="--scheduler"):
            parse_scheduler(bad)


def test_cli_refuses_a_bad_scheduler_with_a_usage_error(tmp_path):
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "infer", "x.dng", "--out", str(tmp_path),
                          "--scheduler", "local:zero"], capture_output=True, text=True, timeout=PATIENCE_S)
    assert run.returncode == 2 and "local:N needs a whole number" in run.stderr and "Traceback" not in run.stderr


def test_publish_once_never_replaces_a_published_file(tmp_path):
    target = tmp_path / "shard.bin"
    assert publish_once(target, lambda p: p.write_bytes(b"first"))
    calls = []
    assert not publish_once(target, lambda p: calls.append(p) or p.write_bytes(b"second"))
    assert target.read_bytes() == b"first" and not calls
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shard.bin"]  # no temporary left behind


# -- a cluster --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cluster():
    """A local cluster of two single-threaded worker processes, closed at the end of the module."""
    from distributed import LocalCluster

    c = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    yield c
    c.close()


def _square(state, item):
    return state["offset"] + item * item, os.getpid(), id(state)


def _state():
    return {"offset": 1000}


def test_fan_out_builds_state_once_per_worker_and_returns_items_in_order(cluster):
    from distributed import Client

    seen = []
    with Client(cluster.scheduler_address) as client:
        results = fan_out(_square, range(12), client=client, state=_state, progress=False,
                          on_result=lambda i, r: seen.append(i))
        worker_pids = set(client.run(os.getpid).values())
    assert [r[0] for r in results] == [1000 + i * i for i in range(12)]
    assert sorted(seen) == list(range(12))
    assert {r[1] for r in results} <= worker_pids and os.getpid() not in worker_pids
    states_per_pid = {pid: {r[2] for r in results if r[1] == pid} for pid in {r[1] for r in results}}
    assert all(len(ids) == 1 for ids in states_per_pid.values()), states_per_pid  # one state per worker
    serial = fan_out(_square, range(12), state=_state, progress=False)
    assert [r[0] for r in serial] == [r[0] for r in results] and len({(r[1], r[2]) for r in serial}) == 1
