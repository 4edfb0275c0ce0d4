"""Transport endpoint of the simulated camera: serves a ``FirmwareDevice`` over a byte stream.

The same connection loop runs over a TCP socket (``FirmwareServer``, loopback
only, what ``bmi firmware-sim serve`` starts) and over an in-process socket
pair (``InProcessLink``), so the host code, framing and faults are the same in
both. The loop answers commands (docs/protocol.md) and, while acquiring, has
frames read out and sends them as fast as the link takes them (the simulator
does not wait out the exposure in real time).

A readout runs on a worker thread (``_ReadoutJob``) so the loop keeps
answering commands while a slow source (a scene rendered through the lens)
takes minutes: it sends a PROGRESS heartbeat every ``device.heartbeat_s``,
answers STOP at once (abandoning the readout between strips) and holds a
stalled frame without blocking. A TCP host that sends no whole message for
``idle_timeout_s`` (except while frames stream to it) is dropped with an ERROR
saying why, so one idle or trickling client cannot lock the camera; with a
token, nothing but AUTH is accepted before the token matches, and an
unauthenticated connection never holds the camera. Every blocking call has a
timeout and every loop checks a stop event, so nothing can hang.

A session notices that its host hung up on its own thread, which a loaded
machine may run late; a host that reconnects at once must not get BUSY from its
own dead session. So when a connection finds the camera held, the device asks
the holding session whether its host is still there (``host_gone``: the
socket has seen end of stream or a reset, polled without reading) and, if not,
ends that session on the spot. BUSY is kept for a host that is still connected.
The session that lost the camera acts on the device only through
``FirmwareDevice.held_by``, so a command its host left behind, a readout or a
late teardown never reaches the next host's session.
"""

from __future__ import annotations

import atexit
import errno
import hmac
import ipaddress
import select
import socket
import threading
import time
import weakref
import zlib

from bmi_sdk.protocol.registers import RegError
from bmi_sdk.protocol.wire import (
    ACK,
    CRC,
    DEFAULT_IDLE_TIMEOUT_S,
    ENVELOPE,
    HEADER,
    HOST_BODY_BYTES,
    PROGRESS,
    REG_ACCESS,
    REG_REPLY,
    U32,
    Msg,
    WireError,
    check_host_body,
    envelope,
    error_body,
    json_body,
    parse_envelope,
    tcp_uri,
)

from .device import FirmwareDevice, NotHeld
from .faults import Fault

SEND_TIMEOUT_S = 10.0
POLL_S = 0.05
# The peer shut its sending side (Linux); elsewhere only a full hang-up (POLLHUP) or a reset counts.
_POLLRDHUP = getattr(select, "POLLRDHUP", 0)
_HUNG_UP = select.POLLHUP | select.POLLERR | select.POLLNVAL | _POLLRDHUP


# -- readouts off the connection thread ---------------------------------------------
_LIVE_JOBS: "weakref.WeakSet[_ReadoutJob]" = weakref.WeakSet()
_JOBS_LOCK = threading.Lock()
_EXITING = False


@atexit.register
def _cancel_readouts_at_exit() -> None:
    """Cancel running readouts and wait for them before the interpreter finalises.

    A daemon thread still inside C++ (scipy's FFT in the renderer) when Python
    finalises is ended by a forced unwind, which C++ answers with
    ``terminate called without an active exception`` (SIGABRT). ``atexit``
    runs while the interpreter is intact; each readout stops at its next strip.
    """
    global _EXITING
    with _JOBS_LOCK:
        _EXITING = True
        jobs = list(_LIVE_JOBS)
    for job in jobs:
        job.cancel.set()
    for job in jobs:
        job.thread.join()


class _ReadoutJob:
    """One frame read out and packed on a worker thread; ``wake`` is written when it is done."""

    def __init__(self, device: FirmwareDevice, wake: socket.socket):
        self.device = device
        self.cancel = threading.Event()
        self.done = threading.Event()
        self.started_s = time.monotonic()
        self.frame_id = device.regs.get("FRAME_COUNTER")
        self.rows_done = self.rows_total = 0
        self._window = device.regs.roi()  # fixed while acquiring
        self._source = device.source
        self.result: tuple | None = None  # (header, payload, payload CRC32)
        self.error: BaseException | None = None
        self._wake = wake
        self.thread = threading.Thread(target=self._run, name="bmi-fw-readout", daemon=True)

    def start(self) -> bool:
        """False when the process is exiting (no new readouts then)."""
        with _JOBS_LOCK:
            if _EXITING:
                return False
            _LIVE_JOBS.add(self)
            self.thread.start()
        return True

    def _progress(self, frame_id: int, rows_done: int, rows_total: int) -> None:
        self.frame_id, self.rows_done, self.rows_total = frame_id, rows_done, rows_total

    def work(self) -> tuple[int, int]:
        """(done, total) for a heartbeat: the source's own measure of its slow work (render blocks) when it
        has one, else rows read out."""
        measure = getattr(self._source, "work", None)
        if measure is not None:
            x, y, w, h = self._window
            got = measure(y, x, h, w)
            if got is not None:
                return got
        return self.rows_done, self.rows_total

    def _run(self) -> None:
        try:
            header, payload = self.device.frame_bytes(self.cancel, self._progress)
            self.result = (header, payload, zlib.crc32(payload))
        except Exception as exc:  # ReadoutCancelled, or a failing source: the host gets ERROR, not a traceback
            self.error = exc
        finally:
            self.done.set()
            try:
                self._wake.send(b"\0")
            except OSError:
                pass


