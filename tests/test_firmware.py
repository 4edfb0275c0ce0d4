"""Firmware simulator: register refusals, RAW12 framing with CRC, header validation, readout, fault seeds."""

import zlib

import numpy as np
import pytest

from bmi_sdk.protocol.registers import BY_NAME, REGISTERS, RegError, Status, TestPattern
from bmi_sdk.protocol.wire import (
    CRC,
    HEADER,
    MAX_BODY_BYTES,
    FrameHeader,
    Msg,
    WireError,
    encode_frame,
    envelope,
    pack12,
    packed_size,
    parse_envelope,
    unpack12,
)
from bmi_sdk.sensor import SensorModel
from firmware_sim import FaultPlan, FirmwareDevice, FlatField, InFocusImageStandIn, make_source
from firmware_sim.faults import Fault, FaultInjector
from firmware_sim.register_file import RegisterFile


def addr(name):
    return BY_NAME[name].address


# -- registers ------------------------------------------------------------------
def test_register_map_is_documented_and_aligned():
    addresses = [r.address for r in REGISTERS]
    assert len(set(addresses)) == len(addresses) and all(a % 4 == 0 for a in addresses)
    for r in REGISTERS:
        assert r.unit and r.doc and r.minimum <= r.default <= r.maximum


@pytest.mark.parametrize("name,bad", [("EXPOSURE_US", 9), ("EXPOSURE_US", 1_000_001), ("ANALOG_GAIN_MILLI", 999),
                                      ("ANALOG_GAIN_MILLI", 16_001), ("BLACK_LEVEL_DN", -1),
                                      ("BLACK_LEVEL_DN", 1024), ("TEST_PATTERN", 3)])
def test_out_of_range_write_is_refused_not_clamped(name, bad):
    regs = RegisterFile()
    before = regs.get(name)
    assert regs.write(addr(name), bad) == RegError.OUT_OF_RANGE
    assert regs.get(name) == before
    assert regs.get("STATUS") & Status.ERROR_LATCHED
    assert regs.read(addr("LAST_ERROR")) == (RegError.OK, RegError.OUT_OF_RANGE)
    assert regs.read(addr("LAST_ERROR")) == (RegError.OK, 0)  # reading clears the latch
    assert not regs.get("STATUS") & Status.ERROR_LATCHED


def test_range_edges_accepted_and_other_refusals():
    regs = RegisterFile(serial=0xBEEF)
    assert regs.write(addr("EXPOSURE_US"), 10) == RegError.OK
    assert regs.write(addr("EXPOSURE_US"), 1_000_000) == RegError.OK
    assert regs.write(addr("FW_VERSION"), 1) == RegError.READ_ONLY
    assert regs.write(addr("FRAME_COUNTER"), 0) == RegError.READ_ONLY
    assert regs.write(0x999, 1) == RegError.UNKNOWN_ADDRESS
    assert regs.read(0x998)[0] == RegError.UNKNOWN_ADDRESS
    assert regs.write(addr("ROI_X_PX"), 3) == RegError.MISALIGNED
    assert regs.write(addr("ROI_X_PX"), 2) == RegError.CONFLICT  # full width from x=2 leaves the sensor
    assert regs.write(addr("ROI_WIDTH_PX"), 64) == RegError.OK
    assert regs.write(addr("ROI_X_PX"), 5936) == RegError.OK
    assert regs.roi() == (5936, 0, 64, 4500)
    regs.set_status(Status.ACQUIRING, True)
    assert regs.write(addr("ROI_Y_PX"), 0) == RegError.BUSY
    assert regs.write(addr("EXPOSURE_US"), 500) == RegError.OK  # exposure may change while streaming
    assert regs.read(addr("SERIAL")) == (RegError.OK, 0xBEEF)


# -- RAW12 and frames --------------------------------------------------------------
def test_pack12_layout_and_round_trip():
    px = np.array([0xABC, 0x123], np.uint16)
    assert pack12(px) == bytes([0xBC, 0x3A, 0x12])  # p0 | p1 << 12, little-endian
    rng = np.random.default_rng(0)
    img = rng.integers(0, 4096, (300, 1000), dtype=np.uint16)  # > one internal chunk
    data = pack12(img)
    assert len(data) == packed_size(img.size)
    out = np.empty_like(img)
    unpack12(data, out)
    np.testing.assert_array_equal(out, img)


