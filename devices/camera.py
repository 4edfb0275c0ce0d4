"""``StreamCamera``: the host camera over a stream link (simulated in-process device or TCP).

Acquisition follows machine-vision practice: ``start(strategy, buffers=N)``
allocates N frame buffers; the link thread decodes each arriving frame into a
free buffer and queues it. ``oldest_first`` hands frames out in order and, when
every buffer is in use, discards the *arriving* frame; ``latest_only`` keeps
only the newest frame and recycles the one it replaces. Discarded, replaced,
incomplete and corrupt frames all give their buffer back. Counters in
``stats`` say what happened: ``lost`` counts frame ids that never reached the
host (dropped on the device or link), ``discarded`` those the host had no
buffer for, ``replaced`` those latest_only overwrote.

Timeouts in ``grab`` and ``capture`` count *silence*: a device that is still
reading out a frame (a scene rendered through the lens can take minutes) sends
PROGRESS heartbeats, each of which restarts the wait; only a device that says
nothing for ``timeout_s`` is given up on. ``on_progress`` sees the heartbeats.

Each sensor frame carries its ``noise_profile``, computed from the sensor model
the device describes in its HELLO reply (``info["sensor_model"]``) at the
gain, exposure and black level of the frame's header, so a decoder is told the
noise instead of estimating it from the picture. A device that does not
describe its sensor gives frames without one (None); so do test-pattern
frames, which are digital and carry no sensor noise.
"""

from __future__ import annotations

import collections
import socket
import threading
import time
import warnings
from typing import Callable

import numpy as np

from bmi_sdk.geometry import SensorGeometry
from bmi_sdk.protocol.registers import BY_NAME, ROI_REGISTERS, RegError
from bmi_sdk.protocol.wire import FLAG_TEST_PATTERN, FrameHeader
from bmi_sdk.sensor import NoiseProfile, SensorModel

from .errors import (
    CameraError,
    ConfigurationError,
    DeviceFaultError,
    DeviceRemovedError,
    GrabTimeoutError,
    NoiseProfileWarning,
)
from .frame import BufferPool, FrameStatus, RawFrame, Roi
from .link import StreamLink
from .settings import Settings, refused, specs_from_register_map

STRATEGIES = ("oldest_first", "latest_only")
MAX_BUFFER_BYTES = 4 << 30
_STAT_KEYS = ("delivered", "complete", "incomplete", "corrupt", "lost", "discarded", "replaced", "disconnects")


