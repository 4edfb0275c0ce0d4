"""The ``sim://`` backend: simulated cameras in this process, served over an in-process socket pair.

This is the one place the host API reaches the simulator, and it imports
``firmware_sim`` inside ``open_sim`` only: ``import devices`` loads neither the
simulator nor the renderer and optics behind its scenes, which a host talking
to a real camera never needs.

A named device lives as long as the process, like a plugged-in camera: its
scene, frame counter and fault ledger persist between opens. Giving ``seed``,
``faults`` or ``serial`` builds it anew; ``scene`` loads a scene into it.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from .camera import StreamCamera
from .errors import ConfigurationError, DeviceBusyError

if TYPE_CHECKING:  # for the type checker only: at run time ``open_sim`` alone imports the simulator
    from firmware_sim import FirmwareDevice

DEFAULT_NAME = "sim0"  # the device ``sim://`` names
_DEVICES: dict[str, FirmwareDevice] = {}
_LOCK = threading.Lock()


def open_sim(uri: str, name: str, query: dict, device=None, **camera_kwargs) -> StreamCamera:
    """A ``StreamCamera`` on ``device``, or else on the process's simulated camera ``name`` configured by
    ``query`` (``scene``, ``seed``, ``faults``, ``serial``); ``camera_kwargs`` go to ``StreamCamera``."""
    from firmware_sim import FaultPlan, FirmwareDevice, InProcessLink, make_source

    if device is None:
        unknown = set(query) - {"scene", "seed", "faults", "serial"}
        if unknown:
            raise ConfigurationError(f"sim:// takes scene, seed, faults, serial; not {', '.join(sorted(unknown))}")
        try:
            with _LOCK:
                device = _DEVICES.get(name)
                if device is None or {"seed", "faults", "serial"} & set(query):
                    if device is not None and not device.claim():
                        raise DeviceBusyError(f"sim://{name} is open elsewhere; close it before rebuilding it")
                    if device is not None:
                        device.release()
                    device = FirmwareDevice(seed=int(query.get("seed", 0)), serial=int(query.get("serial", 1)),
                                            faults=FaultPlan.parse(query["faults"]) if "faults" in query else None)
                    _DEVICES[name] = device
                if "scene" in query:
                    device.load_source(make_source(query["scene"]))
        except ValueError as exc:
            raise ConfigurationError(f"sim://{name}: {exc}") from exc

    def connect():
        link = InProcessLink(device)
        return link.sock, link.close
    return StreamCamera(uri, connect, **camera_kwargs)


def sim_devices() -> dict[str, FirmwareDevice]:
    """The simulated cameras this process has built so far, by name (a snapshot)."""
    with _LOCK:
        return dict(_DEVICES)

