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

from bmi_sdk.scaleout import SchedulerSpec, fan_out, parse_scheduler, publish_once

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
def psf_cache(tmp_path_factory):
    """A PSF disk cache of this module's own holding a complete *synthetic* tensor for the BMI lens
    (Gaussian blur growing with defocus from 2 m, a little with θ): these tests are about who renders
    which sample, not about optics, and the real tensor takes minutes to build. Set before the cluster
    starts, so its workers (and the CLI's) inherit it; the session's own cache is restored after."""
    from bmi_sdk.lenses import lens_tensor

    saved = os.environ.get("BMI_CACHE_DIR")
    root = tmp_path_factory.mktemp("synthetic_psf")
    os.environ["BMI_CACHE_DIR"] = str(root)
    tensor = lens_tensor("bmi_monocentric")
    k = tensor.spec.kernel_px
    yy, xx = np.mgrid[:k, :k] - (k - 1) / 2
    width_px = 0.6 + 2.0 * np.abs(np.log(tensor.depth_m / 2.0))[None, :] + 0.01 * tensor.field_deg[:, None]
    kernels = np.exp(-(yy ** 2 + xx ** 2) / (2 * width_px[..., None, None] ** 2))
    tensor.data[...] = (kernels / kernels.sum(axis=(-2, -1), keepdims=True))[None]
    tensor.filled[...] = True
    for i in range(len(tensor.spec.field_deg)):
        tensor._store_shard(i)
    yield root
    if saved is None:
        os.environ.pop("BMI_CACHE_DIR", None)
    else:
        os.environ["BMI_CACHE_DIR"] = saved
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(psf_cache):
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
        from bmi_sdk.scaleout.malloc import relax_malloc_trimming

        assert all(client.run(relax_malloc_trimming).values())  # the nanny's trimming is found and undone
    assert [r[0] for r in results] == [1000 + i * i for i in range(12)]
    assert sorted(seen) == list(range(12))
    assert {r[1] for r in results} <= worker_pids and os.getpid() not in worker_pids
    states_per_pid = {pid: {r[2] for r in results if r[1] == pid} for pid in {r[1] for r in results}}
    assert all(len(ids) == 1 for ids in states_per_pid.values()), states_per_pid  # one state per worker
    serial = fan_out(_square, range(12), state=_state, progress=False)
    assert [r[0] for r in serial] == [r[0] for r in results] and len({(r[1], r[2]) for r in serial}) == 1


# -- many frames ------------------------------------------------------------------------------------------

class TinyNet(nn.Module):
    """A small net on the model_io contract (random weights: the outputs only have to be compared)."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.a = nn.Conv2d(6, 8, 3, padding=1)
        self.o = nn.Conv2d(8, 4, 3, padding=1)

    def forward(self, x):
        o = self.o(torch.relu(self.a(x)))
        return x[:, :3] + 0.1 * o[:, :3], 0.7 + nn.functional.softplus(o[:, 3:])


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    from bmi_sdk.runtime import export_model

    return export_model(TinyNet(), tmp_path_factory.mktemp("model") / "tiny.onnx", preset="test-tiny")


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Three small ROI captures of the simulated camera, A/B/C.dng, in one folder."""
    from devices import Roi, open_camera

    folder = tmp_path_factory.mktemp("frames")
    for name, seed, x in (("A", 1, 2980), ("B", 2, 1200), ("C", 3, 4400)):
        with open_camera(f"sim://scale-{name}?scene=chart&seed={seed}") as cam:
            cam.settings.roi = Roi(x, 2240, 96, 64)
            cam.capture().save_dng(folder / f"{name}.dng")
    return folder


def _serial_decodes(model, frames, out: Path) -> None:
    from bmi_sdk.runtime import run_job

    for name in "ABC":
        run_job(frames / f"{name}.dng", out / name, model_path=model, tile_px=64, threads=1)


def _assert_same_outputs(got: Path, expected: Path) -> None:
    for name in "ABC":
        for f in OUTPUT_FILES:
            assert (got / name / f).read_bytes() == (expected / name / f).read_bytes(), f"{name}/{f}"
        report = json.loads((got / name / "report.json").read_text())
        assert report["model"]["sha256"] == json.loads((expected / name / "report.json").read_text())["model"]["sha256"]


def test_cli_decodes_three_frames_on_local_2_as_the_serial_decode_does(model, frames, tmp_path):
    _serial_decodes(model, frames, tmp_path / "serial")
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "infer", *(str(frames / f"{n}.dng") for n in "ABC"),
                          "--out", str(tmp_path / "dask"), "--model", str(model), "--tile-px", "64",
                          "--scheduler", "local:2", "--quiet"], capture_output=True, text=True, timeout=PATIENCE_S)
    assert run.returncode == 0, run.stderr
    assert "3 of 3 frames decoded" in run.stdout and "dask: local:2 — 2 workers" in run.stderr
    _assert_same_outputs(tmp_path / "dask", tmp_path / "serial")


