"""Register map of the BMI camera: addresses, units, ranges, access, and the result codes of an access.

Every register is a 32-bit word at a 4-byte-aligned address (signed only where
noted). A write outside a register's range is *refused* with an error code and
the register keeps its value; nothing is ever clamped. The last refusal's code
is latched in ``LAST_ERROR`` and flagged in ``STATUS``. The device sends this
map to the host (``describe()``, in the HELLO reply) so the host's typed
settings show the same ranges. Both ends import it from here: the simulated
firmware enforces it (``firmware_sim.register_file``), the host reads its names
and codes (``devices``).
"""

from __future__ import annotations

import enum
from dataclasses import asdict, dataclass

FIRMWARE_VERSION = (0, 4, 0)


class RegError(enum.IntEnum):
    """Result codes of a register access (0 = OK)."""

    OK = 0
    UNKNOWN_ADDRESS = 1
    READ_ONLY = 2
    OUT_OF_RANGE = 3
    MISALIGNED = 4      # ROI offsets and sizes must be even (whole 2×2 CFA cells)
    CONFLICT = 5        # ROI would reach past the sensor edge
    BUSY = 6            # ROI cannot change while acquiring


class Status(enum.IntFlag):
    """Bits of the STATUS register."""

    ACQUIRING = 1
    ERROR_LATCHED = 2    # a write was refused since the last LAST_ERROR read
    TEST_PATTERN = 4     # pixels come from the digital test pattern, not the sensor


class TestPattern(enum.IntEnum):
    """Digital test patterns injected after the ADC (bit-exact, for link checks)."""

    __test__ = False  # not a pytest class

    OFF = 0
    RAMP = 1          # (row + col) mod 4096 in full-sensor coordinates
    WALKING = 2       # (row + col + frame_id) mod 4096: changes every frame


@dataclass(frozen=True)
class Register:
    address: int
    name: str
    unit: str
    minimum: int
    maximum: int
    default: int
    writable: bool
    doc: str
    even: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


SENSOR_WIDTH_PX = 6000
SENSOR_HEIGHT_PX = 4500
U32_MAX = 2**32 - 1

REGISTERS: tuple[Register, ...] = (
    Register(0x000, "FW_VERSION", "major<<16|minor<<8|patch", 0, U32_MAX,
             FIRMWARE_VERSION[0] << 16 | FIRMWARE_VERSION[1] << 8 | FIRMWARE_VERSION[2], False, "firmware version"),
    Register(0x004, "SERIAL", "number", 0, U32_MAX, 0, False, "device serial number (shown as BMI-%08X)"),
    Register(0x008, "SENSOR_WIDTH_PX", "px", SENSOR_WIDTH_PX, SENSOR_WIDTH_PX, SENSOR_WIDTH_PX, False,
             "full sensor width"),
    Register(0x00C, "SENSOR_HEIGHT_PX", "px", SENSOR_HEIGHT_PX, SENSOR_HEIGHT_PX, SENSOR_HEIGHT_PX, False,
             "full sensor height"),
    Register(0x010, "STATUS", "bit flags (Status)", 0, 7, 0, False, "ACQUIRING=1, ERROR_LATCHED=2, TEST_PATTERN=4"),
    Register(0x014, "LAST_ERROR", "RegError code", 0, 6, 0, False, "code of the last refused write; reading clears"),
    Register(0x020, "EXPOSURE_US", "µs", 10, 1_000_000, 10_000, True, "integration time"),
    Register(0x024, "ANALOG_GAIN_MILLI", "1/1000 ×", 1000, 16_000, 1000, True, "analog gain ×1000 (1× … 16×)"),
    Register(0x028, "BLACK_LEVEL_DN", "DN", 0, 1023, 256, True, "offset added before the 12-bit ADC"),
    Register(0x02C, "TEST_PATTERN", "TestPattern", 0, 2, 0, True, "0 off (sensor), 1 ramp, 2 walking ramp"),
    Register(0x030, "ROI_X_PX", "px", 0, SENSOR_WIDTH_PX - 2, 0, True, "window left edge (even)", even=True),
    Register(0x034, "ROI_Y_PX", "px", 0, SENSOR_HEIGHT_PX - 2, 0, True, "window top edge (even)", even=True),
    Register(0x038, "ROI_WIDTH_PX", "px", 2, SENSOR_WIDTH_PX, SENSOR_WIDTH_PX, True, "window width (even)", even=True),
    Register(0x03C, "ROI_HEIGHT_PX", "px", 2, SENSOR_HEIGHT_PX, SENSOR_HEIGHT_PX, True, "window height (even)",
             even=True),
    Register(0x040, "FRAME_COUNTER", "frames", 0, U32_MAX, 0, False, "frames read out since power-on"),
    Register(0x044, "SENSOR_TEMP_MILLI_C", "m°C (signed)", -40_000, 125_000, 25_000, False, "die temperature"),
)

BY_NAME = {r.name: r for r in REGISTERS}
BY_ADDRESS = {r.address: r for r in REGISTERS}
ROI_REGISTERS = ("ROI_X_PX", "ROI_Y_PX", "ROI_WIDTH_PX", "ROI_HEIGHT_PX")  # the readout window, (x, y, w, h) order


def describe() -> list[dict]:
    """The register map as plain data (what the device sends the host)."""
    return [r.to_dict() for r in REGISTERS]
