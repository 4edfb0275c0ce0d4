"""``RawFrame``: one raw readout with everything needed to interpret it later, and the buffer pool behind it.

A frame from ``Camera.grab`` lives in one of the camera's acquisition buffers.
It goes back to the pool when you call ``frame.release()``, leave a
``with frame:`` block, or drop the last reference to the frame; use
``frame.copy()`` to keep pixels beyond that. Frames from ``capture()``,
``copy()`` and ``load_raw`` own their data.
"""

from __future__ import annotations

import enum
import threading
import weakref
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from bmi_sdk.geometry import SensorGeometry
from bmi_sdk.sensor import NoiseProfile

from .errors import ConfigurationError, IncompleteFrameError

SIDECAR_SCHEMA = "bmi-raw-sidecar/1"


class FrameStatus(str, enum.Enum):
    COMPLETE = "complete"
    INCOMPLETE = "incomplete"   # payload cut short; missing pixels are 0
    CORRUPT = "corrupt"         # payload CRC mismatch; pixels as received


@dataclass(frozen=True)
class Roi:
    """Readout window on the full sensor, in pixels (offsets and sizes even: whole RGGB cells).

    The constructor refuses what no sensor holds (``ConfigurationError``): values that are not whole numbers,
    negative offsets, sizes below 1 px. Evenness and the sensor's bounds are the camera's to check
    (``Settings.check_roi``): a foreign raw file may have odd sizes.
    """

    x_px: int
    y_px: int
    width_px: int
    height_px: int

    def __post_init__(self):
        least_px = {"x_px": 0, "y_px": 0, "width_px": 1, "height_px": 1}
        for name, least in least_px.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ConfigurationError(f"Roi {name} must be a whole number of pixels, got {value!r}")
            if value < least:
                raise ConfigurationError(f"Roi {name} must be ≥ {least} px, got {value}")
            object.__setattr__(self, name, int(value))


@dataclass(eq=False)
class RawFrame:
    data: np.ndarray                 # H×W uint16 DN
    frame_id: int
    status: FrameStatus
    black_level_dn: int
    white_level_dn: int
    exposure_us: int                 # as applied by the device
    analog_gain: float               # as applied by the device
    temperature_c: float
    device_timestamp_ns: int         # start of exposure, device clock
    readout_timestamp_ns: int        # end of readout, device clock
    host_timestamp_ns: int           # arrival, host wall clock (time.time_ns)
    roi: Roi
    geometry: SensorGeometry
    lens: dict                       # {"name", "sha256"} of the lens on the camera
    device: dict                     # {"model", "serial", "firmware_version"}
    cfa: str = "RGGB"
    skipped_frames: int = 0          # frame ids missing between the previous delivered frame and this one
    test_pattern: bool = False
    source: dict | None = None       # what the simulated world showed (None on hardware)
    calibration_id: str | None = None
    is_bmi: bool = True              # False: a raw file from another camera (load_raw(require_bmi=False))
    noise_profile: NoiseProfile | None = None  # the pixels' noise (DNG NoiseProfile); None: unknown, or a test pattern
    _finalizer: weakref.finalize | None = field(default=None, repr=False)

    # -- buffer ownership ------------------------------------------------------
    def release(self) -> None:
        """Give the acquisition buffer back (safe to call twice; no-op for frames that own their data)."""
        if self._finalizer is not None:
            self._finalizer()

    def __enter__(self) -> "RawFrame":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def copy(self) -> "RawFrame":
        """A frame that owns a copy of the pixels (outlives the acquisition buffer)."""
        return replace(self, data=self.data.copy(), _finalizer=None)

    # -- checks and metadata -----------------------------------------------------
    @property
    def complete(self) -> bool:
        return self.status == FrameStatus.COMPLETE

    def check(self) -> "RawFrame":
        """Return self if complete; raise IncompleteFrameError naming the problem otherwise."""
        if self.status != FrameStatus.COMPLETE:
            raise IncompleteFrameError(f"frame {self.frame_id} is {self.status.value}")
        return self

    @property
    def metadata(self) -> dict:
        """Everything but the pixels, as a new JSON-able dict (the DNG sidecar carries it): ``frame.metadata["roi"]``."""
        return {
            "schema": SIDECAR_SCHEMA, "frame_id": self.frame_id, "status": self.status.value, "cfa": self.cfa,
            "black_level_dn": self.black_level_dn, "white_level_dn": self.white_level_dn,
            "exposure_us": self.exposure_us, "analog_gain": self.analog_gain, "temperature_c": self.temperature_c,
            "device_timestamp_ns": self.device_timestamp_ns, "readout_timestamp_ns": self.readout_timestamp_ns,
            "host_timestamp_ns": self.host_timestamp_ns, "roi": asdict(self.roi),
            "geometry": self.geometry.to_dict(), "lens": self.lens, "device": self.device,
            "skipped_frames": self.skipped_frames, "test_pattern": self.test_pattern, "source": self.source,
            "calibration_id": self.calibration_id, "shape": list(self.data.shape),
            "noise_profile": None if self.noise_profile is None else self.noise_profile.to_dict(),
        }

    def save_dng(self, path, overwrite: bool = False) -> None:
        """Write a DNG (readable by rawpy) and its JSON sidecar ``<path>.json``, both atomically.

        An existing DNG or sidecar is refused (``FileExistsError``) unless ``overwrite=True``; a same-named
        JSON that is not this DNG's sidecar is never replaced (``devices.dng.save_dng``).
        """
        from .dng import save_dng

        save_dng(self, path, overwrite=overwrite)


class BufferPool:
    """A fixed set of H×W uint16 buffers; ``take`` returns None when all are out (never allocates more)."""

    def __init__(self, count: int, shape: tuple[int, int]):
        self.shape = shape
        self.count = count
        self._free = [np.empty(shape, np.uint16) for _ in range(count)]
        self._lock = threading.Lock()

    def take(self) -> np.ndarray | None:
        with self._lock:
            return self._free.pop() if self._free else None

    def give(self, buf: np.ndarray) -> None:
        with self._lock:
            if any(b is buf for b in self._free):
                raise RuntimeError("buffer returned twice to the pool")
            self._free.append(buf)

    @property
    def free(self) -> int:
        with self._lock:
            return len(self._free)

    def attach(self, frame: RawFrame, buf: np.ndarray) -> RawFrame:
        """Make ``frame`` hand ``buf`` back when released or garbage-collected."""
        frame._finalizer = weakref.finalize(frame, self.give, buf)
        return frame