class _Drop(Exception):
    """The device ends this session (it has said why, where it could)."""


class _Connection:
    """One host session: commands in, frames out, until the host leaves or ``stop`` is set."""

    def __init__(self, device: FirmwareDevice, sock: socket.socket, stop: threading.Event,
                 token: bytes | None = None, idle_timeout_s: float | None = None):
        self.device = device
        self.sock = sock
        self.stop = stop
        self.token = token
        self.idle_timeout_s = idle_timeout_s
        self.remaining = 0  # frames still to send; -1: until STOP
        self._rx = bytearray()
        self._authed = token is None
        self._job: _ReadoutJob | None = None
        self._held: tuple | None = None  # (send at, FRAME message chunks): a frame a STALL fault holds back
        self._quiet_since = time.monotonic()
        self._last_beat = 0.0
        self._wake_r, self._wake_w = socket.socketpair()

    # -- session ---------------------------------------------------------------------
    def run(self) -> None:
        try:
            self.sock.settimeout(SEND_TIMEOUT_S)
            if self._authed and not self._claim():
                return
            while not self.stop.is_set():
                readable, _, _ = select.select([self.sock, self._wake_r], [], [], self._wait_s())
                if self._wake_r in readable:
                    self._wake_r.recv(4096)
                if self.sock in readable:
                    data = self.sock.recv(1 << 16)
                    if not data:
                        return  # host closed the link
                    self._rx += data
                    self._commands()
                self._check_idle()
                self._acquire()
        except (OSError, ConnectionError, WireError, _Drop, NotHeld):
            pass  # host gone, the device dropped it (after saying why), or the camera went to the next host
        finally:
            self._end_readout()
            self.device.release(self)  # nothing, if it never held the camera or the next host took it
            self._close()

    # -- the device asks these (under its lock) when another host wants the camera --------
    def host_gone(self) -> bool:
        """Whether the host has hung up (end of stream or a reset), though this session's thread may not
        have noticed yet. Polls the socket without reading or waiting."""
        try:
            fd = self.sock.fileno()
            if fd < 0:
                return True
            poller = select.poll()
            poller.register(fd, select.POLLIN | _POLLRDHUP)
            return any(events & _HUNG_UP for _, events in poller.poll(0))
        except (OSError, ValueError):
            return True

    def revoke(self) -> None:
        """The camera went to another host: abandon the readout in flight (this thread ends at its next look)."""
        job = self._job
        if job is not None:
            job.cancel.set()

    def _claim(self) -> bool:
        if self.device.claim(self):
            return True
        self._reply(Msg.BUSY, json_body({"reason": f"device {self.device.describe()['serial']} is held by "
                                                   f"another host"}))
        return False

    def _close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        self._wake_r.close()
        self._wake_w.close()

    def _reply(self, msg: Msg, body: bytes = b"") -> None:
        self.sock.sendall(envelope(msg, body) + body)

    def _error(self, code: str, reason: str, in_reply_to: Msg | None = None) -> None:
        self._reply(Msg.ERROR, error_body(code, reason, in_reply_to))

    def _wait_s(self) -> float:
        """How long select may sleep: until the held frame is due, the next heartbeat, or POLL_S."""
        now = time.monotonic()
        wait = POLL_S
        if self._held is not None:
            wait = min(wait, self._held[0] - now)
        if self._job is not None:
            wait = min(wait, self._last_beat + self.device.heartbeat_s - now)
        return max(0.0, wait)

    def _check_idle(self) -> None:
        """Drop a host that sent no whole message for idle_timeout_s (a stream of frames to it counts as use)."""
        now = time.monotonic()
        streaming = bool(self.remaining or self._job or self._held)
        if streaming and not self._rx:
            self._quiet_since = now
        if self.idle_timeout_s is not None and now - self._quiet_since > self.idle_timeout_s:
            partial = f" ({len(self._rx)} bytes of a message pending)" if self._rx else ""
            self._error("idle_timeout", f"no complete message for {self.idle_timeout_s:g} s{partial}: link "
                                        f"closed; a host that waits sends PING to keep the camera")
            raise _Drop

    # -- commands --------------------------------------------------------------------
    def _commands(self) -> None:
        while len(self._rx) >= ENVELOPE.size:
            try:
                msg, length = parse_envelope(bytes(self._rx[:ENVELOPE.size]))
            except WireError as exc:  # out of sync: nothing after this can be trusted
                self._error("bad_message", str(exc))
                raise _Drop from None
            if len(self._rx) < ENVELOPE.size + length:
                return
            body = bytes(self._rx[ENVELOPE.size:ENVELOPE.size + length])
            del self._rx[:ENVELOPE.size + length]
            self._quiet_since = time.monotonic()
            self._command(msg, body)

    def _command(self, msg: Msg, body: bytes) -> None:
        problem = check_host_body(msg, len(body))
        if problem is not None:
            self._error("bad_message", problem, msg)
            if msg not in HOST_BODY_BYTES and msg != Msg.AUTH:
                raise _Drop  # a device-only type: the host is not speaking this protocol
            return  # the envelope framed it: the stream is still in sync
        if msg == Msg.AUTH:
            self._authenticate(body)
            return
        if not self._authed:
            self._error("auth_required", f"this camera needs a token: send AUTH before {msg.name}", msg)
            raise _Drop
        with self.device.held_by(self):  # NotHeld: the host hung up and the camera went to the next one
            reply = self._answer(msg, body)
        self._reply(*reply)

    def _answer(self, msg: Msg, body: bytes) -> tuple[Msg, bytes]:
        """Carry out a command on the device (under its lock) and return the reply to send."""
        dev = self.device
        if msg == Msg.HELLO:
            link = {"idle_timeout_s": self.idle_timeout_s, "token_required": self.token is not None}
            return Msg.HELLO, json_body(dev.describe() | {"link": link})
        if msg == Msg.PING:
            return Msg.ACK, ACK.pack(Msg.PING, 0)
        if msg == Msg.READ_REG:
            (address,) = U32.unpack(body)
            err, value = dev.read_register(address)
            return Msg.REG_REPLY, REG_REPLY.pack(address, err, value)
        if msg == Msg.WRITE_REG:
            address, value = REG_ACCESS.unpack(body)
            err = dev.write_register(address, value)
            current = dev.read_register(address)[1] if err != RegError.UNKNOWN_ADDRESS else 0
            return Msg.REG_REPLY, REG_REPLY.pack(address, err, current)
        if msg == Msg.START:
            (count,) = U32.unpack(body)
            self.remaining = count if count else -1
            dev.set_acquiring(True)
            return Msg.ACK, ACK.pack(Msg.START, 0)
        if msg == Msg.STOP:
            self.remaining = 0
            self._held = None  # a frame held back is discarded: nothing follows the ACK of STOP
            if self._job is not None:
                self._job.cancel.set()
            dev.set_acquiring(False)
            return Msg.ACK, ACK.pack(Msg.STOP, 0)
        raise AssertionError(f"{msg.name} passed check_host_body but has no handler")

    def _authenticate(self, token: bytes) -> None:
        if self._authed:
            self._reply(Msg.ACK, ACK.pack(Msg.AUTH, 0))
            return
        if not hmac.compare_digest(token, self.token):  # constant time: the comparison leaks no prefix
            self._error("auth_failed", "wrong token", Msg.AUTH)
            raise _Drop
        self._authed = True
        if not self._claim():
            raise _Drop
        self._reply(Msg.ACK, ACK.pack(Msg.AUTH, 0))

    # -- acquisition -------------------------------------------------------------------
    def _acquire(self) -> None:
        now = time.monotonic()
        job = self._job
        if job is not None and job.done.is_set():
            self._job = None
            if not job.cancel.is_set():
                self._finished(job)
        if self._held is not None and now >= self._held[0]:
            _, chunks = self._held
            self._held = None
            self._send(chunks)
        if self.remaining and self._job is None and self._held is None:
            with self.device.held_by(self):  # a readout reads the registers and uses up a frame id
                job = _ReadoutJob(self.device, self._wake_w)
                if not job.start():
                    raise _Drop  # the process is exiting
                self._job, self._last_beat = job, job.started_s
        elif (self._job is not None and not self._job.cancel.is_set()
              and now - self._last_beat >= self.device.heartbeat_s):
            self._reply(Msg.PROGRESS, PROGRESS.pack(self._job.frame_id, *self._job.work()))
            self._last_beat = now

    def _finished(self, job: _ReadoutJob) -> None:
        with self.device.held_by(self):  # the acquiring flag and the fault draws are the device's
            if job.error is not None:
                self.remaining = 0
                self.device.set_acquiring(False)
                failure = f"readout of frame {job.frame_id} failed: {type(job.error).__name__}: {job.error}"
            else:
                failure = None
                header, payload, crc = job.result
                if self.remaining > 0:
                    self.remaining -= 1
                    if self.remaining == 0:
                        self.device.set_acquiring(False)
                fault = self.device.injector.draw(header.frame_id)
                if fault == Fault.DROP:
                    return
                if fault == Fault.STALL:
                    chunks = self._frame_chunks(header, payload, crc, Fault.NONE)
                    self._held = (time.monotonic() + self.device.injector.plan.stall_s, chunks)
                    return
                chunks = self._frame_chunks(header, payload, crc, fault)
        if failure is not None:
            self._error("readout_failed", failure)
            return
        self._send(chunks, hang_up=fault == Fault.DISCONNECT)

    def _frame_chunks(self, header, payload: bytes, crc: int, fault: Fault) -> list:
        """The bytes of one FRAME message with its fault applied (the damage is the injector's draw)."""
        injector = self.device.injector
        full_len = HEADER.size + len(payload) + CRC.size
        if fault == Fault.CORRUPT:
            damaged = bytearray(payload)
            damaged[injector.corrupt_offset(len(payload))] ^= 0xA5
            payload = damaged
        elif fault in (Fault.INCOMPLETE, Fault.DISCONNECT):
            cut = int(len(payload) * injector.cut_fraction())
            length = full_len if fault == Fault.DISCONNECT else HEADER.size + cut
            return [envelope(Msg.FRAME, length=length), header.pack(), memoryview(payload)[:cut]]
        return [envelope(Msg.FRAME, length=full_len), header.pack(), payload, CRC.pack(crc)]

    def _send(self, chunks: list, hang_up: bool = False) -> None:
        """Send one frame (outside the device's lock: a slow host must not hold the camera up);
        ``hang_up``: a DISCONNECT fault, which ends the session."""
        for chunk in chunks:
            self.sock.sendall(chunk)
        if hang_up:
            raise _Drop

    def _end_readout(self) -> None:
        """Abandon a readout in progress and wait for it (it stops at its next strip)."""
        if self._job is not None:
            self._job.cancel.set()
            self._job.thread.join()
            self._job = None


