"""Wire format of the BMI camera (specified in docs/protocol.md): messages, frame header, RAW12 payload, CRC32.

The device (``firmware_sim``, or hardware) writes it and the host
(``devices``) reads it; both import it from here, so neither depends on the
other.

Everything on the link is a *message*: a 12-byte envelope (magic ``BMIP``,
type, body length) and a body. A FRAME message's body is a frame header, the
packed 12-bit payload and a CRC32 of the payload. All integers little-endian.

Lengths are checked *before* anything is allocated: an envelope longer than
``MAX_BODY_BYTES`` or a frame header whose ``payload_len`` disagrees with its
width × height is refused with ``WireError``, so a hostile or broken length
field cannot exhaust memory.

The timing both ends rely on (reply deadline, heartbeat period, longest stall,
idle timeout), the model name a device reports and the form of a TCP camera's
URI are defined here once and read by the device and the host.
"""

from __future__ import annotations

import enum
import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from .registers import SENSOR_HEIGHT_PX, SENSOR_WIDTH_PX


class WireError(ValueError):
    """Bytes that do not follow the protocol (bad magic, version, CRC, length)."""


# -- messages -----------------------------------------------------------------
ENVELOPE = struct.Struct("<4sHHI")  # magic, type, reserved (0), body length
ENVELOPE_MAGIC = b"BMIP"


class Msg(enum.IntEnum):
    HELLO = 1        # host → device: empty; device → host: JSON device description
    BUSY = 2         # device → host: JSON {"reason"}; the device then closes the link
    READ_REG = 3     # host → device: u32 address
    WRITE_REG = 4    # host → device: u32 address, i64 value
    REG_REPLY = 5    # device → host: u32 address, u32 RegError, i64 value
    START = 6        # host → device: u32 frame count (0 = until STOP)
    STOP = 7         # host → device: empty
    ACK = 8          # device → host: u32 type acknowledged, u32 error (0 ok)
    FRAME = 9        # device → host: frame header + payload + CRC32 (may be cut short: incomplete)
    PING = 10        # host → device: empty; keep-alive, answered by ACK
    AUTH = 11        # host → device: the shared token (1 … MAX_TOKEN_BYTES bytes); answered by ACK
    PROGRESS = 12    # device → host: u64 frame id, u32 work done, u32 work total (heartbeat of a readout)
    ERROR = 13       # device → host: JSON {"code", "reason", "in_reply_to"}: a refused message or a failure


REG_ACCESS = struct.Struct("<Iq")
REG_REPLY = struct.Struct("<IIq")
U32 = struct.Struct("<I")
ACK = struct.Struct("<II")
PROGRESS = struct.Struct("<QII")
MAX_CONTROL_BYTES = 1 << 20
MAX_TOKEN_BYTES = 256

# Body sizes of the host's messages (AUTH: 1 … MAX_TOKEN_BYTES); a device answers any other size with ERROR.
HOST_BODY_BYTES = {Msg.HELLO: 0, Msg.READ_REG: U32.size, Msg.WRITE_REG: REG_ACCESS.size, Msg.START: U32.size,
                   Msg.STOP: 0, Msg.PING: 0}

MODEL_NAME = "BMI-SIM"  # HELLO's "model"; a DNG carries it as its Model and is recognised as a BMI capture by it

# -- timing: the one place both ends read (docs/protocol.md, "Timing") ----------
REPLY_TIMEOUT_S = 5.0          # a device answers every request within this, also while it reads out or stalls
HEARTBEAT_S = 1.0              # a readout in progress sends PROGRESS at least this often
MAX_STALL_S = 10.0             # the longest a device may hold a finished frame back
DEFAULT_IDLE_TIMEOUT_S = 60.0  # a TCP device drops a host that sent no whole message for this long (not streaming)


def tcp_uri(host: str, port: int) -> str:
    """``tcp://HOST:PORT``, an IPv6 literal in brackets (``tcp://[::1]:PORT``) as URIs write it."""
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


# -- frames -------------------------------------------------------------------
FRAME_MAGIC = b"BMIF"
FRAME_VERSION = 1
_HEADER_FIELDS = struct.Struct("<4sHHQQQIIHHIIIIBBHiQ")
HEADER = struct.Struct(_HEADER_FIELDS.format + "I")  # + CRC32 of the fields before it
CRC = struct.Struct("<I")
CFA_CODES = {0: "RGGB"}
FLAG_TEST_PATTERN = 1


