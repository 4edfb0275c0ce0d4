"""Host end of a device stream (TCP or in-process socket pair): control requests and a frame reader thread.

The reader thread owns the socket's receive side. It sorts messages into
control replies (handed to the waiting request) and frames, which it decodes
into a buffer the ``FrameSink`` provides: every length is checked against the
protocol limits before a byte is allocated or read, a short FRAME message is
reported as incomplete, a payload CRC mismatch as corrupt, and a stream that
ends or goes silent mid-message as a disconnect. PROGRESS heartbeats (a
readout in progress) go to ``FrameSink.progress``; an ERROR answers the request
it names or, unsolicited, goes to ``FrameSink.device_error``. Nothing blocks
forever: socket reads poll a stop flag, requests and partial messages have
timeouts (``bmi_sdk.protocol.wire.REPLY_TIMEOUT_S``, which the device honours while it reads out).
"""

from __future__ import annotations

import json
import queue
import socket
import threading
import zlib
from typing import Protocol

import numpy as np

from bmi_sdk.protocol.registers import RegError
from bmi_sdk.protocol.wire import (
    ACK,
    CRC,
    ENVELOPE,
    HEADER,
    PROGRESS,
    REG_ACCESS,
    REG_REPLY,
    REPLY_TIMEOUT_S,
    U32,
    FrameHeader,
    Msg,
    WireError,
    envelope,
    parse_envelope,
    unpack12,
)

from .errors import AccessDeniedError, CameraError, DeviceBusyError, DeviceRemovedError, ProtocolError
from .frame import FrameStatus

POLL_S = 0.2


class FrameSink(Protocol):
    def buffer_for(self, header: FrameHeader) -> np.ndarray | None:
        """An H×W uint16 buffer for this frame, or None to discard it (no free buffer)."""

    def deliver(self, header: FrameHeader, buf: np.ndarray, status: FrameStatus) -> None: ...

    def link_closed(self, reason: str) -> None: ...

    def progress(self, frame_id: int, done: int, total: int) -> None:
        """The device is still reading out ``frame_id`` (a heartbeat); ``done`` of ``total`` units of work."""

    def device_error(self, reason: str) -> None:
        """The device reported a failure no request asked about (a readout that failed)."""


def _parse_error(body: bytes) -> dict:
    """An ERROR body as a dict with code, reason, in_reply_to; a malformed one is a protocol error itself."""
    try:
        err = json.loads(body)
        if not isinstance(err, dict):
            raise ValueError("not an object")
        return {"code": str(err.get("code", "?")), "reason": str(err.get("reason", "")),
                "in_reply_to": int(err.get("in_reply_to", 0))}
    except (ValueError, TypeError) as exc:
        raise WireError(f"malformed ERROR body ({exc})") from None


class _Closed(Exception):
    pass


