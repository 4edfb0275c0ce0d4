"""``ReplayCamera``: a folder of BMI DNGs (with sidecars) behaving like a camera.

Frames come back in file-name order through the same calls as a live camera
(``start``/``grab``/``try_grab``/``capture``/``stop``). Settings are what the
files recorded, so writing one raises ``ConfigurationError``. At the end of the
folder ``grab`` raises ``GrabTimeoutError`` at once (``loop=True`` wraps around).

A file that cannot be read as a BMI frame (junk, empty, truncated, another
camera's) is skipped as a camera skips a corrupt readout: an
``UnreadableFrameWarning`` names it and why, ``skipped`` lists it, and
``stats["unreadable"]`` counts it; the frames around it still play. A folder
with no readable frame at all is refused when opened.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Callable

from .dng import load_raw
from .errors import ConfigurationError, DeviceNotFoundError, GrabTimeoutError, RawFileError
from .frame import RawFrame


class UnreadableFrameWarning(UserWarning):
    """A replay folder's file could not be read as a BMI frame and was skipped (``ReplayCamera.skipped``)."""


class ReplaySettings:
    def __init__(self, camera: "ReplayCamera"):
        object.__setattr__(self, "_camera", camera)

    def __getattr__(self, name):
        frame = self._camera._peek()
        values = {"exposure_us": frame.exposure_us, "analog_gain": frame.analog_gain,
                  "black_level_dn": frame.black_level_dn, "test_pattern": int(frame.test_pattern), "roi": frame.roi}
        if name not in values:
            raise AttributeError(f"no setting {name!r}")
        return values[name]

    def __setattr__(self, name, value):
        raise ConfigurationError(f"a replay camera plays recorded frames; {name} cannot be set")

    def ranges(self) -> dict:
        return {}


class ReplayCamera:
    def __init__(self, uri: str, folder: str | Path, loop: bool = False,
                 on_frame: Callable[[RawFrame], None] | None = None,
                 on_disconnect: Callable[[str], None] | None = None):
        folder = Path(folder)
        if not folder.is_dir():
            raise DeviceNotFoundError(f"{uri}: no folder {folder}")
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".dng")
        if not self.files:
            raise DeviceNotFoundError(f"{uri}: folder {folder} holds no .dng files")
        self.uri = uri
        self.loop = loop
        self.on_frame = on_frame
        self.on_disconnect = on_disconnect  # a folder never disconnects; kept for the same signature
        self._next = 0
        self._streaming = False
        self._closed = False
        self.skipped: list[tuple[Path, str]] = []  # (file, why) of every unreadable file met so far
        self._reasons: dict[Path, str] = {}
        self.stats = {"delivered": 0, "complete": 0, "incomplete": 0, "corrupt": 0, "unreadable": 0}
        first = None
        for path in self.files:  # the first readable frame gives the camera's identity
            first = self._load(path)
            if first is not None:
                break
        if first is None:
            path, why = self.skipped[0]
            raise DeviceNotFoundError(f"{uri}: none of the {len(self.files)} .dng files in {folder} is a readable "
                                      f"BMI frame ({path.name}: {why})")
        self._first = first
        self.geometry, self.lens, self.device = first.geometry, first.lens, first.device
        self.info = {"model": first.device.get("model"), "serial": first.device.get("serial"), "replay": str(folder)}
        self.settings = ReplaySettings(self)

    def _load(self, path: Path) -> RawFrame | None:
        """The frame in ``path``, or None for an unreadable file (warned about and listed once)."""
        if path in self._reasons:
            return None
        try:
            return load_raw(path)
        except (RawFileError, OSError) as exc:
            why = str(exc).replace(f"{path}: ", "").replace(f"{path} ", "")
            self._reasons[path] = why
            self.skipped.append((path, why))
            self.stats["unreadable"] += 1
            warnings.warn(f"{self.uri}: skipped {path.name}: {why}", UnreadableFrameWarning, stacklevel=3)
            return None

    def _peek(self) -> RawFrame:
        return self._first

    def _read_next(self) -> RawFrame:
        if self._closed:
            raise ConfigurationError(f"camera {self.uri} is closed")
        frame = None
        while frame is None:
            if len(self._reasons) == len(self.files):
                raise GrabTimeoutError(f"{self.uri}: none of the {len(self.files)} recorded frames is readable")
            if self._next >= len(self.files):
                if not self.loop:
                    raise GrabTimeoutError(f"{self.uri}: all {len(self.files)} recorded frames played")
                self._next = 0
            frame = self._load(self.files[self._next])
            self._next += 1
        self.stats["delivered"] += 1
        self.stats[frame.status.value] += 1
        if self.on_frame is not None:
            self.on_frame(frame)
        return frame

    def start(self, strategy: str = "oldest_first", buffers: int = 4) -> None:
        if strategy not in ("oldest_first", "latest_only"):
            raise ConfigurationError(f"strategy must be oldest_first or latest_only, got {strategy!r}")
        self._streaming = True

    def stop(self) -> None:
        self._streaming = False

    def grab(self, timeout_s: float = 5.0) -> RawFrame:
        if not self._streaming:
            raise ConfigurationError("grab() needs start() first (or use capture())")
        return self._read_next()

    def try_grab(self) -> RawFrame | None:
        try:
            return self.grab()
        except GrabTimeoutError:
            return None

    def capture(self, timeout_s: float = 10.0) -> RawFrame:
        if self._streaming:
            raise ConfigurationError("capture() while streaming; use grab() or stop() first")
        return self._read_next().check()

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> "ReplayCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