def test_serial_batch_of_a_replay_opens_the_decoder_once_and_reports_a_bad_frame(model, frames, tmp_path,
                                                                                 monkeypatch):
    from bmi_sdk.runtime.batch import DecodeOptions, FrameDecoder, plan_outputs, run_batch

    _serial_decodes(model, frames, tmp_path / "serial")
    jobs = plan_outputs([f"replay://{frames}"], tmp_path / "batch")
    assert [(f.name, o.name) for f, o in jobs] == [("A.dng", "A"), ("B.dng", "B"), ("C.dng", "C")]
    opened = []
    original = FrameDecoder.decoder_for

    def counting(self, frame):
        opened.append(len(self.decoders))
        return original(self, frame)

    monkeypatch.setattr(FrameDecoder, "decoder_for", counting)
    summaries = run_batch(jobs, DecodeOptions(model_path=str(model), tile_px=64, threads=1), progress=False)
    assert opened == [0, 1, 1]  # the decoder (its model) was opened for the first frame and reused for the others
    assert all(s["ok"] for s in summaries)
    _assert_same_outputs(tmp_path / "batch", tmp_path / "serial")

    bad = tmp_path / "bad"
    bad.mkdir()
    shutil.copy(frames / "A.dng", bad / "A.dng")
    shutil.copy(frames / "A.json", bad / "A.json")  # the sidecar
    (bad / "B.dng").write_bytes(b"not a DNG")
    summaries = run_batch(plan_outputs([str(bad)], tmp_path / "out2"), DecodeOptions(model_path=str(model),
                          tile_px=64, threads=1), progress=False)
    assert [s["ok"] for s in summaries] == [True, False] and "B.dng" in summaries[1]["frame"]
    assert (tmp_path / "out2" / "A" / "report.json").is_file() and not (tmp_path / "out2" / "B").exists()


def test_batch_inputs_refused_clearly(frames, tmp_path):
    from bmi_sdk.runtime.batch import plan_outputs

    with pytest.raises(FileNotFoundError, match="no raw frame"):
        plan_outputs([str(tmp_path / "missing.dng")], tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="holds no .dng"):
        plan_outputs([str(tmp_path / "empty")], tmp_path)
    with pytest.raises(ValueError, match="once"):
        plan_outputs([f"replay://{frames}?loop=1"], tmp_path)
    with pytest.raises(ValueError, match="would both write"):
        plan_outputs([str(frames / "A.dng"), f"replay://{frames}"], tmp_path)
    assert plan_outputs([str(frames / "A.dng")], tmp_path / "o") == [(frames / "A.dng", tmp_path / "o")]


# -- the training cache -----------------------------------------------------------------------------------

CACHE_SPEC_KW = dict(samples=16, crop_px=16, jitter_px=2, seed=5)
SHARD = 2  # samples a shard: 8 shards, so a worker can be killed while shards are still to render


def _assert_same_cache(got: Path, expected: Path) -> None:
    names = sorted(p.name for p in expected.iterdir())
    assert sorted(p.name for p in got.iterdir()) == names  # no temporaries, nothing extra
    assert json.loads((got / "cache.json").read_text()) == json.loads((expected / "cache.json").read_text())
    for name in names:
        if name.endswith(".npz"):
            with np.load(got / name) as a, np.load(expected / name) as b:
                assert a.files == b.files
                for key in a.files:
                    np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}:{key}")


@pytest.fixture(scope="module")
def serial_cache(psf_cache, tmp_path_factory):
    from bmi_sdk.nn.data import CacheSpec, build_cache

    return build_cache(tmp_path_factory.mktemp("serial") / "cache", CacheSpec(**CACHE_SPEC_KW), progress=False,
                       shard_samples=SHARD)


def test_cache_rendered_on_a_cluster_survives_a_killed_worker_and_equals_the_serial_cache(cluster, serial_cache,
                                                                                          tmp_path):
    from distributed import Client

    from bmi_sdk.nn.data import CacheSpec, build_cache

    target = tmp_path / "cache"
    errors: list[BaseException] = []

    def build():
        try:
            build_cache(target, CacheSpec(**CACHE_SPEC_KW), progress=False, scheduler=cluster.scheduler_address,
                        shard_samples=SHARD)
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            errors.append(exc)

    inodes: dict[str, int] = {}

    def watch_shards() -> int:
        for p in target.glob("shard_*.npz"):
            ino = p.stat().st_ino
            assert inodes.setdefault(p.name, ino) == ino, f"{p.name} was written twice"
        return len(inodes)

    with Client(cluster.scheduler_address) as client:
        runner = threading.Thread(target=build)
        runner.start()
        try:
            busy: list[str] = []

            def rendering_started() -> bool:
                busy[:] = [w for w, keys in client.processing().items() if keys]
                return watch_shards() >= 1 and bool(busy) or not runner.is_alive()

            _wait_for(rendering_started, "the first shard")
            pids = client.run(os.getpid)
            assert runner.is_alive() and watch_shards() < 8, "the run ended before a worker could be killed"
            os.kill(pids[busy[0]], signal.SIGKILL)
            while runner.is_alive():
                watch_shards()
                runner.join(0.05)
        finally:
            runner.join()
        assert set(client.run(os.getpid).values()) != set(pids.values())  # the killed worker was replaced
    assert not errors, errors
    assert watch_shards() == 8
    _assert_same_cache(target, serial_cache)


