"""RawFrame.noise_profile: set from the device's sensor model on every sim:// frame, matching the frames' measured
noise."""

import warnings

import numpy as np
import pytest

from bmi_sdk.sensor import SensorModel
from devices import NoiseProfileWarning, Roi, open_camera
from firmware_sim import FirmwareDevice, FlatField

SMALL = Roi(2968, 2226, 64, 48)
CENTRE = Roi(2872, 2124, 256, 256)  # cos θ ≈ 1 over the window
SOURCE = FlatField((0.2, 0.3, 0.1))  # at ≤ 2 ms and gain ≤ 4, nothing saturates


def _camera(device, roi=SMALL):
    cam = open_camera("sim://", device=device)
    cam.settings.roi = roi
    return cam


def test_sim_frames_carry_the_device_models_profile_at_their_gain_exposure_and_black_level():
    dev = FirmwareDevice(source=SOURCE, seed=3)
    with _camera(dev) as cam:
        cam.settings.exposure_us = 2000
        first = cam.capture()
        assert first.noise_profile == dev.model.noise_profile(1.0, 2000, 256)
        cam.settings.analog_gain = 4.0
        cam.settings.black_level_dn = 100
        second = cam.capture()
        assert second.noise_profile == dev.model.noise_profile(4.0, 2000, 100)
        # in DN, the shot noise's scale is the gain: 4× the first frame's
        assert second.noise_profile.scale * (4095 - 100) == pytest.approx(4 * first.noise_profile.scale * (4095 - 256))
        assert second.metadata["noise_profile"] == second.noise_profile.to_dict()
        cam.settings.test_pattern = 1
        assert cam.capture().noise_profile is None  # digital: no sensor noise to describe
    # the photon model's profile does not depend on the exposure; the additive model's does
    additive = FirmwareDevice(source=SOURCE, model=SensorModel(additive_sigma=0.01))
    with _camera(additive) as cam:
        for exposure_us in (1000, 2000):
            cam.settings.exposure_us = exposure_us
            assert cam.capture().noise_profile == additive.model.noise_profile(1.0, exposure_us, 256)


@pytest.mark.parametrize("gain", [1.0, 4.0])
def test_the_profile_is_the_measured_noise_of_two_sim_captures(gain):
    """Independent of the formula: for two captures of one static scene, E[(a − b)²] / 2 per pixel is Var[x]
    at that pixel's signal, and Var[x] is linear in x, so over the window it is scale · mean(x) + offset."""
    dev = FirmwareDevice(source=SOURCE, seed=4)
    with _camera(dev, CENTRE) as cam:
        cam.settings.exposure_us = 2000
        cam.settings.analog_gain = gain
        a, b = cam.capture(), cam.capture()
    span = a.white_level_dn - a.black_level_dn
    xa, xb = ((f.data.astype(np.float64) - f.black_level_dn) / span for f in (a, b))
    measured = np.mean((xa - xb) ** 2) / 2
    expected = float(a.noise_profile.variance(np.mean((xa + xb) / 2)))
    n = xa.size
    assert a.noise_profile == b.noise_profile
    assert abs(measured / expected - 1) < 4 * np.sqrt(2 / n)  # ≈ 0.022


def test_a_device_that_does_not_describe_its_sensor_gives_frames_without_a_profile():
    dev = FirmwareDevice(source=SOURCE)
    full = dev.describe()
    dev.describe = lambda: {k: v for k, v in full.items() if k != "sensor_model"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with _camera(dev) as cam:
            assert cam.capture().noise_profile is None
    # one this host cannot read (a newer firmware's field) opens the camera with a warning, not an error
    dev.describe = lambda: full | {"sensor_model": full["sensor_model"] | {"dark_current_e_per_s": 0.1}}
    with pytest.warns(NoiseProfileWarning, match="sensor_model is unreadable"):
        cam = _camera(dev)
    with cam:
        assert cam.capture().noise_profile is None
