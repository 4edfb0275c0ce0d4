"""`bmi bench device`: full-resolution frame rate through pack → TCP loopback → unpack → CRC, host CPU and
memory per frame, and the time to simulate one full-resolution frame.

The firmware runs in a separate process (`bmi firmware-sim serve`) so the host
figures are the host's alone. The transport run uses the digital walking-ramp
test pattern (the device still packs RAW12 and computes the CRC every frame) so
that it measures the link, not the sensor simulation, which is timed on its own.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import time

from ..option_values import whole
from . import add_json_argument, check_record_path, emit


def register(subparsers) -> None:
    p = subparsers.add_parser("device", help="camera link frame rate, host CPU/memory per frame, simulated frame time")
    p.add_argument("--frames", type=whole(1, 10000), default=20, help="full-resolution frames to stream over TCP")
    p.add_argument("--sim-frames", type=whole(1, 1000), default=3,
                   help="full-resolution frames to simulate (per scene)")
    add_json_argument(p)
    p.set_defaults(handler=_run)


def _serve():
    proc = subprocess.Popen([sys.executable, "-m", "bmi_sdk.cli", "firmware-sim", "serve", "--port", "0",
                             "--scene", "flat", "--duration-s", "600"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    line = proc.stdout.readline()
    if " on tcp://" not in line:
        proc.kill()
        raise RuntimeError(f"firmware-sim serve did not start: {line!r}")
    return proc, line.rsplit(" on ", 1)[1].strip()


def _run(args) -> int:
    from bmi_sdk.protocol.wire import pack12, unpack12
    from devices import open_camera
    from firmware_sim import FirmwareDevice, make_source

    check_record_path(args.json, args.overwrite)

    proc, uri = _serve()
    try:
        with open_camera(uri, timeout_s=30) as cam:
            cam.settings.test_pattern = 2
            cam.start("oldest_first", buffers=2)
            cam.grab(timeout_s=30).release()  # warm-up
            rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            cpu0, t0 = time.process_time(), time.perf_counter()
            bad = 0
            for _ in range(args.frames):
                with cam.grab(timeout_s=30) as f:
                    bad += not f.complete
            wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
            rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            cam.stop()
            stats = dict(cam.stats)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    mb = 6000 * 4500 * 1.5 / 1e6
    lines = ["## Device link: 6000×4500 RAW12 over TCP loopback (firmware in its own process)",
             "| frames | fps | MB/s (payload) | host CPU s/frame | host peak RSS MB | incomplete/corrupt | lost |",
             "|---|---|---|---|---|---|---|"]
    lines.append(f"| {args.frames} | {args.frames / wall:.2f} | {args.frames * mb / wall:.0f} | {cpu / args.frames:.3f} "
          f"| {rss1 / 1024:.0f} (grew {max(0, rss1 - rss0) / 1024:.0f} while streaming) | {bad} | {stats['lost']} |")
    lines += ["", "## Simulated full-resolution frame (in process, one core of numpy)",
              "| scene | readout s/frame (irradiance → noise → ADC) | RAW12 pack s | unpack s |", "|---|---|---|---|"]
    import numpy as np

    for scene in ("flat", "chart"):
        dev = FirmwareDevice(source=make_source(scene))
        dev.read_out()  # first frame also builds the cos θ table for the window
        t0 = time.perf_counter()
        for _ in range(args.sim_frames):
            res = dev.read_out()
        t_read = (time.perf_counter() - t0) / args.sim_frames
        t0 = time.perf_counter()
        packed = pack12(res.pixels)
        t_pack = time.perf_counter() - t0
        out = np.empty_like(res.pixels)
        t0 = time.perf_counter()
        unpack12(packed, out)
        t_unpack = time.perf_counter() - t0
        lines.append(f"| {scene} | {t_read:.2f} | {t_pack:.3f} | {t_unpack:.3f} |")
    emit("\n".join(lines), args.json, args.overwrite)
    return 0
