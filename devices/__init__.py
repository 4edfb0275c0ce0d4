"""Host camera API of the BMI camera.

    from devices import open_camera
    with open_camera("sim://") as cam:            # or "tcp://127.0.0.1:PORT", "replay://FOLDER"
        cam.settings.exposure_us = 5000
        frame = cam.capture()                      # RawFrame: uint16 H×W + metadata
        frame.save_dng("frame.dng")

URIs:

* ``sim://[NAME][?scene=SPEC&seed=N&faults=SPEC&serial=N]`` — a simulated camera
  in this process (``firmware_sim``, imported only when a ``sim://`` camera is
  opened: ``devices.sim``), served over an in-process socket pair with
  the same protocol as TCP. A named device lives as long as the process, like a
  plugged-in camera (its scene, frame counter and fault ledger persist between
  opens; the registers a host writes return to defaults when it closes, see
  docs/protocol.md); giving ``seed``,
  ``faults`` or ``serial`` builds it anew, ``scene`` (see
  ``firmware_sim.make_source``) loads a scene into it. ``open_camera(uri,
  device=FirmwareDevice(...))`` serves a device you built.
* ``tcp://HOST:PORT[?token=T | ?token_file=PATH]`` — a device served by
  ``bmi firmware-sim serve`` (or hardware); an IPv6 literal as ``tcp://[::1]:PORT``
  (``tcp://::1:PORT`` is read too: the last colon starts the port). ``token`` is
  the shared secret of ``serve --token-file``; ``token_file`` reads it from a
  file, which keeps it out of command lines that ``ps`` shows.
* ``replay://FOLDER[?loop=1]`` — a folder of DNGs written by ``RawFrame.save_dng``.

The wire format and register map come from ``bmi_sdk.protocol``, which the
device side shares; importing this package loads neither the simulator nor the
optics or the renderer.
"""

from __future__ import annotations

import ipaddress
import socket
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from bmi_sdk.protocol.wire import MAX_TOKEN_BYTES, MODEL_NAME, tcp_uri

from .camera import STRATEGIES, StreamCamera
from .camera_protocol import Camera
from .dng import load_raw, save_dng
from .errors import (
    AccessDeniedError,
    CameraError,
    ConfigurationError,
    DeviceBusyError,
    DeviceFaultError,
    DeviceNotFoundError,
    DeviceRemovedError,
    GrabTimeoutError,
    IncompleteFrameError,
    NoiseProfileWarning,
    ProtocolError,
    RawFileError,
)
from .frame import FrameStatus, RawFrame, Roi
from .replay import ReplayCamera
from .sim import DEFAULT_NAME as _SIM_DEFAULT_NAME
from .sim import open_sim, sim_devices

__all__ = [
    "Camera",
    "open_camera", "list_devices", "parse_tcp_address", "DeviceInfo", "StreamCamera", "ReplayCamera", "RawFrame",
    "FrameStatus", "Roi", "load_raw", "save_dng", "STRATEGIES", "AccessDeniedError", "CameraError",
    "ConfigurationError", "DeviceBusyError", "DeviceFaultError", "DeviceNotFoundError", "DeviceRemovedError",
    "GrabTimeoutError", "IncompleteFrameError", "NoiseProfileWarning", "ProtocolError", "RawFileError",
]


@dataclass(frozen=True)
class DeviceInfo:
    uri: str
    model: str
    serial: str
    busy: bool


def _connector_tcp(host: str, port: int, timeout_s: float):
    def connect():
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise DeviceNotFoundError(f"no camera answers at {tcp_uri(host, port)} ({exc})") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock, lambda: None
    return connect


