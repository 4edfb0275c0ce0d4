"""The simulated camera's register values, with the refusal rules of the register map.

The map itself (addresses, ranges, codes) is the protocol's
(``bmi_sdk.protocol.registers``) and the host reads it too; this is the state
only the firmware holds: the values, what a refused write latches, and what a
host's disconnect resets.
"""

from __future__ import annotations

from bmi_sdk.protocol.registers import (
    BY_ADDRESS,
    BY_NAME,
    REGISTERS,
    ROI_REGISTERS,
    SENSOR_HEIGHT_PX,
    SENSOR_WIDTH_PX,
    U32_MAX,
    RegError,
    Status,
    TestPattern,
)


class RegisterFile:
    """The device's register values with the refusal rules of the map."""

    def __init__(self, serial: int = 0):
        self._values = {r.address: r.default for r in REGISTERS}
        self._values[BY_NAME["SERIAL"].address] = int(serial) & U32_MAX

    # -- firmware-side access (no checks: the firmware owns read-only registers)
    def get(self, name: str) -> int:
        return self._values[BY_NAME[name].address]

    def set_internal(self, name: str, value: int) -> None:
        self._values[BY_NAME[name].address] = int(value)

    def set_status(self, flag: Status, on: bool) -> None:
        status = Status(self.get("STATUS"))
        self.set_internal("STATUS", int(status | flag if on else status & ~flag))

    # -- host-side access, as it arrives over the link -----------------------
    def read(self, address: int) -> tuple[RegError, int]:
        reg = BY_ADDRESS.get(address)
        if reg is None:
            return self._refuse(RegError.UNKNOWN_ADDRESS), 0
        value = self._values[address]
        if reg.name == "LAST_ERROR":
            self._values[address] = 0
            self.set_status(Status.ERROR_LATCHED, False)
        return RegError.OK, value

    def write(self, address: int, value: int) -> RegError:
        reg = BY_ADDRESS.get(address)
        if reg is None:
            return self._refuse(RegError.UNKNOWN_ADDRESS)
        if not reg.writable:
            return self._refuse(RegError.READ_ONLY)
        if not reg.minimum <= value <= reg.maximum:
            return self._refuse(RegError.OUT_OF_RANGE)
        if reg.even and value % 2:
            return self._refuse(RegError.MISALIGNED)
        if reg.name in ROI_REGISTERS:
            if self.get("STATUS") & Status.ACQUIRING:
                return self._refuse(RegError.BUSY)
            window = {n: self.get(n) for n in ROI_REGISTERS} | {reg.name: value}
            x_px, y_px, width_px, height_px = (window[n] for n in ROI_REGISTERS)
            if x_px + width_px > SENSOR_WIDTH_PX or y_px + height_px > SENSOR_HEIGHT_PX:
                return self._refuse(RegError.CONFLICT)
        self._values[address] = int(value)
        if reg.name == "TEST_PATTERN":
            self.set_status(Status.TEST_PATTERN, value != TestPattern.OFF)
        return RegError.OK

    def _refuse(self, code: RegError) -> RegError:
        self._values[BY_NAME["LAST_ERROR"].address] = int(code)
        self.set_status(Status.ERROR_LATCHED, True)
        return code

    def reset_session(self) -> None:
        """A host let go: every writable register back to its default, LAST_ERROR and STATUS cleared.

        Nothing one host wrote (test pattern, exposure, black level, window) reaches the next one;
        the serial, frame counter and temperature are the device's own and stay.
        """
        for reg in REGISTERS:
            if reg.writable:
                self._values[reg.address] = reg.default
        self.set_internal("LAST_ERROR", 0)
        self.set_internal("STATUS", 0)

    def roi(self) -> tuple[int, int, int, int]:
        """(x, y, width, height) of the readout window on the full sensor."""
        return tuple(self.get(n) for n in ROI_REGISTERS)
