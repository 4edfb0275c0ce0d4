"""``Camera``: the interface every camera that ``open_camera`` returns offers.

``StreamCamera`` (``sim://``, ``tcp://``) and ``ReplayCamera`` (``replay://``)
both implement it; code that only acquires frames (``bmi acquire``, the
calibration capture loop, an application) should type its argument as
``Camera`` so that a recorded folder can stand in for a live camera. The
protocol is ``runtime_checkable``; tests/test_camera_protocol.py checks that
both classes satisfy it with the same method signatures.

Live cameras offer more (``reconnect``, ``read_register``, ``buffers_free``);
those are not part of the shared interface.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol, runtime_checkable

if TYPE_CHECKING:
    from typing import Self

    from bmi_sdk.geometry import SensorGeometry

    from .frame import RawFrame


@runtime_checkable
class Camera(Protocol):
    """Acquisition: ``start`` / ``grab`` / ``try_grab`` / ``stop`` to stream, ``capture`` for one
    frame; a context manager that ``close``s."""

    uri: str
    info: dict
    """What the device says about itself: at least ``model`` and ``serial``."""
    geometry: SensorGeometry
    lens: dict
    """The lens identity stamped on every frame (``name``, ``sha256``)."""
    device: dict
    """The device identity stamped on every frame (``model``, ``serial``, ...)."""
    settings: Any
    """``exposure_us``, ``analog_gain``, ``black_level_dn``, ``test_pattern``, ``roi`` and ``ranges()``;
    a replay camera reads them from its files and refuses writes."""
    stats: dict
    """Frame counters: at least ``delivered``, ``complete``, ``incomplete``, ``corrupt``."""
    on_frame: Callable[[RawFrame], None] | None
    on_disconnect: Callable[[str], None] | None

    def start(self, strategy: str = "oldest_first", buffers: int = 4) -> None:
        """Begin streaming into ``buffers`` frame buffers (strategy: ``oldest_first`` or ``latest_only``)."""

    def stop(self) -> None:
        """End streaming."""

    def grab(self, timeout_s: float = 5.0) -> RawFrame:
        """The next streamed frame; ``GrabTimeoutError`` when none comes in time."""

    def try_grab(self) -> RawFrame | None:
        """The next streamed frame if one is ready, else None."""

    def capture(self, timeout_s: float = 10.0) -> RawFrame:
        """One checked frame while not streaming."""

    def close(self) -> None:
        """Let go of the device; safe to call twice."""

    def __enter__(self) -> Self: ...

    def __exit__(self, *exc) -> None: ...
