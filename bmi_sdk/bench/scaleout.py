"""`bmi bench scaleout --scheduler local:1 --scheduler local:2`: throughput of the two jobs that fan out on Dask.

* **Training-cache rendering** (``nn.data.build_cache``): pairs rendered per second into a fresh cache.
* **Frame decoding** (``runtime.batch.run_batch``, the ``bmi infer`` batch): frames per second over ROI
  captures of the simulated camera, decoded by the packaged default model.

Each job runs once in this process (the baseline, as without ``--scheduler``) and once per scheduler given.
The cluster's start-up (worker processes, imports) is timed apart from the job: "job s" is the fan-out
alone, the throughput is work / job s, and "start s" is what a one-off run pays on top. "CPU s" is the
CPU time the job used in this process and in the workers; "cores got" = CPU s / job s says how much of
the machine the job actually had (on a shared machine, less than its workers could use). The PSF tensor
is built before the first measurement (a per-machine cost, shared through the disk cache).
"""

from __future__ import annotations

import os
import resource
import shutil
import sys
import time
from pathlib import Path

from ..option_values import size_hw, whole
from . import add_json_argument, check_record_path


def _process_cpu_s() -> float:
    """CPU seconds of the calling process (run here and, through ``client.run``, on each worker)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _cpu_s(client) -> float:
    """CPU seconds of this process plus every worker of ``client`` so far."""
    return _process_cpu_s() + (0.0 if client is None else sum(client.run(_process_cpu_s).values()))


def register(subparsers) -> None:
    p = subparsers.add_parser("scaleout", help="cache rendering and frame decoding throughput in-process vs on Dask",
                              description=__doc__)
    p.add_argument("--scheduler", action="append", default=None, metavar="local:N|tcp://HOST:PORT",
                   help="a scheduler to measure (repeatable; default local:1 and local:2); in-process is always run")
    p.add_argument("--samples", type=whole(1, 100000), default=32, help="pairs rendered per cache run (default 32)")
    p.add_argument("--crop", type=whole(16, 1024, unit="px", multiple_of=4), default=64,
                   help="training crop in pixels (default 64)")
    p.add_argument("--shard-samples", type=whole(1), default=4, help="pairs a shard (task) holds (default 4)")
    p.add_argument("--frames", type=whole(1, 1000), default=4, help="frames decoded per run (default 4)")
    p.add_argument("--frame-px", type=size_hw(64, 6000, multiple_of=2), default="1024x1536",
                   help="H×W of each ROI capture (default 1024x1536)")
    p.add_argument("--work-dir", default="out/bench_scaleout")
    add_json_argument(p)
    p.set_defaults(handler=_run)


def _frames(work: Path, count: int, height_px: int, width_px: int) -> list[Path]:
    """``count`` ROI captures of the simulated camera's chart scene at different sensor positions (kept)."""
    from devices import Roi, open_camera

    folder = work / f"frames_{height_px}x{width_px}"
    paths = []
    for i in range(count):
        path = folder / f"frame_{i:02d}.dng"
        if not path.is_file():
            with open_camera(f"sim://bench-scaleout?scene=chart&seed={i}") as cam:
                cam.settings.roi = Roi(1000 + 600 * (i % 4), 800 + 500 * (i // 4 % 4), width_px, height_px)
                cam.capture(timeout_s=300).save_dng(path)
        paths.append(path)
    return paths


def _timed_on(scheduler: str | None, job) -> tuple[float, float, float]:
    """(start s, job s, CPU s): the cluster's start-up, and the job run on it (``job(client)``)."""
    from bmi_sdk.scaleout import open_client

    t0 = time.perf_counter()
    with open_client(scheduler, announce=False) as client:
        cpu0 = _cpu_s(client)  # also: every worker is up and answering
        t1 = time.perf_counter()
        job(client)
        t2 = time.perf_counter()
        cpu_s = _cpu_s(client) - cpu0
    return t1 - t0, t2 - t1, cpu_s


def _cache_row(args, work: Path, scheduler: str | None) -> list:
    from bmi_sdk.nn.data import CacheSpec, build_cache

    spec = CacheSpec(samples=args.samples, crop_px=args.crop, seed=11)
    target = work / "cache_run"
    shutil.rmtree(target, ignore_errors=True)

    def job(client):  # build_cache connects to the cluster started (and timed) here by its address
        address = None if client is None else client.scheduler_info()["address"]
        build_cache(target, spec, progress=False, scheduler=address, shard_samples=args.shard_samples)

    start_s, job_s, cpu_s = _timed_on(scheduler, job)
    shutil.rmtree(target, ignore_errors=True)
    return ["cache rendering", scheduler or "in-process", f"{args.samples} pairs", start_s, job_s, cpu_s,
            cpu_s / job_s, f"{args.samples / job_s:.2f} pairs/s"]


def _infer_row(args, work: Path, frames: list[Path], scheduler: str | None) -> list:
    from bmi_sdk.runtime.batch import DecodeOptions, run_batch

    out = work / "infer_run"
    shutil.rmtree(out, ignore_errors=True)
    jobs = [(f, out / f.stem) for f in frames]
    failures = []

    def job(client):
        failures.extend(s for s in run_batch(jobs, DecodeOptions(), client=client, progress=False) if not s["ok"])

    start_s, job_s, cpu_s = _timed_on(scheduler, job)
    shutil.rmtree(out, ignore_errors=True)
    if failures:
        raise ValueError(f"decoding failed: {failures[0]['error']}")
    height_px, width_px = args.frame_px
    return ["frame decoding", scheduler or "in-process", f"{len(frames)} frames of {height_px}x{width_px} px", start_s,
            job_s, cpu_s, cpu_s / job_s, f"{len(frames) / job_s:.3f} frames/s"]


def _run(args) -> int:
    from bmi_sdk.bench import emit, markdown_table
    from bmi_sdk.lenses import DEFAULT_LENS, lens_tensor
    from bmi_sdk.runtime.decoders import DEFAULT_DECODER
    from bmi_sdk.scaleout import parse_scheduler

    check_record_path(args.json, args.overwrite)

    schedulers = args.scheduler or ["local:1", "local:2"]
    for s in schedulers:
        parse_scheduler(s)
    height_px, width_px = args.frame_px
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    lens_tensor(DEFAULT_LENS).ensure_all(progress=True)
    frames = _frames(work, args.frames, height_px, width_px)
    rows = []
    for scheduler in [None, *schedulers]:
        rows += [_cache_row(args, work, scheduler), _infer_row(args, work, frames, scheduler)]
        for row in rows[-2:]:
            print(f"{row[0]} on {row[1]}: {row[-1]}", file=sys.stderr, flush=True)  # progress
    rows.sort(key=lambda r: r[0])
    text = markdown_table(["job", "where", "work", "start s", "job s", "CPU s", "cores got", "throughput"], rows)
    text += (f"\n\nIn-process: cache shards in this one process, frames decoded with onnxruntime on all "
             f"{os.cpu_count()} cores (the `bmi infer` default); local:N: N worker processes of one thread each. "
             f"Cache: crop {args.crop} px, {args.shard_samples} pairs a shard; frames: ROI captures of the "
             f"simulated camera, the default ({DEFAULT_DECODER}) decoder, 512-px tiles.")
    emit(text, args.json, args.overwrite)
    return 0
