"""One hierarchy for everything a camera can refuse or suffer; no call reports failure with a silent False."""

from __future__ import annotations


class CameraError(Exception):
    """Base of all device errors."""


class DeviceNotFoundError(CameraError, LookupError):
    """No camera answers at this URI (nothing listening, no such folder, unknown scheme)."""


class DeviceBusyError(CameraError):
    """Another host (or another open_camera in this process) holds the camera."""


class AccessDeniedError(CameraError, PermissionError):
    """The device wants a token (``tcp://HOST:PORT?token=…``) and none or a wrong one was given."""


class DeviceFaultError(CameraError):
    """The device reported that it could not deliver (a readout failed); the link is still up."""


class DeviceRemovedError(CameraError, ConnectionError):
    """The link dropped (unplugged, device reset, stream ended mid-frame). ``reconnect()`` may recover."""


class GrabTimeoutError(CameraError, TimeoutError):
    """No frame arrived within the timeout."""


class IncompleteFrameError(CameraError):
    """A frame arrived short (missing payload) or with a CRC mismatch, and a complete one was required."""


class ConfigurationError(CameraError, ValueError):
    """A setting outside its range or a call that does not fit the camera's state; nothing was sent."""


class ProtocolError(CameraError):
    """The device sent bytes that do not follow docs/protocol.md (bad magic, CRC, impossible length)."""


class RawFileError(CameraError, ValueError):
    """A raw file that is not a BMI raw frame (another camera's DNG, a missing or mismatched sidecar)."""


class NoiseProfileWarning(UserWarning):
    """A noise profile could not be read (a device's unreadable sensor model, a malformed DNG NoiseProfile tag
    in another camera's raw file): the frame comes without one (``noise_profile`` None)."""
