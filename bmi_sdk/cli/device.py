"""`bmi acquire` (frames from a camera to DNG files) and `bmi firmware-sim serve` (a simulated camera on TCP)."""

from __future__ import annotations

import logging
import sys
import time

from ..option_values import SEED, OptionError, number, whole
from ._logging import bars_shown


def register(subparsers) -> None:
    acq = subparsers.add_parser("acquire", help="grab raw frames from a camera and write them as DNG + JSON sidecar")
    acq.add_argument("--device", default="sim://",
                     help="camera URI: sim://, tcp://127.0.0.1:PORT[?token_file=F], tcp://[::1]:PORT, replay://DIR")
    acq.add_argument("--count", type=whole(1, MAX_COUNT), default=1,
                     help=f"frames to write (1 … {MAX_COUNT}; checked against the free disk space first)")
    acq.add_argument("--out", required=True,
                     help="output folder; files are frame_<UTC start of the run>_<frame id>.dng, and an "
                          "existing file is never replaced")
    acq.add_argument("--scene", help="scene for sim:// (flat, flat:0.3, dark, chart, image:PATH, or a registered one)")
    acq.add_argument("--exposure-us", type=int, help="exposure time in µs")
    acq.add_argument("--gain", type=float, help="analog gain (×)")
    acq.add_argument("--roi", help="readout window X,Y,WIDTH,HEIGHT in px (even values)")
    acq.add_argument("--timeout-s", type=number(0, 86400, lo_open=True, unit="s"), default=30.0,
                     help="give up when no frame arrives for this long (s)")
    acq.set_defaults(handler=_acquire)

    fw = subparsers.add_parser("firmware-sim", help="the simulated camera firmware")
    fw_sub = fw.add_subparsers(dest="fw_command", metavar="COMMAND")
    serve = fw_sub.add_parser("serve", help="serve a simulated camera on TCP (loopback only)")
    serve.add_argument("--port", type=whole(0, 65535), default=0, help="TCP port (0: pick a free one and print it)")
    serve.add_argument("--host", default="127.0.0.1", help="loopback address to bind (127.0.0.1, ::1)")
    serve.add_argument("--scene", default="chart", help="what the camera sees (flat, dark, chart, image:PATH…)")
    serve.add_argument("--seed", type=SEED, default=0, help="noise seed (0 … 2³²−1)")
    serve.add_argument("--serial", type=whole(0, 2**32 - 1), default=1, help="device serial number (0 … 2³²−1)")
    serve.add_argument("--faults", default="", help="fault plan, e.g. seed=1,drop=0.05,corrupt=0.02,stall_s=0.2")
    serve.add_argument("--duration-s", type=number(0, unit="s"), default=0,
                       help="stop after this long, in s (0: until Ctrl-C or SIGTERM)")
    serve.add_argument("--token-file", help="file holding a shared token; hosts must send it "
                                            "(tcp://HOST:PORT?token_file=F or ?token=…)")
    serve.add_argument("--idle-timeout-s", type=number(0, 86400, lo_open=True, unit="s"), default=None,
                       help="drop a host that sends no whole message for this long while no frames stream to it "
                            "(default 60; hosts that wait send PING)")
    serve.set_defaults(handler=_serve)
    fw.set_defaults(handler=lambda args: fw.print_help() or 2)


MAX_COUNT = 100_000
"""Most frames one ``bmi acquire`` writes: a day at one frame a second; more is a typo (``--count 1e9``)."""
SIDECAR_BYTES = 8192
"""Room one frame's sidecar and DNG tags take beside its pixels (about 3 KB each; rounded up)."""


def _frame_bytes(roi) -> int:
    """Disk space of one frame: 16-bit pixels, the DNG's tags and the JSON sidecar."""
    return roi.width_px * roi.height_px * 2 + SIDECAR_BYTES


def _check_disk(out, count: int, roi) -> None:
    """Refuse a run whose frames (``count`` of ``roi``) would not fit the free space of ``out``'s disk."""
    import shutil

    planned = count * _frame_bytes(roi)
    free = shutil.disk_usage(out).free
    if planned > free:
        raise OptionError(f"--count {count}: {count} frames of {roi.width_px}×{roi.height_px} px need about "
                          f"{planned / 1e9:.2f} GB; {out} has {free / 1e9:.2f} GB free (lower --count or --roi)",
                          "--count")


