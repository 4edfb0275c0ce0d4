"""`bmi simulate`: scene → lens → sensor → DNG, checked value by value against the forward model."""

import json

import numpy as np
import pytest
import rawpy

from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.sensor import SensorModel, bayer_mosaic, relative_illumination


def _expected_raw(rgb, depth, meta) -> np.ndarray:
    """The raw a noiseless capture of (``rgb``, ``depth``) holds, from the same optical source as the device: the
    mosaic · cos-θ falloff · ADC, clipped to the white level."""
    from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens
    from firmware_sim import RenderedScene

    roi = meta["roi"]
    h, w = depth.shape
    source = RenderedScene(rgb, np.where(depth > 0, depth, np.nan), roi["y_px"], roi["x_px"],
                           tensor=PsfTensor(get_lens(), TensorSpec()), psf_mode="tensor")
    irr = source.irradiance(roi["y_px"], roi["x_px"], h, w)
    mosaic = bayer_mosaic(irr, roi["y_px"], roi["x_px"]) * relative_illumination(BMI_SENSOR, roi["y_px"], roi["x_px"],
                                                                                    h, w)
    model = SensorModel()
    full_scale_dn = model.electrons_per_us * meta["exposure_us"] * model.conversion_gain_dn_per_e * meta["analog_gain"]
    return np.clip(np.rint(mosaic * full_scale_dn + meta["black_level_dn"]), 0, model.white_level_dn)


def test_simulate_writes_the_coded_scene_as_raw_dng(tmp_path, bmi):
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 0.6, (64, 64, 3)).astype(np.float32)
    depth = np.full((64, 64), 2.0, np.float32)
    depth[20:40, 20:40] = 0.8
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "depth.npy", depth)
    out = tmp_path / "frame.dng"
    bmi("simulate", "--rgb", tmp_path / "rgb.npy", "--depth", tmp_path / "depth.npy", "--out", out, "--field-deg", 30,
        "--azimuth-deg", 45, "--noise", 0, "--psf-mode", "tensor", "--preview")
    meta = json.loads(out.with_suffix(".json").read_text())
    roi = meta["roi"]
    row_c, col_c = BMI_SENSOR.pixel_of_field(30.0, 45.0)
    assert abs(roi["y_px"] + 32 - row_c) <= 1.5 and abs(roi["x_px"] + 32 - col_c) <= 1.5
    assert roi["x_px"] % 2 == 0 and roi["y_px"] % 2 == 0  # Bayer phase kept
    raw = rawpy.imread(str(out)).raw_image.astype(np.float64)
    assert np.abs(raw - _expected_raw(rgb, depth, meta)).max() <= 1.0
    assert (tmp_path / "frame_coded.png").exists() and (tmp_path / "frame_scene.png").exists()


def test_a_highlight_brighter_than_white_spreads_through_the_kernel_and_clips_at_the_sensor(tmp_path, bmi):
    """A float scene may hold a highlight above white (a lamp): the lens spreads it over its neighbours before the
    sensor clips, so the clipped samples cover more than the highlight, and every sample still matches the forward
    model (the clip at the white level included)."""
    rgb = np.full((64, 64, 3), 0.2, np.float32)
    rgb[30:34, 30:34] = 500.0
    depth = np.full((64, 64), 1.0, np.float32)
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "depth.npy", depth)
    out = tmp_path / "lamp.dng"
    bmi("simulate", "--rgb", tmp_path / "rgb.npy", "--depth", tmp_path / "depth.npy", "--out", out, "--field-deg", 10,
        "--noise", 0, "--psf-mode", "tensor", "--preview")
    meta = json.loads(out.with_suffix(".json").read_text())
    raw = rawpy.imread(str(out)).raw_image.astype(np.float64)
    clipped = raw >= SensorModel().white_level_dn
    assert clipped.sum() > 4 * 16  # the near kernel spreads the 16-px highlight well beyond itself
    assert not clipped[:16].any() and not clipped[-16:].any()  # and not over the whole window
    assert np.abs(raw - _expected_raw(rgb, depth, meta)).max() <= 1.0


def test_simulate_refuses_a_scene_that_does_not_fit(tmp_path, bmi):
    np.save(tmp_path / "rgb.npy", np.zeros((400, 400, 3), np.float32))
    np.save(tmp_path / "depth.npy", np.ones((400, 400), np.float32))
    bad = bmi("simulate", "--rgb", tmp_path / "rgb.npy", "--depth", tmp_path / "depth.npy", "--out", tmp_path / "x.dng",
              "--field-deg", 59, check=False)
    assert bad.returncode != 0 and "does not fit" in bad.stderr
    assert not (tmp_path / "x.dng").exists()


@pytest.mark.parametrize("sigma", [0.005, 0.05])
def test_additive_gaussian_noise_has_the_papers_sigma(sigma):
    model = SensorModel(additive_sigma=sigma)
    rng = np.random.default_rng(1)
    dn = model.expose_mosaic(np.full((256, 256), 0.5, np.float32), 10_000, 1.0, 256, rng).astype(np.float64)
    full_scale = model.electrons_per_us * 10_000 * model.conversion_gain_dn_per_e
    signal = (dn - 256) / full_scale
    assert signal.mean() == pytest.approx(0.5, abs=3 * sigma / 256 + 1e-3)
    assert signal.std() == pytest.approx(np.sqrt(sigma**2 + 1 / (12 * full_scale**2)), rel=0.03)  # + quantisation