def packed_size(pixels: int) -> int:
    """Bytes of a RAW12 payload: two pixels in three bytes."""
    if pixels % 2:
        raise WireError(f"a RAW12 payload needs an even pixel count, got {pixels}")
    return pixels // 2 * 3


MAX_PAYLOAD_BYTES = packed_size(SENSOR_WIDTH_PX * SENSOR_HEIGHT_PX)
MAX_BODY_BYTES = HEADER.size + MAX_PAYLOAD_BYTES + CRC.size


@dataclass(frozen=True)
class FrameHeader:
    frame_id: int
    device_ts_ns: int       # start of exposure, device clock
    readout_ts_ns: int      # end of readout, device clock
    exposure_us: int
    gain_milli: int
    black_level_dn: int
    white_level_dn: int
    roi_x_px: int
    roi_y_px: int
    width_px: int
    height_px: int
    temperature_milli_c: int
    payload_len: int
    bit_depth: int = 12
    cfa: str = "RGGB"
    flags: int = 0

    def pack(self) -> bytes:
        cfa_code = {v: k for k, v in CFA_CODES.items()}[self.cfa]
        fields = _HEADER_FIELDS.pack(
            FRAME_MAGIC, FRAME_VERSION, HEADER.size, self.frame_id, self.device_ts_ns, self.readout_ts_ns,
            self.exposure_us, self.gain_milli, self.black_level_dn, self.white_level_dn,
            self.roi_x_px, self.roi_y_px, self.width_px, self.height_px, self.bit_depth, cfa_code, self.flags,
            self.temperature_milli_c, self.payload_len)
        return fields + CRC.pack(zlib.crc32(fields))

    @classmethod
    def parse(cls, data: bytes | memoryview) -> "FrameHeader":
        """Validate and parse a header; every check runs before the payload is touched."""
        if len(data) < HEADER.size:
            raise WireError(f"frame header truncated: {len(data)} of {HEADER.size} bytes")
        (magic, version, header_len, frame_id, dev_ts, ro_ts, exposure, gain, black, white, x, y, w, h,
         bits, cfa_code, flags, temp, payload_len, crc) = HEADER.unpack_from(data)
        if magic != FRAME_MAGIC:
            raise WireError(f"bad frame magic {bytes(magic)!r} (expected {FRAME_MAGIC!r})")
        if version != FRAME_VERSION:
            raise WireError(f"unsupported frame version {version} (this host reads version {FRAME_VERSION})")
        if header_len != HEADER.size:
            raise WireError(f"frame header length {header_len} != {HEADER.size} for version {version}")
        if zlib.crc32(bytes(data[:_HEADER_FIELDS.size])) != crc:
            raise WireError("frame header CRC mismatch")
        if bits != 12:
            raise WireError(f"unsupported bit depth {bits} (RAW12 only)")
        if cfa_code not in CFA_CODES:
            raise WireError(f"unknown CFA code {cfa_code}")
        if not (0 < w <= SENSOR_WIDTH_PX and 0 < h <= SENSOR_HEIGHT_PX and w % 2 == 0 and h % 2 == 0
                and x + w <= SENSOR_WIDTH_PX and y + h <= SENSOR_HEIGHT_PX):
            raise WireError(f"frame window {w}×{h} at ({x}, {y}) does not fit the "
                            f"{SENSOR_WIDTH_PX}×{SENSOR_HEIGHT_PX} sensor")
        if payload_len != packed_size(w * h):
            raise WireError(f"payload_len {payload_len} does not match a {w}×{h} RAW12 frame "
                            f"({packed_size(w * h)} bytes)")
        return cls(frame_id, dev_ts, ro_ts, exposure, gain, black, white, x, y, w, h, temp, payload_len,
                   bits, CFA_CODES[cfa_code], flags)


# -- RAW12 packing --------------------------------------------------------------
# Pixel pair (p0, p1) → 24-bit little-endian word p0 | p1 << 12:
#   byte0 = p0 & 0xFF, byte1 = (p0 >> 8) | (p1 & 0x0F) << 4, byte2 = p1 >> 4.
_CHUNK_PAIRS = 1 << 18  # work in cache-sized chunks


