"""The simulated camera: register file, sensor readout, frame counter, temperature, fault injector.

``FirmwareDevice`` is what the camera's firmware holds. It knows nothing of
sockets: ``firmware_sim.endpoint`` serves it over a stream (TCP or an
in-process socket pair). One host at a time may hold the device (``claim``),
as with a real camera; when it lets go (``release``), the registers it could
write return to their defaults, so one host's settings never reach the next.

The device knows nothing of sockets, but a holder (the endpoint's session) may
say whether its host has hung up (``Holder.host_gone``): a session notices
that on its own thread, which a loaded machine may run late, and until then
the camera would refuse the next host (the same host, reopening) with BUSY.
``claim`` therefore ends such a session on the spot, and ``held_by`` fences
it: a session that lost the camera cannot touch it any more.
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, Protocol

import numpy as np

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.protocol import registers as R
from bmi_sdk.protocol.wire import FLAG_TEST_PATTERN, HEARTBEAT_S, MODEL_NAME, FrameHeader, pack12, packed_size
from bmi_sdk.sensor import CFA_PATTERN, SensorModel

from .faults import FaultInjector, FaultPlan
from .readout import Readout, ReadoutCancelled
from .register_file import RegisterFile
from .sources import IrradianceSource, PolarChart

LENS_PROFILE_ALIASES = {"monocentric": "bmi_monocentric", "bmi": "bmi_monocentric", "fisheye_matched": "fisheye"}
"""Other names ``optics.get_lens`` takes for a lens profile (``bmi_sdk.lenses``), and the profile each means."""


def lens_profile_name(name: str) -> str:
    """The lens profile a lens name stands for (``fisheye_matched``, the Lens the ``fisheye`` profile traces, is
    ``fisheye``): frames name the profile, which decoders and models match (``models/fisheye.manifest.json``)."""
    return LENS_PROFILE_ALIASES.get(name, name)


def lens_identity(name: str = "bmi_monocentric") -> dict:
    """Name (the lens profile, ``lens_profile_name``) and optical SHA-256 of the lens the camera carries."""
    from bmi_sdk.optics import get_lens

    lens = get_lens(name)  # "fisheye" is the baseline matched to the monocentric lens
    return {"name": lens_profile_name(lens.name), "sha256": lens.sha256()}


class NotHeld(RuntimeError):
    """A session acted on the device after it lost it (its host hung up and another host took the camera)."""


class Holder(Protocol):
    """A host's session as the device sees it; both methods are optional (an object without them is a holder
    whose host is never taken for gone)."""

    def host_gone(self) -> bool:
        """Whether the host has hung up, though the session may not have noticed yet. Called under the
        device's lock: it must not block."""

    def revoke(self) -> None:
        """The camera went to another host: abandon the work in flight. Called under the device's lock."""


_ANONYMOUS = object()  # the holder of ``claim()`` without one


@dataclass
class ReadoutResult:
    header: FrameHeader
    pixels: np.ndarray