def _apply_settings(cam, args) -> None:
    """--exposure-us, --gain and --roi onto the camera; a value it refuses names its option."""
    from devices import ConfigurationError, Roi

    for option, name, value in (("--exposure-us", "exposure_us", args.exposure_us),
                                ("--gain", "analog_gain", args.gain)):
        if value is not None:
            try:
                setattr(cam.settings, name, value)
            except ConfigurationError as exc:
                raise OptionError(f"{option} {value}: {exc}", option) from None
    if args.roi:
        usage = "--roi takes X,Y,WIDTH,HEIGHT in px (even values, inside the sensor)"
        try:
            values = [int(v) for v in args.roi.split(",")]
        except ValueError:
            raise OptionError(f"{usage}, got {args.roi!r}", "--roi") from None
        if len(values) != 4:
            raise OptionError(f"{usage}, got {args.roi!r}", "--roi")
        try:
            cam.settings.roi = Roi(*values)
        except ConfigurationError as exc:
            raise OptionError(f"--roi {args.roi}: {exc}", "--roi") from None


def _open_device(uri: str, args):
    """The camera of ``--device`` (with ``--scene``). A value no camera could have is refused naming its option:
    an unknown URI scheme or a malformed URI names ``--device``, a scene the simulator does not know names
    ``--scene``. A camera that does not answer (``DeviceNotFoundError``) or is busy is the device's state, not
    the option's, and reaches the user as its own one-line error."""
    from urllib.parse import urlsplit

    from devices import ConfigurationError, open_camera

    if urlsplit(args.device).scheme not in ("sim", "tcp", "replay"):
        raise OptionError(f"--device {args.device}: a camera URI is sim://, tcp://HOST:PORT or replay://DIR",
                          "--device")
    try:
        return open_camera(uri)
    except (ConfigurationError, ValueError) as exc:
        if args.scene and "scene" in str(exc):
            raise OptionError(f"--scene {args.scene}: {exc}", "--scene") from None
        raise OptionError(f"--device {args.device}: {exc}", "--device") from None


def _acquire(args) -> int:
    import errno
    from pathlib import Path
    from urllib.parse import urlsplit

    from tqdm import tqdm

    from devices import GrabTimeoutError, ReplayCamera

    from ._options import check_writable_folder

    uri = args.device
    scheme = urlsplit(uri).scheme
    if args.scene:
        if scheme != "sim":
            raise OptionError("--scene only applies to sim:// (a TCP server chooses its scene: "
                              "bmi firmware-sim serve --scene)", "--scene")
        uri += ("&" if "?" in uri else "?") + f"scene={args.scene}"
    elif scheme == "sim" and "scene=" not in uri:
        print("sim:// shows its calibration chart; to capture a scene give --scene image:PATH (or flat, dark, "
              "chart), or render an RGB + depth scene with bmi simulate")
    out = Path(args.out)
    check_writable_folder("--out", out)
    run_stamp = _run_stamp()
    written = bad = patterns = 0
    disk_full = None
    with _open_device(uri, args) as cam:
        _apply_settings(cam, args)
        _check_disk(out, args.count, cam.settings.roi)
        cam.start("oldest_first", buffers=4)
        try:
            with tqdm(total=args.count, desc="acquire", unit="frame", disable=not bars_shown()) as bar:
                while written < args.count:
                    try:
                        frame = cam.grab(timeout_s=args.timeout_s)
                    except GrabTimeoutError:
                        if isinstance(cam, ReplayCamera):  # the folder played to its end
                            break
                        raise TimeoutError(f"no frame for {args.timeout_s} s after {written} written") from None
                    with frame:
                        if not frame.complete:
                            bad += 1
                            continue
                        path = out / f"frame_{run_stamp}_{frame.frame_id:08d}.dng"
                        try:
                            frame.save_dng(path)
                        except OSError as exc:
                            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                                raise
                            path.unlink(missing_ok=True)  # a DNG whose sidecar found no room (new: never a kept one)
                            disk_full = exc
                            break
                        patterns += frame.test_pattern
                    written += 1
                    bar.update(1)
        finally:
            cam.stop()
        stats = dict(cam.stats)
        skipped = list(cam.skipped) if isinstance(cam, ReplayCamera) else []
    print(f"wrote {written} DNG files to {out} (skipped {bad} incomplete/corrupt; link stats {stats})")
    log = logging.getLogger("bmi.acquire")
    if patterns:
        log.warning(f"{patterns} of {written} frames are the digital test pattern, "
                    "not the scene (TEST_PATTERN register set on the device)")
    if disk_full is not None:
        log.error(f"the disk holding {out} is full ({disk_full.strerror}): stopped after {written} of {args.count} "
                  "frames; every file written is whole")
        return 1
    if skipped:
        log.error(f"{len(skipped)} unreadable file{'s' if len(skipped) > 1 else ''} skipped: "
                  + "; ".join(f"{p.name} ({why})" for p, why in skipped))
        return 1
    if written < args.count:
        log.error(f"{uri} played {written} of the {args.count} frames asked for")
        return 1
    return 0


