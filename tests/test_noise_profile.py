"""RawFrame.noise_profile: set from the device's sensor model on every sim:// frame, matching the frames' measured
noise, carried through DNG (NoiseProfile tag 51041) and its sidecar, and refused or dropped when unreadable."""

import json
import warnings

import numpy as np
import pytest
import rawpy
import tifffile

from bmi_sdk.sensor import NoiseProfile, SensorModel
from devices import NoiseProfileWarning, RawFileError, Roi, load_raw, open_camera
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


def _capture(tmp_path, name="f.dng", **settings):
    with _camera(FirmwareDevice(source=SOURCE, seed=5)) as cam:
        cam.settings.exposure_us = 2000
        for key, value in settings.items():
            setattr(cam.settings, key, value)
        frame = cam.capture()
    path = tmp_path / name
    frame.save_dng(path)
    return frame, path


def test_dng_round_trip_keeps_the_profile_exactly_and_rawpy_reads_the_pixels(tmp_path):
    frame, path = _capture(tmp_path, analog_gain=2.5)
    with tifffile.TiffFile(path) as tif:
        tag = tif.pages[0].tags[51041]
        assert tag.dtype == 12 and tag.count == 2  # DOUBLE, one (S, O) pair
        assert tag.value == (frame.noise_profile.scale, frame.noise_profile.offset)
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, frame.data)
    back = load_raw(path)
    assert back.noise_profile == frame.noise_profile  # bit for bit: DOUBLE in the DNG, repr in the JSON
    assert json.loads(path.with_suffix(".json").read_text())["noise_profile"] == frame.noise_profile.to_dict()


def test_a_dng_without_the_tag_loads_without_a_profile(tmp_path):
    frame, path = _capture(tmp_path, test_pattern=1)
    assert frame.noise_profile is None
    with tifffile.TiffFile(path) as tif:
        assert 51041 not in tif.pages[0].tags
    assert load_raw(path).noise_profile is None
    # a sidecar written before frames had profiles (no key) still loads
    side = path.with_suffix(".json")
    meta = json.loads(side.read_text())
    del meta["noise_profile"]
    side.write_text(json.dumps(meta))
    assert load_raw(path).noise_profile is None


def _overwrite_tag(path, value):
    with tifffile.TiffFile(path, mode="r+b") as tif:
        tif.pages[0].tags[51041].overwrite(value)


@pytest.mark.parametrize("value, match", [
    ((1e-4, 1e-6, 3.0), "holds"),                        # an odd count
    ((1e-4, 1e-6, 2e-4, 1e-6, 1e-4, 1e-6), "3 equal"),   # per-plane pairs that differ
    ((-1e-4, 1e-6), "scale must be finite and >= 0"),
    ((1e-4, float("nan")), "offset must be finite and >= 0"),
    ((0.0, 0.0), "both 0"),
])
def test_a_malformed_tag_in_a_bmi_dng_is_an_error_naming_file_and_tag(tmp_path, value, match):
    _, path = _capture(tmp_path)
    _overwrite_tag(path, value)
    with pytest.raises(RawFileError, match=match) as err:
        load_raw(path)
    assert str(path) in str(err.value) and "NoiseProfile tag (51041)" in str(err.value)


def test_a_tag_that_disagrees_with_the_sidecar_is_an_error(tmp_path):
    frame, path = _capture(tmp_path)
    _overwrite_tag(path, (2 * frame.noise_profile.scale, frame.noise_profile.offset))
    with pytest.raises(RawFileError, match="disagrees with the sidecar"):
        load_raw(path)


def test_another_cameras_tag_is_read_or_dropped_with_a_warning(tmp_path):
    data = np.random.default_rng(0).integers(0, 1023, (32, 48), dtype=np.uint16)

    def foreign(name, noise):
        path = tmp_path / name
        tifffile.imwrite(path, data, photometric=32803, extratags=[
            (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "Other Cam X1", True),
            (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
            (50714, "H", 1, (64,), True), (50717, "H", 1, (1023,), True),
            (51041, "d", len(noise), noise, True)])
        return path

    same = foreign("same.dng", (2e-4, 3e-6) * 3)  # one pair per colour plane, all equal: one profile
    assert load_raw(same, require_bmi=False).noise_profile == NoiseProfile(2e-4, 3e-6)
    per_plane = foreign("planes.dng", (2e-4, 3e-6, 1e-4, 3e-6, 3e-4, 3e-6))
    with pytest.warns(NoiseProfileWarning, match="planes.dng.*3 equal"):
        flagged = load_raw(per_plane, require_bmi=False)
    assert flagged.noise_profile is None and not flagged.is_bmi
    np.testing.assert_array_equal(flagged.data, data)


def test_replay_frames_carry_the_recorded_profile(tmp_path):
    frame, _ = _capture(tmp_path, name="frame_00000000.dng", analog_gain=3.0)
    with open_camera(f"replay://{tmp_path}") as cam:
        got = cam.capture()
    assert got.noise_profile == frame.noise_profile == SensorModel().noise_profile(3.0, 2000, 256)