def pack12(pixels: np.ndarray) -> bytes:
    """uint16 pixels (values < 4096, even count) → RAW12 bytes."""
    flat = np.ascontiguousarray(pixels, dtype=np.uint16).reshape(-1)
    pairs = flat.reshape(-1, 2) if flat.size % 2 == 0 else None
    if pairs is None:
        raise WireError(f"a RAW12 payload needs an even pixel count, got {flat.size}")
    out = np.empty((pairs.shape[0], 3), np.uint8)
    word = np.empty(min(_CHUNK_PAIRS, pairs.shape[0]), np.uint32)
    for s in range(0, pairs.shape[0], _CHUNK_PAIRS):
        p = pairs[s:s + _CHUNK_PAIRS]
        w = word[:p.shape[0]]
        np.left_shift(p[:, 1], 12, out=w, dtype=np.uint32)
        w |= p[:, 0]
        out[s:s + p.shape[0]] = w.view(np.uint8).reshape(-1, 4)[:, :3]
    return out.tobytes()


def unpack12(data: bytes | memoryview, out: np.ndarray) -> None:
    """RAW12 bytes → ``out`` (uint16, any shape with 2 × len/3 elements), in place."""
    raw = np.frombuffer(data, np.uint8)
    if raw.size % 3:
        raise WireError(f"RAW12 data of {raw.size} bytes is not a whole number of pixel pairs")
    triples = raw.reshape(-1, 3)
    flat = out.reshape(-1)
    if flat.size != 2 * triples.shape[0]:
        raise WireError(f"RAW12 data holds {2 * triples.shape[0]} pixels, buffer has {flat.size}")
    pairs = flat.reshape(-1, 2)
    quad = np.zeros((min(_CHUNK_PAIRS, triples.shape[0]), 4), np.uint8)
    for s in range(0, triples.shape[0], _CHUNK_PAIRS):
        t = triples[s:s + _CHUNK_PAIRS]
        q = quad[:t.shape[0]]
        q[:, :3] = t
        w = q.view(np.uint32).reshape(-1)
        pairs[s:s + t.shape[0], 0] = w & 0xFFF
        pairs[s:s + t.shape[0], 1] = w >> 12


def encode_frame(header: FrameHeader, payload: bytes) -> bytes:
    """FRAME body: header, payload, CRC32(payload)."""
    if len(payload) != header.payload_len:
        raise WireError(f"payload is {len(payload)} bytes, header says {header.payload_len}")
    return header.pack() + payload + CRC.pack(zlib.crc32(payload))


def envelope(msg: Msg, body: bytes = b"", length: int | None = None) -> bytes:
    """The 12-byte envelope of a message whose body is ``body`` (or ``length`` bytes sent separately)."""
    return ENVELOPE.pack(ENVELOPE_MAGIC, int(msg), 0, len(body) if length is None else length)


def parse_envelope(data: bytes) -> tuple[Msg, int]:
    """(type, body length) of a 12-byte envelope; refuses unknown types and oversize bodies."""
    magic, mtype, _reserved, length = ENVELOPE.unpack(data)
    if magic != ENVELOPE_MAGIC:
        raise WireError(f"bad message magic {magic!r} (expected {ENVELOPE_MAGIC!r}): stream out of sync")
    try:
        msg = Msg(mtype)
    except ValueError:
        raise WireError(f"unknown message type {mtype}") from None
    limit = MAX_BODY_BYTES if msg == Msg.FRAME else MAX_CONTROL_BYTES
    if length > limit:
        raise WireError(f"{msg.name} message claims {length} bytes, more than the {limit} a "
                        f"{SENSOR_WIDTH_PX}×{SENSOR_HEIGHT_PX} RAW12 camera can send")
    return msg, length


def json_body(obj) -> bytes:
    return json.dumps(obj).encode()


def error_body(code: str, reason: str, in_reply_to: Msg | None = None) -> bytes:
    """ERROR body; ``in_reply_to`` is the refused request's type (0: unsolicited, e.g. a failed readout)."""
    return json_body({"code": code, "reason": reason, "in_reply_to": int(in_reply_to or 0)})


def check_host_body(msg: Msg, length: int) -> str | None:
    """Why a host message of this type cannot have a body of ``length`` bytes (None: it can)."""
    if msg == Msg.AUTH:
        if not 1 <= length <= MAX_TOKEN_BYTES:
            return f"AUTH carries a token of 1 to {MAX_TOKEN_BYTES} bytes, got {length}"
        return None
    expected = HOST_BODY_BYTES.get(msg)
    if expected is None:
        return f"host sent {msg.name}, which only a device sends"
    if length != expected:
        return f"{msg.name} body is {length} bytes, expected {expected}"
    return None