def test_a_cache_run_that_died_resumes_and_a_different_sharding_is_refused(serial_cache, tmp_path):
    from bmi_sdk.nn.data import CacheSpec, build_cache

    target = tmp_path / "cache"
    shutil.copytree(serial_cache, target)
    (target / "shard_00003.npz").unlink()  # a run killed before it published shard 3 ...
    (target / ".shard_00003.npz.dead.npz").write_bytes(b"half")  # ... while writing it
    (target / ".shard_00004.npz.lost.npz").write_bytes(b"a lost race")
    before = {p.name: p.stat().st_ino for p in target.glob("shard_*.npz")}
    build_cache(target, CacheSpec(**CACHE_SPEC_KW), progress=False, shard_samples=SHARD)
    assert {p.name: p.stat().st_ino for p in target.glob("shard_*.npz") if p.name in before} == before
    _assert_same_cache(target, serial_cache)
    with pytest.raises(ValueError, match="3 samples a shard|samples a shard"):
        build_cache(target, CacheSpec(**CACHE_SPEC_KW), progress=False, shard_samples=3)


def test_a_cache_rendered_in_two_local_processes_equals_the_serial_cache(serial_cache, tmp_path):
    """``workers=2`` without a scheduler: spawned single-threaded processes (``parallel.map_jobs``), each with
    one renderer for all its shards, publish the serial cache's shards byte for byte and no temporaries."""
    from bmi_sdk.nn.data import CacheSpec, build_cache

    build_cache(tmp_path / "cache", CacheSpec(**CACHE_SPEC_KW), progress=False, workers=2, shard_samples=SHARD)
    _assert_same_cache(tmp_path / "cache", serial_cache)


def test_a_refinement_cache_decoded_in_two_local_processes_equals_the_serial_one(psf_cache, tmp_path):
    """The classical decode of the render shards, one decoder per process: in 2 spawned processes
    (``parallel.map_jobs``) it stores the same raw frames (noise drawn per pair index) and σ as in this one,
    and the same classical channels to float16 rounding (numpy runs one BLAS thread in a pool's process,
    several here, and sums in another order)."""
    from bmi_sdk.nn.data import CacheSpec, build_cache
    from bmi_sdk.nn.refine_data import RefineSpec, build_refine_cache

    renders = build_cache(tmp_path / "serial", CacheSpec(samples=3, crop_px=48, jitter_px=4, seed=3),
                          progress=False, shard_samples=1)
    shutil.copytree(renders, tmp_path / "pooled")
    refine = RefineSpec(decoder={"candidates": 12})
    serial = build_refine_cache(renders, refine, workers=1, progress=False)
    pooled = build_refine_cache(tmp_path / "pooled", refine, workers=2, progress=False)
    assert sorted(p.name for p in pooled.iterdir()) == sorted(p.name for p in serial.iterdir())
    for path in serial.glob("shard_*.npz"):
        with np.load(path) as a, np.load(pooled / path.name) as b:
            assert a.files == ["raw", "features", "sigma"] == b.files
            assert np.array_equal(a["raw"], b["raw"]) and np.array_equal(a["sigma"], b["sigma"]), path.name
            np.testing.assert_allclose(b["features"].astype(np.float32), a["features"].astype(np.float32),
                                       rtol=2 ** -8, atol=2 ** -8, err_msg=path.name)


def test_cli_train_renders_its_cache_on_local_2_as_the_serial_cache(psf_cache, tmp_path):
    from bmi_sdk.nn.data import CacheSpec, build_cache

    spec = CacheSpec(samples=4, crop_px=16, seed=3)
    serial = build_cache(tmp_path / "serial", spec, progress=False)
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "train", "--preset", "tiny", "--steps", "1",
                          "--batch", "2", "--samples", "4", "--crop", "16", "--seed", "3", "--threads", "1",
                          "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "dask"), "--no-export",
                          "--scheduler", "local:2"], capture_output=True, text=True, timeout=PATIENCE_S)
    assert run.returncode == 0, run.stderr
    assert "dask: local:2 — 2 workers" in run.stderr and (tmp_path / "run" / "checkpoint.pt").is_file()
    _assert_same_cache(tmp_path / "dask", serial)


def test_eval_benchmark_tiles_rendered_on_a_cluster_equal_the_in_process_renders(cluster):
    from dataclasses import replace

    from bmi_sdk.lenses import lens_tensor
    from bmi_sdk.nn.evaluate import Benchmark

    bench = Benchmark(tiles=2, tile_px=32, seed=4)
    here = bench.renders(lens_tensor(bench.lens))
    there = replace(bench, scheduler=cluster.scheduler_address).renders(lens_tensor(bench.lens))
    assert [(r["region"], r["tile"], r["row0"], r["col0"]) for r in there] == \
        [(r["region"], r["tile"], r["row0"], r["col0"]) for r in here] and len(here) == 4
    for a, b in zip(here, there):
        for key in ("optical_full", "rgb", "range_m"):
            np.testing.assert_array_equal(a[key], b[key])
