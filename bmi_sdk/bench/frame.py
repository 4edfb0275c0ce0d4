"""`bmi bench frame`: the whole `bmi infer` command on one raw frame, a camera's first frame and its next.

Each run is the command a user types, ``bmi infer FRAME --out DIR --ply-step 4 [--calibration C]``, in its own
process: reading, decoding, writing the outputs and the point cloud all count. Per camera (the design, and the
calibrated one when ``--calibration`` is given) the PSF cache starts empty (a new ``BMI_CACHE_DIR``): the first
run traces every zone kernel the frame reads, the second reads them back. The table gives each run's wall
time, its peak resident memory (``os.wait4``: the process's own, with any workers it waited for), the one-minute
load average just before it (wall times scale with it), the decode's stages from its ``report.json`` and the
kernel sets it traced. The outputs and the caches are deleted afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import add_json_argument, check_record_path, emit, markdown_table

RUNS = ("first frame", "next frame")
"""The runs per camera, in order: the first fills the empty PSF cache, the next reads it."""


def register(subparsers) -> None:
    p = subparsers.add_parser("frame", help="whole bmi infer command on one frame: a camera's first frame and its next",
                              description=__doc__)
    p.add_argument("frame", metavar="RAW.dng", help="the frame to decode (e.g. bmi simulate --procedural 5 "
                                                    "--full-frame --psf-mode tensor --noise 0.005 --out full.dng)")
    p.add_argument("--calibration", default=None, metavar="C.json",
                   help="also time the camera this calibration describes (bmi calibrate --out C.json)")
    p.add_argument("--decoder", default=None, help="bmi infer's --decoder (default: its default)")
    p.add_argument("--texture-exponent", default=None, help="bmi infer's --texture-exponent (default: its default)")
    add_json_argument(p)
    p.set_defaults(handler=_run)


def _run(args) -> int:
    check_record_path(args.json, args.overwrite)
    frame = Path(args.frame)
    if not frame.is_file():
        raise FileNotFoundError(f"RAW.dng {frame}: no such file")
    cameras = [("design", [])]
    if args.calibration is not None:
        if not Path(args.calibration).is_file():
            raise FileNotFoundError(f"--calibration {args.calibration}: no such file")
        cameras.append(("calibrated", ["--calibration", str(Path(args.calibration).resolve())]))
    extra = [] if args.decoder is None else ["--decoder", args.decoder]
    extra += [] if args.texture_exponent is None else ["--texture-exponent", args.texture_exponent]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bmi-bench-frame-") as work:
        for name, camera_args in cameras:
            cache = Path(work) / f"cache-{name}"
            cache.mkdir()
            for run in RUNS:
                out = Path(work) / "out"
                rows.append([name, run, *_timed_infer(frame.resolve(), out, cache, camera_args + extra)])
                shutil.rmtree(out)
    text = "\n".join([
        f"### The whole bmi infer command on {frame.name}",
        "",
        f"Each run: `bmi infer FRAME --out DIR --ply-step 4 [--calibration C]{''.join(' ' + a for a in extra)}` in a "
        "new process; first frame: the "
        "camera's PSF cache empty, next frame: filled by the first. load: the one-minute load average before the "
        "run. Stages from the run's report.json.",
        "",
        markdown_table(["camera", "run", "load before", "whole command s", "peak RSS GB", "evidence stage s",
                        "kernel sets traced", "AiF s", "writing s"], rows),
    ])
    emit(text, args.json, args.overwrite)
    return 0


def _timed_infer(frame: Path, out: Path, cache: Path, extra: list[str]) -> list:
    """[load before, wall s, peak RSS GB, evidence stage s, kernel sets traced, AiF s, writing s] of one run."""
    command = [sys.executable, "-m", "bmi_sdk.cli", "-q", "infer", str(frame), "--out", str(out), "--ply-step", "4",
               *extra]
    load = round(os.getloadavg()[0], 2)
    env = {**os.environ, "BMI_CACHE_DIR": str(cache)}
    start = time.perf_counter()
    with tempfile.TemporaryFile() as stderr:
        process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=stderr)
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        wall_s = time.perf_counter() - start
        if process.returncode != 0:  # its own one-line error names the problem (a bad frame, option or file)
            stderr.seek(0)
            lines = stderr.read().decode(errors="replace").strip().splitlines() or ["(no message)"]
            raise ValueError(f"bmi infer {frame.name} exited {process.returncode}: {lines[-1].strip()}")
    report = json.loads((out / "report.json").read_text())
    timings, stages = report.get("timings_s", {}), report.get("stage_timings_s", {})
    traced = report.get("decoder_stats", {}).get("kernel_sets_traced")
    return [load, round(wall_s, 1), round(usage.ru_maxrss * 1024 / 1e9, 2), _seconds(timings.get("evidence_s")),
            traced, _seconds(timings.get("aif_s")), _seconds(stages.get("write_outputs_s"))]


def _seconds(value) -> float | None:
    return None if value is None else round(float(value), 1)