def _header(**kw):
    base = dict(frame_id=7, device_ts_ns=1, readout_ts_ns=2, exposure_us=100, gain_milli=1000, black_level_dn=256,
                white_level_dn=4095, roi_x_px=0, roi_y_px=0, width_px=4, height_px=2, temperature_milli_c=30000,
                payload_len=packed_size(8))
    base.update(kw)
    return FrameHeader(**base)


def test_frame_encoding_header_crc_and_payload_crc():
    h = _header()
    payload = pack12(np.arange(8, dtype=np.uint16))
    body = encode_frame(h, payload)
    assert FrameHeader.parse(body) == h
    assert body[HEADER.size:-CRC.size] == payload
    assert CRC.unpack(body[-CRC.size:])[0] == zlib.crc32(payload)


@pytest.mark.parametrize("damage,match", [
    (lambda b: b"XXXX" + b[4:], "magic"),
    (lambda b: b[:4] + b"\x09\x00" + b[6:], "version"),
    (lambda b: b[:20] + bytes([b[20] ^ 1]) + b[21:], "header CRC"),
    (lambda b: b[:30], "truncated"),
])
def test_malformed_header_is_refused(damage, match):
    good = _header().pack()
    with pytest.raises(WireError, match=match):
        FrameHeader.parse(damage(good))


def test_header_with_huge_or_inconsistent_length_is_refused():
    with pytest.raises(WireError, match="payload_len"):
        FrameHeader.parse(_header(payload_len=2**62).pack())
    with pytest.raises(WireError, match="does not fit"):
        FrameHeader.parse(_header(width_px=6002, payload_len=packed_size(6002 * 2)).pack())
    with pytest.raises(WireError, match="more than"):
        parse_envelope(envelope(Msg.FRAME, length=MAX_BODY_BYTES + 1))
    with pytest.raises(WireError, match="more than"):
        parse_envelope(envelope(Msg.HELLO, length=2**32 - 1))
    with pytest.raises(WireError, match="magic"):
        parse_envelope(b"HTTP/1.1 200")


# -- readout ----------------------------------------------------------------------
def _device(**kw):
    dev = FirmwareDevice(**kw)
    regs = dev.regs
    for name, v in (("ROI_WIDTH_PX", 64), ("ROI_HEIGHT_PX", 48), ("ROI_X_PX", 2968), ("ROI_Y_PX", 2226)):
        assert regs.write(addr(name), v) == RegError.OK
    return dev


def test_flat_field_frame_matches_photon_transfer_mean():
    model = SensorModel()
    dev = _device(source=FlatField((0.5, 0.5, 0.5)), seed=3, model=model)
    res = dev.read_out()
    h = res.header
    assert res.pixels.shape == (48, 64) and res.pixels.dtype == np.uint16
    assert (h.roi_x_px, h.roi_y_px, h.width_px, h.height_px) == (2968, 2226, 64, 48)
    # near the axis cos θ ≈ 1: mean DN = black + g μ
    mu_e = 0.5 * model.electrons_per_us * h.exposure_us
    expect = h.black_level_dn + model.conversion_gain_dn_per_e * mu_e
    assert abs(res.pixels.mean() - expect) < 0.01 * expect
    assert dev.regs.get("FRAME_COUNTER") == 1
    # same seed, same frame id: same noise
    again = _device(source=FlatField((0.5, 0.5, 0.5)), seed=3, model=model).read_out()
    np.testing.assert_array_equal(again.pixels, res.pixels)


def test_readout_cfa_phase_and_dark_frame():
    dev = _device(source=FlatField((0.9, 0.3, 0.05)), model=SensorModel(read_noise_e=0.0))
    px = dev.read_out().pixels.astype(float)
    r, g1, g2, b = px[0::2, 0::2].mean(), px[0::2, 1::2].mean(), px[1::2, 0::2].mean(), px[1::2, 1::2].mean()
    assert r > g1 > b and abs(g1 - g2) < 0.02 * g1
    dark = _device(source=make_source("dark"), model=SensorModel(read_noise_e=0.0)).read_out()
    assert (dark.pixels == dark.header.black_level_dn).all()