class StreamLink:
    def __init__(self, sock: socket.socket, sink: FrameSink, io_timeout_s: float = 5.0,
                 request_timeout_s: float = REPLY_TIMEOUT_S):
        self.sock = sock
        self.sink = sink
        self.io_timeout_s = io_timeout_s
        self.request_timeout_s = request_timeout_s
        self._replies: queue.Queue = queue.Queue()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self.closed_reason: str | None = None
        self._device_said: str | None = None  # the reason of the last unsolicited ERROR
        self._rx = bytearray()
        sock.settimeout(POLL_S)
        self._thread = threading.Thread(target=self._read_loop, name="bmi-host-link", daemon=True)
        self._thread.start()

    # -- control ------------------------------------------------------------------
    def request(self, msg: Msg, body: bytes, expect: Msg) -> bytes:
        if self.closed_reason is not None:
            # A device may answer and close at once (BUSY to a second host): its queued answer still counts.
            try:
                reply, reply_body = self._replies.get_nowait()
            except queue.Empty:
                reply = None
            if reply == Msg.BUSY:
                raise DeviceBusyError(json.loads(reply_body).get("reason", "device busy"))
            if reply == Msg.ERROR:
                self._raise_refusal(msg, reply_body)
            raise DeviceRemovedError(f"link is down: {self.closed_reason}")
        with self._send_lock:
            timeout_s = self.request_timeout_s
            try:
                self.sock.sendall(envelope(msg, body) + body)
            except OSError:
                timeout_s = 1.0  # the device may have said why (BUSY) before closing: look for it
            try:
                reply, reply_body = self._replies.get(timeout=timeout_s)
            except queue.Empty:
                raise DeviceRemovedError(f"device did not answer {msg.name} within {timeout_s} s") from None
        if reply is None:
            raise DeviceRemovedError(f"link dropped while waiting for {msg.name}: {reply_body}")
        if reply == Msg.BUSY:
            raise DeviceBusyError(json.loads(reply_body).get("reason", "device busy"))
        if reply == Msg.ERROR:
            self._raise_refusal(msg, reply_body)
        if reply != expect:
            raise ProtocolError(f"device answered {msg.name} with {reply.name}, expected {expect.name}")
        return reply_body

    @staticmethod
    def _raise_refusal(msg: Msg, err: dict) -> None:
        if err["code"] == "auth_required":
            raise AccessDeniedError("this camera needs a token: add ?token_file=FILE (a file holding it) to the "
                                    "tcp:// URI, e.g. tcp://HOST:PORT?token_file=token.txt")
        if err["code"].startswith("auth"):
            raise AccessDeniedError(f"device refused {msg.name}: {err['reason']}")
        raise ProtocolError(f"device refused {msg.name} ({err['code']}): {err['reason']}")

    def authenticate(self, token: bytes) -> None:
        """Send the shared token (a device with a token accepts nothing before it)."""
        ACK.unpack(self.request(Msg.AUTH, token, Msg.ACK))

    def ping(self) -> None:
        """Keep-alive: a round trip that tells the device this host is still here."""
        ACK.unpack(self.request(Msg.PING, b"", Msg.ACK))

    def hello(self) -> dict:
        return json.loads(self.request(Msg.HELLO, b"", Msg.HELLO))

    def read_register(self, address: int) -> tuple[RegError, int]:
        _, err, value = REG_REPLY.unpack(self.request(Msg.READ_REG, U32.pack(address), Msg.REG_REPLY))
        return RegError(err), value

    def write_register(self, address: int, value: int) -> tuple[RegError, int]:
        _, err, current = REG_REPLY.unpack(self.request(Msg.WRITE_REG, REG_ACCESS.pack(address, value),
                                                        Msg.REG_REPLY))
        return RegError(err), current

    def start(self, count: int) -> None:
        ACK.unpack(self.request(Msg.START, U32.pack(count), Msg.ACK))

    def stop(self) -> None:
        ACK.unpack(self.request(Msg.STOP, b"", Msg.ACK))

    def close(self) -> None:
        self._stop.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._thread.join(timeout=self.io_timeout_s + 1)
        self.sock.close()

    # -- reader ---------------------------------------------------------------------
    def _recv_into(self, view: memoryview, idle_ok: bool) -> int:
        """Fill ``view``; returns bytes read (< len only at end of stream). Between messages
        (``idle_ok``) it waits as long as the link lives; mid-message it allows io_timeout_s of silence."""
        got, silent = 0, 0.0
        while got < len(view):
            if self._stop.is_set():
                raise _Closed("closed by host")
            try:
                k = self.sock.recv_into(view[got:])
            except (TimeoutError, socket.timeout):
                if not (idle_ok and got == 0):
                    silent += POLL_S
                    if silent >= self.io_timeout_s:
                        raise _Closed(f"device went silent for {self.io_timeout_s} s mid-message") from None
                continue
            except OSError as exc:
                raise _Closed(f"link error: {exc}") from None
            if k == 0:
                return got
            got += k
            silent = 0.0
        return got

    def _read_exact(self, n: int, what: str, idle_ok: bool = False) -> bytes:
        buf = bytearray(n)
        got = self._recv_into(memoryview(buf), idle_ok)
        if got == 0:
            raise _Closed("the camera closed the link (it stopped, or dropped this host)")
        if got < n:
            raise _Closed(f"the camera closed the link mid-message (after {got} of {n} bytes of {what})")
        return bytes(buf)

    def _read_loop(self) -> None:
        reason = "closed by host"
        try:
            while not self._stop.is_set():
                msg, length = parse_envelope(self._read_exact(ENVELOPE.size, "a message envelope", idle_ok=True))
                if msg == Msg.FRAME:
                    self._read_frame(length)
                    continue
                body = self._read_exact(length, msg.name) if length else b""
                if msg == Msg.PROGRESS:
                    if length != PROGRESS.size:
                        raise WireError(f"PROGRESS body is {length} bytes, expected {PROGRESS.size}")
                    self.sink.progress(*PROGRESS.unpack(body))
                elif msg == Msg.ERROR:
                    err = _parse_error(body)
                    if err["in_reply_to"]:
                        self._replies.put((msg, err))
                    else:
                        self._device_said = f"{err['reason']} ({err['code']})"
                        self.sink.device_error(self._device_said)
                else:
                    self._replies.put((msg, body))
        except _Closed as exc:
            reason = str(exc) if self._device_said is None else f"{exc}; the device said: {self._device_said}"
        except WireError as exc:
            reason = f"protocol error: {exc}"
        except CameraError as exc:
            reason = str(exc)
        except Exception as exc:  # e.g. a user's on_frame / on_progress callback: say so, not "closed by host"
            reason = f"link reader stopped by {type(exc).__name__}: {exc}"
        finally:
            self.closed_reason = reason
            self._replies.put((None, reason))
            if not self._stop.is_set():
                self.sink.link_closed(reason)

    def _read_frame(self, length: int) -> None:
        if length < HEADER.size:
            raise WireError(f"FRAME message of {length} bytes is shorter than a frame header ({HEADER.size})")
        header = FrameHeader.parse(self._read_exact(HEADER.size, "a frame header"))
        full = HEADER.size + header.payload_len + CRC.size
        if length > full:
            raise WireError(f"FRAME message of {length} bytes is longer than its {header.width_px}×"
                            f"{header.height_px} frame ({full})")
        sent = length - HEADER.size  # payload (+ CRC) bytes the device sends for this frame
        if len(self._rx) < sent:
            self._rx = bytearray(sent)
        view = memoryview(self._rx)[:sent]
        buf = self.sink.buffer_for(header)  # after validation, before the payload: a discard still drains it
        got = self._recv_into(view, idle_ok=False)
        if buf is None:
            if got < sent:
                raise _Closed(f"stream ended after {got} of {sent} payload bytes of frame {header.frame_id}")
            return
        payload_got = min(got, header.payload_len)
        if got == full - HEADER.size:
            crc_ok = zlib.crc32(view[:header.payload_len]) == CRC.unpack(view[header.payload_len:])[0]
            unpack12(view[:header.payload_len], buf)
            self.sink.deliver(header, buf, FrameStatus.COMPLETE if crc_ok else FrameStatus.CORRUPT)
        else:
            pairs = payload_got // 3
            flat = buf.reshape(-1)
            unpack12(view[:3 * pairs], flat[:2 * pairs])
            flat[2 * pairs:] = 0
            self.sink.deliver(header, buf, FrameStatus.INCOMPLETE)
        if got < sent:
            raise _Closed(f"stream ended after {got} of {sent} payload bytes of frame {header.frame_id}")