def parse_tcp_address(netloc: str, uri: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT``, ``[IPV6]:PORT`` or, unbracketed, ``IPV6:PORT`` (the last colon
    starts the port, the way ``bmi firmware-sim serve --host ::1`` used to print it)."""
    usage = f"tcp URIs look like tcp://127.0.0.1:PORT or tcp://[::1]:PORT, got {uri!r}"
    if netloc.startswith("["):
        host, sep, port = netloc[1:].partition("]:")
        if not sep:
            raise ConfigurationError(usage)
    else:
        host, sep, port = netloc.rpartition(":")
        if not sep:
            raise ConfigurationError(usage)
        if ":" in host:
            try:
                ipaddress.IPv6Address(host)
            except ValueError:
                raise ConfigurationError(usage) from None
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigurationError(f"bad host or port in {uri!r} (port 1–65535); {usage}")
    return host, int(port)


def _tcp_token(query: dict, uri: str) -> bytes | None:
    unknown = set(query) - {"token", "token_file"}
    if unknown:
        raise ConfigurationError(f"tcp:// takes token or token_file (the server chooses scene and faults), "
                                 f"not {', '.join(sorted(unknown))}")
    if "token" in query and "token_file" in query:
        raise ConfigurationError("give token or token_file, not both")
    if "token_file" in query:
        try:
            token = Path(query["token_file"]).read_bytes().strip()
        except OSError as exc:
            raise ConfigurationError(f"token_file: {exc}") from None
    elif "token" in query:
        token = query["token"].encode()
    else:
        return None
    if not 1 <= len(token) <= MAX_TOKEN_BYTES:
        raise ConfigurationError(f"a token is 1 to {MAX_TOKEN_BYTES} bytes, got {len(token)} in {uri!r}")
    return token


def open_camera(uri: str = "sim://", *, device=None, on_frame=None, on_disconnect=None, on_progress=None,
                timeout_s: float = 5.0):
    """Open the camera at ``uri`` (see the module doc); use it as a context manager.

    ``on_progress(frame_id, done, total)``: heartbeats of a readout in progress (a slow scene); done and
    total count the device's units of work (render blocks for a scene seen through the lens, else rows).
    """
    parts = urlsplit(uri)
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    if parts.scheme == "sim":
        return open_sim(uri, parts.netloc or _SIM_DEFAULT_NAME, query, device, on_frame=on_frame,
                        on_disconnect=on_disconnect, io_timeout_s=timeout_s, on_progress=on_progress)
    if device is not None:
        raise ConfigurationError("device= only applies to sim:// URIs")
    if parts.scheme == "tcp":
        token = _tcp_token(query, uri)
        host, port = parse_tcp_address(parts.netloc, uri)
        return StreamCamera(uri, _connector_tcp(host, port, timeout_s), on_frame, on_disconnect,
                            io_timeout_s=timeout_s, token=token, on_progress=on_progress)
    if parts.scheme == "replay":
        folder = Path(parts.netloc + parts.path)
        return ReplayCamera(uri, folder, loop=query.get("loop") in ("1", "true"), on_frame=on_frame,
                            on_disconnect=on_disconnect)
    raise DeviceNotFoundError(f"unknown camera URI scheme in {uri!r}; use sim://, tcp://HOST:PORT or replay://DIR")


def list_devices(tcp_ports: tuple[int, ...] = (), host: str = "127.0.0.1", timeout_s: float = 1.0) \
        -> list[DeviceInfo]:
    """Cameras this host can open: the in-process simulated ones (``sim://`` always) and any
    device answering on the given TCP ports of ``host``."""
    found = []
    sims = sim_devices()
    if _SIM_DEFAULT_NAME not in sims:
        found.append(DeviceInfo("sim://", MODEL_NAME, "BMI-00000001", False))
    for name, dev in sims.items():
        busy = dev.claimed  # a look, not a claim: release() would reset the registers
        found.append(DeviceInfo("sim://" if name == _SIM_DEFAULT_NAME else f"sim://{name}", MODEL_NAME,
                                dev.describe()["serial"], busy))
    for port in tcp_ports:
        uri = tcp_uri(host, port)
        try:
            with open_camera(uri, timeout_s=timeout_s) as cam:
                found.append(DeviceInfo(uri, cam.info["model"], cam.info["serial"], False))
        except DeviceBusyError:
            found.append(DeviceInfo(uri, "?", "?", True))
        except (DeviceNotFoundError, DeviceRemovedError):
            continue
    return found
