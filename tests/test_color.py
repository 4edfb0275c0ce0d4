"""The sRGB transfer function (bmi_sdk.color) against IEC 61966-2-1, and the places that encode or decode with it."""

import cv2
import numpy as np
import pytest

from bmi_sdk.color import linear_to_srgb, srgb_to_linear, srgb_uint_to_linear


# IEC 61966-2-1, written out independently of the SDK (float64)
def iec_encode(x):
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def iec_decode(v):
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


GRID = np.concatenate([np.linspace(0.0, 0.01, 2001), np.linspace(0.01, 1.0, 5001)])


def test_encode_and_decode_follow_the_standard():
    enc = linear_to_srgb(GRID)
    dec = srgb_to_linear(GRID)
    assert enc.dtype == np.float32 and dec.dtype == np.float32
    np.testing.assert_allclose(enc, iec_encode(GRID), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(dec, iec_decode(GRID), rtol=1e-6, atol=1e-9)
    # reference points: 18 % grey encodes to 0.4614, encoded 0.5 is 0.2140 linear; 0 and 1 are fixed
    assert linear_to_srgb(np.array([0.0, 0.18, 1.0])) == pytest.approx([0.0, 0.461356, 1.0], abs=1e-6)
    assert srgb_to_linear(np.array([0.0, 0.5, 1.0])) == pytest.approx([0.0, 0.214041, 1.0], abs=1e-6)


def test_encoding_clips_to_the_unit_interval():
    assert linear_to_srgb(np.array([-0.5, 1.5])) == pytest.approx([0.0, 1.0])


def test_round_trip():
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(GRID)), GRID, rtol=2e-6, atol=1e-8)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(GRID)), GRID, rtol=2e-6, atol=1e-7)


def test_the_two_pieces_meet_at_the_knee():
    # the standard's rounded constants make the line and the power law meet at the knee to within
    # 3e-8 encoded (2.9e-8) and 3e-9 linear (2.3e-9), far below one 16-bit code (1.5e-5)
    assert 12.92 * 0.0031308 == pytest.approx(1.055 * 0.0031308 ** (1 / 2.4) - 0.055, abs=3e-8)
    assert 0.04045 / 12.92 == pytest.approx(((0.04045 + 0.055) / 1.055) ** 2.4, abs=3e-9)
    # and the SDK's functions have no step there: a hair either side of the knee they agree to 2e-6 relative
    # (the standard's gap plus float32 rounding)
    for f, knee in ((linear_to_srgb, 0.0031308), (srgb_to_linear, 0.04045)):
        below, above = f(np.array([knee * (1 - 1e-7), knee * (1 + 1e-7)]))
        assert abs(above - below) < 2e-6 * below


def test_integer_images_decode_through_the_same_curve():
    for dtype in (np.uint8, np.uint16):
        codes = np.arange(np.iinfo(dtype).max + 1, dtype=dtype)
        lut = srgb_uint_to_linear(codes)
        assert lut.dtype == np.float32 and np.all(np.diff(lut) > 0)
        np.testing.assert_allclose(lut, iec_decode(codes / np.iinfo(dtype).max), rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        srgb_uint_to_linear(np.zeros(3, dtype=np.float32))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_simulated_cameras_image_stand_in_decodes_files_with_the_standard(tmp_path, dtype):
    from firmware_sim.sources import InFocusImageStandIn

    rgb = np.random.default_rng(0).integers(0, np.iinfo(dtype).max + 1, (6, 8, 3)).astype(dtype)
    path = tmp_path / "image.png"
    assert cv2.imwrite(str(path), rgb[..., ::-1])  # OpenCV writes BGR
    image = InFocusImageStandIn.from_file(path).image
    np.testing.assert_allclose(image, iec_decode(rgb / np.iinfo(dtype).max), rtol=1e-6, atol=1e-9)


def test_bmi_simulate_previews_are_encoded_with_the_standard(tmp_path):
    from bmi_sdk.cli.simulate import _write_preview

    linear = np.linspace(0.0, 1.0, 2 * 3 * 3).reshape(2, 3, 3).astype(np.float32)
    _write_preview(tmp_path / "preview.png", linear)
    got = cv2.imread(str(tmp_path / "preview.png"))[..., ::-1]
    np.testing.assert_array_equal(got, np.floor(iec_encode(linear) * 255 + 0.5))  # 8-bit, rounded