def _check_loopback(host: str) -> None:
    try:
        ok = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"the simulator serves on loopback only (127.0.0.1, ::1, localhost), not {host!r}")


class FirmwareServer:
    """TCP endpoint on loopback; one host at a time, others get BUSY. ``port=0`` picks a free port.

    ``token``: when given, a host must send it (AUTH) before anything else; ``idle_timeout_s``: a host
    that sends no whole message for this long, while no frames stream to it, is dropped.
    """

    def __init__(self, device: FirmwareDevice, host: str = "127.0.0.1", port: int = 0,
                 token: bytes | None = None, idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S):
        _check_loopback(host)
        if token is not None and not token:
            raise ValueError("an empty token protects nothing; give none or a non-empty one")
        if not idle_timeout_s > 0:
            raise ValueError(f"idle_timeout_s must be > 0 s (an idle host would hold the camera forever), "
                             f"got {idle_timeout_s}")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"a TCP port is 0–65535 (0: a free one), got {port!r}")
        self.device = device
        self.token = token
        self.idle_timeout_s = float(idle_timeout_s)
        self._stop = threading.Event()
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
        except OSError as exc:
            self._listener.close()
            if exc.errno == errno.EADDRINUSE:
                raise OSError(exc.errno, f"port {port} on {host} is in use (another server?); pick another port, "
                                         "or 0 for a free one") from exc
            raise
        self._listener.listen(4)
        self._listener.settimeout(POLL_S * 4)
        self.host, self.port = host, self._listener.getsockname()[1]
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept_loop, name="bmi-fw-accept", daemon=True)

    @property
    def uri(self) -> str:
        return tcp_uri(self.host, self.port)

    def start(self) -> "FirmwareServer":
        self._accept_thread.start()
        return self

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _Connection(self.device, sock, self._stop, self.token, self.idle_timeout_s)
            t = threading.Thread(target=conn.run, name="bmi-fw-conn", daemon=True)
            t.start()
            self._threads = [x for x in self._threads if x.is_alive()] + [t]

    def close(self) -> None:
        self._stop.set()
        self._listener.close()
        if self._accept_thread.is_alive():
            self._accept_thread.join(timeout=2)
        for t in self._threads:
            t.join(timeout=SEND_TIMEOUT_S)

    def __enter__(self) -> "FirmwareServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class InProcessLink:
    """The device served on one end of a socket pair in a thread of this process; ``sock`` is the host's end.

    No token and no idle timeout: only this process can reach it.
    """

    def __init__(self, device: FirmwareDevice):
        self._stop = threading.Event()
        self.sock, device_end = socket.socketpair()
        self._thread = threading.Thread(target=_Connection(device, device_end, self._stop).run,
                                        name="bmi-fw-inproc", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=SEND_TIMEOUT_S)
