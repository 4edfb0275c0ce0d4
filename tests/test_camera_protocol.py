"""``devices.Camera``: the live and the replay camera offer the same interface (issue 15, section 5)."""

import inspect

import pytest

from devices import Camera, ReplayCamera, Roi, StreamCamera, open_camera
from devices.camera_protocol import Camera as ProtocolCamera
from firmware_sim import FirmwareDevice, FlatField

_METHODS = ("start", "stop", "grab", "try_grab", "capture", "close", "__enter__", "__exit__")


def _parameters(fn):
    return [(p.name, p.kind, p.default, p.annotation) for p in inspect.signature(fn).parameters.values()]


@pytest.mark.parametrize("cls", [StreamCamera, ReplayCamera])
def test_methods_match_the_protocol(cls):
    assert Camera is ProtocolCamera
    for name in _METHODS:
        assert _parameters(getattr(cls, name)) == _parameters(getattr(Camera, name)), f"{cls.__name__}.{name}"
        if name != "__enter__":  # returns its own class
            assert (inspect.signature(getattr(cls, name)).return_annotation
                    == inspect.signature(getattr(Camera, name)).return_annotation), f"{cls.__name__}.{name}"


def test_live_and_replay_cameras_are_cameras(tmp_path):
    with open_camera("sim://", device=FirmwareDevice(source=FlatField(), seed=1)) as live:
        assert isinstance(live, Camera)
        live.settings.roi = Roi(2968, 2226, 64, 48)
        live.capture().save_dng(tmp_path / "f0.dng")
    with open_camera(f"replay://{tmp_path}") as replay:
        assert isinstance(replay, Camera)
    assert not isinstance(object(), Camera)