class StreamCamera:
    """A camera reached through ``connect()``, which returns a fresh connected socket (and a cleanup).

    ``token``: sent (AUTH) on every connect, for a device that wants one; ``on_progress(frame_id,
    done, total)`` is called on the link thread for each heartbeat of a readout in progress.
    """

    def __init__(self, uri: str, connect: Callable[[], tuple[socket.socket, Callable[[], None]]],
                 on_frame: Callable[[RawFrame], None] | None = None,
                 on_disconnect: Callable[[str], None] | None = None, io_timeout_s: float = 5.0,
                 token: bytes | None = None, on_progress: Callable[[int, int, int], None] | None = None):
        self.uri = uri
        self._connect = connect
        self.on_frame = on_frame
        self.on_disconnect = on_disconnect
        self.on_progress = on_progress
        self.io_timeout_s = io_timeout_s
        self._token = token
        self._alive_s = time.monotonic()  # when the device last showed life (frame or heartbeat)
        self._fault: str | None = None  # an unsolicited device ERROR not yet raised to the user
        self._cond = threading.Condition()
        self._queue: collections.deque[RawFrame] = collections.deque()
        self._pool: BufferPool | None = None
        self._strategy = "oldest_first"
        self._streaming = False
        self._oneshot: list[RawFrame] | None = None
        self._removed: str | None = None
        self._last_header_id: int | None = None
        self._last_handed_id: int | None = None
        self.stats = dict.fromkeys(_STAT_KEYS, 0)
        self._link: StreamLink | None = None
        self._cleanup = lambda: None
        self._closed = False
        self._applied: dict[str, int] = {}  # register writes to restore on reconnect
        self._open_link()

    # -- connection ------------------------------------------------------------------
    def _open_link(self) -> None:
        sock, cleanup = self._connect()
        self._cleanup = cleanup
        self._removed = None
        self._link = StreamLink(sock, self, io_timeout_s=self.io_timeout_s)
        try:
            if self._token is not None:
                self._link.authenticate(self._token)
            self.info = self._link.hello()
        except CameraError:
            self._link.close()
            cleanup()
            raise
        self.geometry = SensorGeometry.from_dict(self.info["geometry"])
        self.lens = self.info["lens"]
        self.device = {k: self.info[k] for k in ("model", "serial", "firmware_version")}
        self.settings = Settings(specs_from_register_map(self.info["registers"]), self.info["registers"],
                                 self._read_reg, self._write_reg)
        self._sensor_model = self._sensor_model_from_info()

    def _sensor_model_from_info(self) -> SensorModel | None:
        """The device's ``SensorModel`` from HELLO, or None when it sends none. One it sends but this host
        cannot read (unknown fields, values out of range) is a warning, not a failure to open: only the
        frames' noise profiles depend on it."""
        described = self.info.get("sensor_model")
        if described is None:
            return None
        try:
            return SensorModel(**described)
        except (TypeError, ValueError) as exc:
            warnings.warn(f"{self.uri}: the device's sensor_model is unreadable ({exc}); its frames carry no "
                          "noise profile", NoiseProfileWarning)
            return None

    def _noise_profile(self, header: FrameHeader) -> NoiseProfile | None:
        """The noise of a frame read out with ``header``'s settings; None for a test pattern (no sensor noise),
        without a sensor model, or for a header the model cannot describe (its white level differs, or a
        gain, exposure or black level outside the model's domain)."""
        model = self._sensor_model
        if model is None or header.flags & FLAG_TEST_PATTERN or header.white_level_dn != model.white_level_dn:
            return None
        try:
            return model.noise_profile(header.gain_milli / 1000, header.exposure_us, header.black_level_dn)
        except ValueError:
            return None

    def reconnect(self) -> None:
        """Open a new link after a disconnect; re-applies the settings written so far (a device that
        reset has lost them) and restarts streaming if it was on."""
        self._check_open()
        self._drop_link()
        self._open_link()
        applied = dict(self._applied)
        roi_values = [applied.pop(n, None) for n in ROI_REGISTERS]
        for name, value in applied.items():
            self._write_reg(name, value)
        if any(v is not None for v in roi_values):
            current = self.settings.roi
            self.settings.set_roi(Roi(*(c if v is None else v for v, c in zip(roi_values, (
                current.x_px, current.y_px, current.width_px, current.height_px)))))
        if self._streaming:
            self._check_link().start(0)

    def _drop_link(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None
        self._cleanup()
        self._cleanup = lambda: None

    def close(self) -> None:
        """Stop streaming and let go of the device. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self._streaming and self._removed is None and self._link is not None:
            try:
                self._link.stop()
            except CameraError:
                pass
        self._streaming = False
        self._drop_link()
        self._flush()

    def __enter__(self) -> "StreamCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise ConfigurationError(f"camera {self.uri} is closed")

    def _check_link(self) -> StreamLink:
        self._check_open()
        if self._removed is not None:
            raise DeviceRemovedError(f"{self.uri}: {self._removed} (call reconnect())")
        if self._link is None:  # a reconnect() that failed left no link
            raise DeviceRemovedError(f"{self.uri}: not connected (call reconnect())")
        return self._link

    # -- registers ----------------------------------------------------------------------
    def _read_reg(self, name: str) -> int:
        err, value = self._check_link().read_register(BY_NAME[name].address)
        if err != RegError.OK:
            raise refused(name, value, err)
        return value

    def _write_reg(self, name: str, value: int) -> None:
        err, _ = self._check_link().write_register(BY_NAME[name].address, int(value))
        if err != RegError.OK:
            raise refused(name, value, err)
        self._applied[name] = int(value)

    def ping(self) -> None:
        """Keep-alive: tell the device this host is still here. A TCP device drops a host that sends
        nothing for its idle timeout (``info["link"]["idle_timeout_s"]``) while not streaming; call this
        while you wait between captures."""
        self._check_link().ping()

    def read_register(self, name: str) -> int:
        """Raw register read by name (see ``bmi_sdk.protocol.registers``), e.g. ``FRAME_COUNTER``."""
        if name not in BY_NAME:
            raise ConfigurationError(f"no register {name!r}")
        return self._read_reg(name)

    # -- acquisition -----------------------------------------------------------------------
    def start(self, strategy: str = "oldest_first", buffers: int = 4) -> None:
        link = self._check_link()
        if self._streaming:
            raise ConfigurationError("already streaming; stop() first")
        if strategy not in STRATEGIES:
            raise ConfigurationError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
        roi = self.settings.roi
        if isinstance(buffers, bool) or not isinstance(buffers, int) or buffers < 1:
            raise ConfigurationError(f"buffers must be an integer >= 1, got {buffers!r}")
        if buffers * roi.width_px * roi.height_px * 2 > MAX_BUFFER_BYTES:
            raise ConfigurationError(f"{buffers} buffers of {roi.width_px}×{roi.height_px} exceed "
                                     f"{MAX_BUFFER_BYTES >> 30} GiB")
        self._strategy = strategy
        self._pool = BufferPool(buffers, (roi.height_px, roi.width_px))
        self._fault = None
        self._streaming = True
        try:
            link.start(0)
        except CameraError:
            self._streaming = False
            raise

    def stop(self) -> None:
        """Stop streaming; frames still queued are released."""
        if not self._streaming:
            return
        self._streaming = False
        if self._removed is None and not self._closed and self._link is not None:
            self._link.stop()
        self._flush()

    def _flush(self) -> None:
        with self._cond:
            while self._queue:
                self._queue.popleft().release()

    @property
    def buffers_free(self) -> int:
        return 0 if self._pool is None else self._pool.free

    def _wait_until(self, ready, timeout_s: float, removed_hint: str = "") -> None:
        """Wait on the condition (held by the caller) until ``ready()``; raise if removed, if the device
        reported a failure, or after ``timeout_s`` without a frame or a heartbeat."""
        start = time.monotonic()
        while not ready():
            if self._removed is not None:
                raise DeviceRemovedError(f"{self.uri}: {self._removed}{removed_hint}")
            if self._fault is not None:
                fault, self._fault = self._fault, None
                raise DeviceFaultError(f"{self.uri}: {fault}")
            left = max(start, self._alive_s) + timeout_s - time.monotonic()
            if left <= 0:
                raise GrabTimeoutError(f"no frame and no heartbeat from {self.uri} for {timeout_s} s")
            self._cond.wait(left)

    def grab(self, timeout_s: float = 5.0) -> RawFrame:
        """Next frame (per the strategy); GrabTimeoutError after ``timeout_s``; release it when done."""
        self._check_open()
        if not self._streaming:
            raise ConfigurationError("grab() needs start() first (or use capture())")
        with self._cond:
            self._wait_until(lambda: self._queue, timeout_s, " (call reconnect())")
            return self._hand_out(self._queue.popleft())

    def try_grab(self) -> RawFrame | None:
        """A queued frame or None; raises DeviceRemovedError if the link is down and nothing is queued."""
        self._check_open()
        with self._cond:
            if self._queue:
                return self._hand_out(self._queue.popleft())
            if self._removed is not None:
                raise DeviceRemovedError(f"{self.uri}: {self._removed} (call reconnect())")
            return None

    def capture(self, timeout_s: float = 10.0) -> RawFrame:
        """One frame now (not while streaming); the frame owns its data. Raises IncompleteFrameError
        if it arrives incomplete or corrupt and GrabTimeoutError if it never arrives."""
        link = self._check_link()
        if self._streaming:
            raise ConfigurationError("capture() while streaming; use grab() or stop() first")
        with self._cond:
            self._oneshot = []
            self._fault = None
        try:
            link.start(1)
            with self._cond:
                self._wait_until(lambda: self._oneshot, timeout_s)
                frame = self._oneshot[0]
        finally:
            with self._cond:
                self._oneshot = None
        return frame.check()

    def _hand_out(self, frame: RawFrame) -> RawFrame:
        """Stamp how many frame ids the user missed since the previous frame they got."""
        if self._last_handed_id is not None:
            frame.skipped_frames = (frame.frame_id - self._last_handed_id - 1) % (1 << 32)
        self._last_handed_id = frame.frame_id
        return frame

    # -- FrameSink (called on the link thread) --------------------------------------------------
    def buffer_for(self, header: FrameHeader) -> np.ndarray | None:
        with self._cond:
            if self._last_header_id is not None:
                self.stats["lost"] += (header.frame_id - self._last_header_id - 1) % (1 << 32)
            self._last_header_id = header.frame_id
            if self._oneshot is not None:
                return np.empty((header.height_px, header.width_px), np.uint16)
            pool = self._pool
            if not self._streaming or pool is None or pool.shape != (header.height_px, header.width_px):
                self.stats["discarded"] += 1
                return None
            buf = pool.take()
            if buf is None and self._strategy == "latest_only" and self._queue:
                self._queue.popleft().release()
                self.stats["replaced"] += 1
                buf = pool.take()
            if buf is None:
                self.stats["discarded"] += 1
            return buf

    def deliver(self, header: FrameHeader, buf: np.ndarray, status: FrameStatus) -> None:
        with self._cond:
            frame = RawFrame(
                data=buf, frame_id=header.frame_id, status=status, black_level_dn=header.black_level_dn,
                white_level_dn=header.white_level_dn, exposure_us=header.exposure_us,
                analog_gain=header.gain_milli / 1000, temperature_c=header.temperature_milli_c / 1000,
                device_timestamp_ns=header.device_ts_ns, readout_timestamp_ns=header.readout_ts_ns,
                host_timestamp_ns=time.time_ns(),
                roi=Roi(header.roi_x_px, header.roi_y_px, header.width_px, header.height_px),
                geometry=self.geometry, lens=self.lens, device=self.device, cfa=header.cfa,
                test_pattern=bool(header.flags & FLAG_TEST_PATTERN),
                source=self.info.get("source"), noise_profile=self._noise_profile(header))
            self.stats["delivered"] += 1
            self.stats[status.value] += 1
            self._alive_s = time.monotonic()
            if self._oneshot is not None:
                self._oneshot.append(self._hand_out(frame))
                self._cond.notify_all()
                return
            assert self._pool is not None  # buffer_for took buf from the pool
            self._pool.attach(frame, buf)
            if self.on_frame is None:
                if self._strategy == "latest_only":
                    while self._queue:
                        self._queue.popleft().release()
                        self.stats["replaced"] += 1
                self._queue.append(frame)
                self._cond.notify_all()
                return
        self.on_frame(self._hand_out(frame))  # the buffer returns once the callback keeps no reference to the frame

    def progress(self, frame_id: int, done: int, total: int) -> None:
        with self._cond:
            self._alive_s = time.monotonic()
            self._cond.notify_all()
        if self.on_progress is not None:
            self.on_progress(frame_id, done, total)

    def device_error(self, reason: str) -> None:
        with self._cond:
            self._fault = reason
            self._cond.notify_all()

    def link_closed(self, reason: str) -> None:
        with self._cond:
            self._removed = reason
            self.stats["disconnects"] += 1
            self._cond.notify_all()
        if self.on_disconnect is not None:
            self.on_disconnect(reason)
