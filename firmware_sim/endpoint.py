"""Transport endpoint of the simulated camera: serves a ``FirmwareDevice`` over a byte stream.

The same connection loop runs over a TCP socket (``FirmwareServer``, loopback
only, what ``bmi firmware-sim serve`` starts) and over an in-process socket
pair (``connect_in_process``), so the host code, framing and faults are the
same in both. The loop answers commands (docs/protocol.md) and, while
acquiring, reads out and sends frames as fast as the link takes them (the
simulator does not wait out the exposure in real time). Every blocking call has
a timeout and every loop checks a stop event, so nothing can hang.
"""

from __future__ import annotations

import ipaddress
import select
import socket
import threading
import time
import zlib

from .device import FirmwareDevice
from .faults import Fault
from .registers import RegError
from .wire import (ACK, CRC, HEADER, REG_ACCESS, REG_REPLY, U32, Msg, WireError, envelope, json_body,
                   parse_envelope)

SEND_TIMEOUT_S = 10.0
POLL_S = 0.05


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:])
        if k == 0:
            raise ConnectionError("host closed the link")
        got += k
    return bytes(buf)


class _Connection:
    """One host session: commands in, frames out, until the host leaves or ``stop`` is set."""

    def __init__(self, device: FirmwareDevice, sock: socket.socket, stop: threading.Event):
        self.device = device
        self.sock = sock
        self.stop = stop
        self.remaining = 0  # frames still to send; -1: until STOP

    def run(self) -> None:
        self.sock.settimeout(SEND_TIMEOUT_S)
        if not self.device.claim():
            try:
                body = json_body({"reason": f"device {self.device.describe()['serial']} is held by another host"})
                self.sock.sendall(envelope(Msg.BUSY, body) + body)
            except OSError:
                pass
            self._close()
            return
        try:
            while not self.stop.is_set():
                readable, _, _ = select.select([self.sock], [], [], 0 if self.remaining else POLL_S)
                if readable:
                    self._command()
                elif self.remaining:
                    if not self._send_frame():
                        return
        except (OSError, ConnectionError, WireError):
            pass  # host gone or speaking garbage: drop the link like hardware would
        finally:
            self.device.release()
            self._close()

    def _close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    def _reply(self, msg: Msg, body: bytes = b"") -> None:
        self.sock.sendall(envelope(msg, body) + body)

    def _command(self) -> None:
        msg, length = parse_envelope(_recv_exact(self.sock, 12))
        body = _recv_exact(self.sock, length) if length else b""
        dev = self.device
        if msg == Msg.HELLO:
            self._reply(Msg.HELLO, json_body(dev.describe()))
        elif msg == Msg.READ_REG:
            (address,) = U32.unpack(body)
            err, value = dev.read_register(address)
            self._reply(Msg.REG_REPLY, REG_REPLY.pack(address, err, value))
        elif msg == Msg.WRITE_REG:
            address, value = REG_ACCESS.unpack(body)
            err = dev.write_register(address, value)
            current = dev.read_register(address)[1] if err != RegError.UNKNOWN_ADDRESS else 0
            self._reply(Msg.REG_REPLY, REG_REPLY.pack(address, err, current))
        elif msg == Msg.START:
            (count,) = U32.unpack(body)
            self.remaining = count if count else -1
            dev.set_acquiring(True)
            self._reply(Msg.ACK, ACK.pack(Msg.START, 0))
        elif msg == Msg.STOP:
            self.remaining = 0
            dev.set_acquiring(False)
            self._reply(Msg.ACK, ACK.pack(Msg.STOP, 0))
        else:
            raise WireError(f"host sent {msg.name}, which only a device sends")

    def _send_frame(self) -> bool:
        """Read out, inject this frame's fault, send. False when the link is dropped."""
        header, payload = self.device.frame_bytes()
        if self.remaining > 0:
            self.remaining -= 1
            if self.remaining == 0:
                self.device.set_acquiring(False)
        injector = self.device.injector
        fault = injector.draw(header.frame_id)
        if fault == Fault.DROP:
            return True
        crc = CRC.pack(zlib.crc32(payload))
        full_len = HEADER.size + len(payload) + CRC.size
        if fault == Fault.CORRUPT:
            damaged = bytearray(payload)
            damaged[injector.corrupt_offset(len(payload))] ^= 0xA5
            payload = damaged
        elif fault == Fault.STALL:
            deadline = time.monotonic() + self.device.injector.plan.stall_s
            while time.monotonic() < deadline and not self.stop.is_set():
                time.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
        elif fault in (Fault.INCOMPLETE, Fault.DISCONNECT):
            cut = int(len(payload) * injector.cut_fraction())
            length = full_len if fault == Fault.DISCONNECT else HEADER.size + cut
            self.sock.sendall(envelope(Msg.FRAME, length=length))
            self.sock.sendall(header.pack())
            self.sock.sendall(memoryview(payload)[:cut])
            return fault != Fault.DISCONNECT
        self.sock.sendall(envelope(Msg.FRAME, length=full_len))
        self.sock.sendall(header.pack())
        self.sock.sendall(payload)
        self.sock.sendall(crc)
        return True


def _check_loopback(host: str) -> None:
    try:
        ok = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"the simulator serves on loopback only (127.0.0.1, ::1, localhost), not {host!r}")


class FirmwareServer:
    """TCP endpoint on loopback; one host at a time, others get BUSY. ``port=0`` picks a free port."""

    def __init__(self, device: FirmwareDevice, host: str = "127.0.0.1", port: int = 0):
        _check_loopback(host)
        self.device = device
        self._stop = threading.Event()
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((host, port))
        self._listener.listen(4)
        self._listener.settimeout(POLL_S * 4)
        self.host, self.port = host, self._listener.getsockname()[1]
        self._threads: list[threading.Thread] = []
        self._accept_thread = threading.Thread(target=self._accept_loop, name="bmi-fw-accept", daemon=True)

    @property
    def uri(self) -> str:
        return f"tcp://{self.host}:{self.port}"

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
            t = threading.Thread(target=_Connection(self.device, sock, self._stop).run,
                                 name="bmi-fw-conn", daemon=True)
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
    """The device served on one end of a socket pair in a thread of this process; ``sock`` is the host's end."""

    def __init__(self, device: FirmwareDevice):
        self._stop = threading.Event()
        self.sock, device_end = socket.socketpair()
        self._thread = threading.Thread(target=_Connection(device, device_end, self._stop).run,
                                        name="bmi-fw-inproc", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=SEND_TIMEOUT_S)