def _run_stamp() -> str:
    """The run's start, UTC to the millisecond, for file names: frame ids restart in every device session,
    so ids alone would make a second run into the same folder reuse the first run's names."""
    now_ns = time.time_ns()
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime(now_ns // 1_000_000_000)) + \
        f"{now_ns // 1_000_000 % 1000:03d}Z"


def _read_token(path: str) -> bytes:
    """The shared token in ``path`` (surrounding whitespace dropped); refuses an empty or oversize one."""
    import os
    from pathlib import Path

    from bmi_sdk.protocol.wire import MAX_TOKEN_BYTES

    try:
        token = Path(path).read_bytes().strip()
    except OSError as exc:
        raise OptionError(f"--token-file {path}: cannot read it ({exc.strerror or exc})", "--token-file") from None
    if not token:
        raise ValueError(f"--token-file {path} is empty: an empty token protects nothing")
    if len(token) > MAX_TOKEN_BYTES:
        raise ValueError(f"--token-file {path} holds {len(token)} bytes; a token is at most {MAX_TOKEN_BYTES}")
    if os.stat(path).st_mode & 0o077:
        logging.getLogger("bmi.firmware-sim").warning(f"--token-file {path} can be read by other users (chmod 600 it)")
    return token


def _serve(args) -> int:
    from bmi_sdk.protocol.wire import DEFAULT_IDLE_TIMEOUT_S
    from firmware_sim import FaultPlan, FirmwareDevice, FirmwareServer, make_source

    token = _read_token(args.token_file) if args.token_file else None
    try:
        faults = FaultPlan.parse(args.faults) if args.faults else None
    except ValueError as exc:
        raise OptionError(f"--faults {args.faults}: {exc}", "--faults") from None
    device = FirmwareDevice(source=make_source(args.scene), seed=args.seed, serial=args.serial, faults=faults)
    idle_s = DEFAULT_IDLE_TIMEOUT_S if args.idle_timeout_s is None else args.idle_timeout_s
    with FirmwareServer(device, host=args.host, port=args.port, token=token, idle_timeout_s=idle_s) as server:
        _stop_on_signals()  # once it serves: a refused port or token leaves the caller's handlers alone
        deadline = time.monotonic() + args.duration_s if args.duration_s > 0 else None
        try:  # from the line that tells hosts where it serves, a stop signal stops it cleanly
            print(f"serving {device.describe()['serial']} ({args.scene}{', token required' if token else ''}) "
                  f"on {server.uri}", flush=True)
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
        except KeyboardInterrupt:  # Ctrl-C is how a server is stopped: report, do not call it a failure
            pass
    print(f"stopped; faults injected: {device.injector.counts()}", file=sys.stderr)
    return 0


def _stop_on_signals() -> None:
    """Make Ctrl-C (SIGINT) and a service manager's SIGTERM stop the server the same way (close, then the fault
    summary). Python installs its SIGINT handler only where SIGINT is not ignored at start, and a job started in
    the background of a script (``serve … &``) inherits it ignored: such a server could not be stopped cleanly."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, stop)