class FirmwareDevice:
    """State of one simulated camera. Thread-safe: the link thread and the host's in-process calls share it."""

    def __init__(self, source: IrradianceSource | None = None, serial: int = 1, seed: int = 0,
                 faults: FaultPlan | None = None, geometry: SensorGeometry = BMI_SENSOR,
                 model: SensorModel = SensorModel(), lens: str = "bmi_monocentric", heartbeat_s: float = HEARTBEAT_S):
        """``heartbeat_s``: how often a readout in progress tells the host it is alive (PROGRESS)."""
        if (geometry.width_px, geometry.height_px) != (R.SENSOR_WIDTH_PX, R.SENSOR_HEIGHT_PX):
            raise ValueError(f"the firmware drives a {R.SENSOR_WIDTH_PX}×{R.SENSOR_HEIGHT_PX} sensor, "
                             f"geometry is {geometry.width_px}×{geometry.height_px}")
        if not 0 < heartbeat_s <= HEARTBEAT_S:
            raise ValueError(f"heartbeat_s must be in (0, {HEARTBEAT_S:g}] s (hosts rely on that bound), "
                             f"got {heartbeat_s}")
        self.heartbeat_s = float(heartbeat_s)
        self.regs = RegisterFile(serial)
        self.seed = int(seed)
        self.geometry = geometry
        self.model = model
        self.lens = lens_identity(lens)
        self.injector = FaultInjector(faults or FaultPlan())
        self._readout = Readout(geometry, model)
        self._source = source if source is not None else PolarChart(geometry)
        self._lock = threading.RLock()
        self._readout_lock = threading.Lock()  # one readout at a time, also while a revoked one winds down
        self._holder: object | None = None
        self._boot_ns = time.monotonic_ns()

    # -- ownership ------------------------------------------------------------
    def claim(self, holder: Holder | None = None) -> bool:
        """Take the device for ``holder`` (a host's session); False while another live session holds it.

        A current holder whose ``host_gone()`` says its host has hung up is released first, as if its
        session had ended (registers reset), and revoked: a host that closes and reopens at once, or comes
        back after a crash, is not refused BUSY by its own dead session. A live host keeps the camera.
        """
        with self._lock:
            current = self._holder
            if current is not None:
                gone = getattr(current, "host_gone", None)
                if gone is None or not gone():
                    return False
                self._end_session()
                revoke = getattr(current, "revoke", None)
                if revoke is not None:
                    revoke()
            self._holder = _ANONYMOUS if holder is None else holder
            return True

    @property
    def claimed(self) -> bool:
        """Whether a host holds the device now."""
        return self._holder is not None

    def release(self, holder: Holder | None = None) -> bool:
        """``holder`` lets go (its host closed or lost the link): the session registers return to their
        defaults. A holder that no longer holds the device (another host took it after this one hung up)
        releases nothing; False then."""
        with self._lock:
            if self._holder is None or self._holder is not (_ANONYMOUS if holder is None else holder):
                return False
            self._end_session()
            return True

    def _end_session(self) -> None:
        self._holder = None
        self.regs.reset_session()

    @contextmanager
    def held_by(self, holder: Holder) -> Iterator[None]:
        """Hold the device's lock while ``holder`` holds the device; ``NotHeld`` if it does not (any more).
        A session acts on the device inside this, so it cannot reach the next host's session."""
        with self._lock:
            if self._holder is not holder:
                raise NotHeld("the camera went to another host after this session's host hung up")
            yield

    # -- world ----------------------------------------------------------------
    def load_source(self, source: IrradianceSource) -> None:
        """Put another scene in front of the camera (the simulated world)."""
        if not isinstance(source, IrradianceSource):
            raise TypeError(f"{source!r} is not an irradiance source (needs name, irradiance(), metadata())")
        with self._lock:
            self._source = source

    def set_faults(self, plan: FaultPlan | None) -> None:
        """Replace the fault plan (a fresh injector and ledger)."""
        with self._lock:
            self.injector = FaultInjector(plan or FaultPlan())

    @property
    def source(self) -> IrradianceSource:
        return self._source

    def describe(self) -> dict:
        """What the device tells a host in its HELLO reply."""
        serial = self.regs.get("SERIAL")
        return {
            "model": MODEL_NAME, "serial": f"BMI-{serial:08X}",
            "firmware_version": ".".join(map(str, R.FIRMWARE_VERSION)),
            "registers": R.describe(), "cfa": CFA_PATTERN, "bit_depth": self.model.adc_bits,
            "white_level_dn": self.model.white_level_dn, "geometry": self.geometry.to_dict(),
            "lens": self.lens, "sensor_model": self.model.to_dict(), "source": self._source.metadata(),
            "heartbeat_s": self.heartbeat_s,
        }

    # -- registers ------------------------------------------------------------
    def read_register(self, address: int) -> tuple[R.RegError, int]:
        with self._lock:
            return self.regs.read(address)

    def write_register(self, address: int, value: int) -> R.RegError:
        with self._lock:
            return self.regs.write(address, value)

    def set_acquiring(self, on: bool) -> None:
        with self._lock:
            self.regs.set_status(R.Status.ACQUIRING, on)

    def now_ns(self) -> int:
        """Device clock: nanoseconds since power-on."""
        return time.monotonic_ns() - self._boot_ns

    # -- readout --------------------------------------------------------------
    def read_out(self, cancel: threading.Event | None = None,
                 progress: Callable[[int, int, int], None] | None = None) -> ReadoutResult:
        """Expose and read one frame with the current registers; FRAME_COUNTER advances when it is done.

        ``cancel`` abandons the readout between strips (``ReadoutCancelled``; the frame id is not used
        up); ``progress(frame_id, rows_done, rows_total)`` is called between strips. Readouts run one at
        a time (a session revoked mid-readout winds down before the next host's readout starts).
        """
        with self._readout_lock:
            if cancel is not None and cancel.is_set():  # cancelled while another readout ran
                raise ReadoutCancelled("readout cancelled before it started")
            return self._read_out(cancel, progress)

    def _read_out(self, cancel, progress) -> ReadoutResult:
        with self._lock:
            regs = self.regs
            frame_id = regs.get("FRAME_COUNTER")
            roi = regs.roi()
            exposure_us = regs.get("EXPOSURE_US")
            gain_milli = regs.get("ANALOG_GAIN_MILLI")
            black = regs.get("BLACK_LEVEL_DN")
            pattern = R.TestPattern(regs.get("TEST_PATTERN"))
            source = self._source
        start_ns = self.now_ns()
        if pattern == R.TestPattern.OFF:
            rng = np.random.default_rng([self.seed, frame_id])
            strip_progress = None if progress is None else (lambda done, total: progress(frame_id, done, total))
            pixels = self._readout.sensor_frame(source, roi, exposure_us, gain_milli / 1000, black, rng,
                                                cancel=cancel, progress=strip_progress)
        else:
            pixels = self._readout.test_pattern(pattern, roi, frame_id)
        with self._lock:
            regs.set_internal("FRAME_COUNTER", (frame_id + 1) & R.U32_MAX)
            temp_mc = int(25_000 + 15_000 * (1 - math.exp(-(frame_id + 1) / 2000)))
            regs.set_internal("SENSOR_TEMP_MILLI_C", temp_mc)
        x, y, w, h = roi
        header = FrameHeader(
            frame_id=frame_id, device_ts_ns=start_ns, readout_ts_ns=self.now_ns(), exposure_us=exposure_us,
            gain_milli=gain_milli, black_level_dn=black, white_level_dn=self.model.white_level_dn,
            roi_x_px=x, roi_y_px=y, width_px=w, height_px=h, temperature_milli_c=temp_mc,
            payload_len=packed_size(w * h), flags=FLAG_TEST_PATTERN if pattern else 0)
        return ReadoutResult(header, pixels)

    def frame_bytes(self, cancel: threading.Event | None = None,
                    progress: Callable[[int, int, int], None] | None = None) -> tuple[FrameHeader, bytes]:
        """Read out one frame (see ``read_out``) and pack its payload (RAW12) as it goes on the wire."""
        result = self.read_out(cancel, progress)
        return result.header, pack12(result.pixels)