def test_test_pattern_is_bit_exact_in_sensor_coordinates():
    dev = _device()
    assert dev.regs.write(addr("TEST_PATTERN"), TestPattern.WALKING) == RegError.OK
    dev.read_out()
    res = dev.read_out()
    rows = np.arange(2226, 2226 + 48)[:, None]
    cols = np.arange(2968, 2968 + 64)[None, :]
    np.testing.assert_array_equal(res.pixels, (rows + cols + 1) % 4096)
    assert res.header.flags & 1


def test_stand_in_image_fills_sensor_and_says_what_it_is():
    img = np.zeros((3, 4, 3), np.float32)
    img[0, 0] = (1, 0, 0)
    src = InFocusImageStandIn(img)
    assert "stand-in" in src.metadata()["note"]
    window = src.irradiance(0, 0, 2, 2)
    np.testing.assert_array_equal(window[0, 0], (1, 0, 0))
    assert src.irradiance(4498, 5998, 2, 2).shape == (2, 2, 3)
    with pytest.raises(ValueError, match="unknown scene"):
        make_source("nosuch")


def test_sources_must_return_the_window_shape():
    class Broken:
        name = "broken"

        def irradiance(self, row0, col0, height, width):
            return np.zeros((height, width), np.float32)

        def metadata(self):
            return {}

    with pytest.raises(ValueError, match="broken"):
        _device(source=Broken()).read_out()


# -- ownership ----------------------------------------------------------------------
class _Session:
    def __init__(self):
        self.gone = False
        self.revoked = 0

    def host_gone(self):
        return self.gone

    def revoke(self):
        self.revoked += 1


def test_a_session_whose_host_hung_up_gives_way_and_loses_the_camera_for_good():
    from firmware_sim.device import NotHeld

    dev = _device(source=FlatField())
    first, second, third = _Session(), _Session(), _Session()
    assert dev.claim(first) and not dev.claim(second)  # a live host keeps the camera
    with dev.held_by(first):
        assert dev.write_register(addr("EXPOSURE_US"), 5000) == RegError.OK
    first.gone = True  # its host hung up; its session has not noticed yet
    assert dev.claim(second) and first.revoked == 1
    assert dev.regs.get("EXPOSURE_US") == 10_000  # reset, as when the first session ends
    with pytest.raises(NotHeld):
        with dev.held_by(first):
            pass
    assert not dev.release(first) and dev.claimed  # the first session's late teardown lets go of nothing
    assert not dev.claim(third) and second.revoked == 0
    assert dev.release(second) and not dev.claimed and dev.claim(third)
    plain = object()  # a holder with no host_gone is never taken for gone, nor is claim() without one
    assert dev.release(third) and dev.claim(plain) and not dev.claim(third) and dev.release(plain)
    assert dev.claim() and not dev.claim(third) and not dev.release(third) and dev.release()


# -- faults -------------------------------------------------------------------------
def test_fault_injection_is_seeded_and_counted():
    plan = FaultPlan(seed=11, drop=0.1, corrupt=0.1, incomplete=0.1, stall=0.05, disconnect=0.05)
    a, b = FaultInjector(plan), FaultInjector(plan)
    seq_a = [a.draw(i) for i in range(2000)]
    assert seq_a == [b.draw(i) for i in range(2000)]
    counts = a.counts()
    assert counts == {k.value: seq_a.count(k) for k in Fault if k != Fault.NONE}
    assert abs(counts["drop"] - 200) < 60 and abs(counts["disconnect"] - 100) < 45
    with pytest.raises(ValueError, match="sum"):
        FaultPlan(drop=0.7, corrupt=0.5)
    assert FaultPlan.parse("seed=3,drop=0.25") == FaultPlan(seed=3, drop=0.25)
    with pytest.raises(ValueError, match="KEY=VALUE"):
        FaultPlan.parse("explode=1")
