"""Host camera API against the simulated firmware: settings, capture, streaming, DNG, replay, broken streams."""

import socket
import threading
import time

import numpy as np
import pytest
import rawpy

from bmi_sdk.protocol.wire import HEADER, FrameHeader, Msg, envelope, json_body, packed_size
from devices import (
    ConfigurationError,
    DeviceBusyError,
    DeviceNotFoundError,
    DeviceRemovedError,
    FrameStatus,
    GrabTimeoutError,
    IncompleteFrameError,
    RawFileError,
    Roi,
    list_devices,
    load_raw,
    open_camera,
)
from firmware_sim import FirmwareDevice, FirmwareServer, FlatField

SMALL = Roi(2968, 2226, 64, 48)


def small_camera(uri="sim://", **kw):
    cam = open_camera(uri, **kw)
    cam.settings.roi = SMALL
    return cam


def test_capture_small_roi_with_metadata():
    dev = FirmwareDevice(source=FlatField(), seed=2)
    with small_camera(device=dev) as cam:
        cam.settings.exposure_us = 5000
        cam.settings.analog_gain = 2.5
        frame = cam.capture()
        assert frame.data.shape == (48, 64) and frame.data.dtype == np.uint16
        assert frame.status == FrameStatus.COMPLETE and frame.cfa == "RGGB"
        assert frame.roi == SMALL and frame.exposure_us == 5000 and frame.analog_gain == 2.5
        assert frame.black_level_dn == 256 and frame.white_level_dn == 4095
        assert frame.lens["name"] == "bmi_monocentric" and len(frame.lens["sha256"]) == 64
        assert frame.geometry.radius_mm == pytest.approx(7.199)
        assert frame.readout_timestamp_ns >= frame.device_timestamp_ns
        assert 24 < frame.temperature_c < 41
        assert cam.read_register("FRAME_COUNTER") == 1
    cam.close()  # safe twice


def test_settings_are_checked_before_sending():
    with open_camera("sim://") as cam:
        ranges = cam.settings.ranges()
        assert ranges["exposure_us"]["minimum"] == 10 and ranges["exposure_us"]["maximum"] == 1_000_000
        assert ranges["analog_gain"]["maximum"] == 16.0
        before = cam.read_register("LAST_ERROR")
        for name, bad in (("exposure_us", 5), ("exposure_us", 12.5), ("analog_gain", 0.5), ("analog_gain", 1.0005),
                          ("black_level_dn", "256"), ("roi", Roi(1, 0, 64, 48)), ("roi", Roi(5990, 0, 64, 48)),
                          ("gamma", 2)):
            with pytest.raises(ConfigurationError):
                setattr(cam.settings, name, bad)
        assert before == 0 and not cam.read_register("STATUS") & 2  # nothing reached the device


def test_second_open_is_busy_and_unknown_uris_are_not_found():
    with open_camera("sim://busytest"):
        with pytest.raises(DeviceBusyError):
            open_camera("sim://busytest")
    with open_camera("sim://busytest"):
        pass  # free again after close
    with pytest.raises(DeviceNotFoundError):
        open_camera("gige://cam0")
    with pytest.raises(DeviceNotFoundError):
        open_camera(f"tcp://127.0.0.1:{_free_port()}", timeout_s=1)
    assert any(d.uri == "sim://" for d in list_devices())


def _free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_streaming_strategies_recycle_buffers():
    with small_camera() as cam:
        cam.start("oldest_first", buffers=3)
        ids = []
        for _ in range(6):
            with cam.grab(timeout_s=5) as f:
                ids.append(f.frame_id)
        assert ids == sorted(ids)
        time.sleep(0.2)  # let the device fill every buffer and overrun
        cam.stop()
        assert cam.buffers_free == 3
        assert cam.stats["discarded"] > 0  # frames that found no buffer were counted, not lost silently
        cam.start("latest_only", buffers=2)
        time.sleep(0.2)
        f = cam.grab(timeout_s=5)
        assert f.skipped_frames > 0 and cam.stats["replaced"] > 0
        held = cam.try_grab()
        f.release()
        f.release()
        if held is not None:
            held.release()
        cam.stop()
        assert cam.buffers_free == 2
        with pytest.raises(ConfigurationError):
            cam.grab(0.1)
        assert cam.try_grab() is None


def test_on_frame_callback_and_grab_timeout():
    got = []
    done = threading.Event()

    def on_frame(frame):
        got.append((frame.frame_id, frame.data.copy()))
        if len(got) >= 3:
            done.set()

    with small_camera(on_frame=on_frame) as cam:
        cam.settings.test_pattern = 1
        cam.start(buffers=2)
        assert done.wait(5)
        cam.stop()
        rows = np.arange(SMALL.y_px, SMALL.y_px + SMALL.height_px)[:, None]
        cols = np.arange(SMALL.x_px, SMALL.x_px + SMALL.width_px)[None, :]
        np.testing.assert_array_equal(got[0][1], (rows + cols) % 4096)  # bit-exact through RAW12 + CRC
        cam.settings.test_pattern = 0
    with small_camera(device=FirmwareDevice(faults=_plan(drop=1.0))) as cam:
        cam.start(buffers=2)
        with pytest.raises(GrabTimeoutError):
            cam.grab(timeout_s=0.3)
        cam.stop()


def _plan(**kw):
    from firmware_sim import FaultPlan

    return FaultPlan(**kw)


def test_dng_round_trip_through_rawpy(tmp_path):
    with small_camera(device=FirmwareDevice(source=FlatField((0.4, 0.6, 0.2)))) as cam:
        cam.settings.black_level_dn = 100
        frame = cam.capture()
    path = tmp_path / "f.dng"
    frame.save_dng(path)
    with rawpy.imread(str(path)) as raw:
        np.testing.assert_array_equal(raw.raw_image_visible, frame.data)
        assert list(raw.black_level_per_channel) == [100] * 4 and raw.white_level == 4095
        desc = raw.color_desc.decode()
        assert "".join(desc[i] for i in raw.raw_pattern.reshape(-1)) == "RGGB"
    back = load_raw(path)
    np.testing.assert_array_equal(back.data, frame.data)
    assert back.roi == frame.roi and back.geometry == frame.geometry and back.lens == frame.lens
    assert frame.noise_profile is not None and back.noise_profile == frame.noise_profile  # the DNG's tag 51041
    assert back.is_bmi and back.black_level_dn == 100
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind
    # without its sidecar, or with another frame's sidecar, it is refused or flagged
    (tmp_path / "f.json").rename(tmp_path / "g.json")
    with pytest.raises(RawFileError, match="sidecar"):
        load_raw(path)
    flagged = load_raw(path, require_bmi=False)
    assert not flagged.is_bmi and "sidecar" in flagged.source["foreign_raw_reason"]


def test_foreign_dng_is_detected(tmp_path):
    import tifffile

    data = np.random.default_rng(0).integers(0, 1023, (32, 48), dtype=np.uint16)
    path = tmp_path / "other.dng"
    tifffile.imwrite(path, data, photometric=32803, extratags=[
        (50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "Other Cam X1", True),
        (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
        (50714, "H", 1, (64,), True), (50717, "H", 1, (1023,), True)])
    with pytest.raises(RawFileError, match="another camera"):
        load_raw(path)
    flagged = load_raw(path, require_bmi=False)
    assert not flagged.is_bmi and flagged.white_level_dn == 1023
    np.testing.assert_array_equal(flagged.data, data)


def test_replay_folder_behaves_like_a_camera(tmp_path):
    with small_camera(device=FirmwareDevice(seed=5)) as cam:
        frames = [cam.capture() for _ in range(3)]
    for f in frames:
        f.save_dng(tmp_path / f"frame_{f.frame_id:08d}.dng")
    with open_camera(f"replay://{tmp_path}") as cam:
        cam.start()
        for f in frames:
            got = cam.grab()
            assert got.frame_id == f.frame_id and got.noise_profile == f.noise_profile
            np.testing.assert_array_equal(got.data, f.data)
        with pytest.raises(GrabTimeoutError):
            cam.grab()
        with pytest.raises(ConfigurationError):
            cam.settings.exposure_us = 100
    with pytest.raises(DeviceNotFoundError):
        open_camera(f"replay://{tmp_path / 'missing'}")


def test_tcp_capture_and_reconnect_after_disconnect():
    dev = FirmwareDevice(source=FlatField(), faults=_plan(seed=1, disconnect=1.0))
    with FirmwareServer(dev) as server:
        assert server.uri.startswith("tcp://127.0.0.1:")
        lost = threading.Event()
        with small_camera(server.uri, on_disconnect=lambda reason: lost.set()) as cam:
            with pytest.raises(IncompleteFrameError):  # half the frame came, then the link dropped
                cam.capture(timeout_s=5)
            assert lost.wait(5) and cam.stats["incomplete"] == 1 and cam.stats["disconnects"] == 1
            with pytest.raises(DeviceRemovedError):
                cam.settings.exposure_us = 100
            dev.set_faults(None)  # the same device keeps serving: heal it and reconnect
            cam.reconnect()
            assert cam.settings.roi == SMALL
            frame = cam.capture(timeout_s=5)
            assert frame.complete and frame.frame_id == 1


def _fake_device(script):
    """A loopback server that answers HELLO, register reads and START like a device (a 64×48
    window), then sends ``script`` bytes and closes."""
    from bmi_sdk.protocol.registers import BY_ADDRESS
    from bmi_sdk.protocol.wire import ACK, REG_REPLY, U32, parse_envelope

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    listener.settimeout(5)
    info = FirmwareDevice().describe()
    regs = {r.name: r.default for r in BY_ADDRESS.values()} | {"ROI_WIDTH_PX": 64, "ROI_HEIGHT_PX": 48}

    def run():
        conn, _ = listener.accept()
        conn.settimeout(5)
        while True:
            msg, length = parse_envelope(conn.recv(12, socket.MSG_WAITALL))
            body = conn.recv(length, socket.MSG_WAITALL) if length else b""
            if msg == Msg.HELLO:
                reply = json_body(info)
            elif msg == Msg.READ_REG:
                (address,) = U32.unpack(body)
                reply = REG_REPLY.pack(address, 0, regs[BY_ADDRESS[address].name])
                msg = Msg.REG_REPLY
            else:
                reply, msg = ACK.pack(Msg.START, 0), Msg.ACK
            conn.sendall(envelope(msg, reply) + reply)
            if msg == Msg.ACK:
                break
        conn.sendall(script)
        time.sleep(0.2)
        conn.close()
        listener.close()

    threading.Thread(target=run, daemon=True).start()
    return f"tcp://127.0.0.1:{listener.getsockname()[1]}"


def _header_bytes(**kw):
    base = dict(frame_id=0, device_ts_ns=0, readout_ts_ns=0, exposure_us=100, gain_milli=1000, black_level_dn=0,
                white_level_dn=4095, roi_x_px=0, roi_y_px=0, width_px=64, height_px=48, temperature_milli_c=0,
                payload_len=packed_size(64 * 48))
    base.update(kw)
    return FrameHeader(**base).pack()


@pytest.mark.parametrize("script,match", [
    (envelope(Msg.FRAME, length=HEADER.size + 10) + b"JUNK" + bytes(HEADER.size + 6), "magic"),
    (envelope(Msg.FRAME, length=2**32 - 1) + bytes(64), "more than"),
    (envelope(Msg.FRAME, length=HEADER.size + packed_size(64 * 48) + 4) + _header_bytes(payload_len=2**60), "payload_len"),
    (envelope(Msg.FRAME, length=HEADER.size + packed_size(64 * 48) + 4) + _header_bytes() + bytes(100), "stream ended"),
])
def test_broken_streams_get_clear_errors(script, match):
    import tracemalloc

    uri = _fake_device(script)
    tracemalloc.start()
    with open_camera(uri, timeout_s=2) as cam:
        reasons = []
        cam.on_disconnect = reasons.append
        cam.start(buffers=1)
        with pytest.raises(DeviceRemovedError, match=match):
            while True:
                frame = cam.grab(timeout_s=3)
                frame.release()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50 << 20  # a huge length field allocated nothing
    assert reasons and match.split()[0] in reasons[0]

def test_frames_the_devices_sensor_model_cannot_describe_have_no_noise_profile():
    """A header at a gain of 0 (outside the model) or another white level than the model's gets None, not a
    profile for other pixels than these, nor a crash of the link thread."""
    import zlib

    from bmi_sdk.sensor import SensorModel

    payload = bytes(packed_size(64 * 48))

    def frame(**kw):
        body = _header_bytes(**kw) + payload + zlib.crc32(payload).to_bytes(4, "little")
        return envelope(Msg.FRAME, body) + body

    uri = _fake_device(frame(frame_id=0) + frame(frame_id=1, gain_milli=0) + frame(frame_id=2, white_level_dn=1023))
    with open_camera(uri, timeout_s=2) as cam:
        cam.start(buffers=3)
        got = [cam.grab(timeout_s=3) for _ in range(3)]
        assert [f.complete for f in got] == [True] * 3
        assert [f.noise_profile for f in got] == [SensorModel().noise_profile(1.0, 100, 0), None, None]
        for f in got:
            f.release()


def test_bmi_acquire_writes_dngs_rawpy_opens(tmp_path):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "acquire", "--device", "sim://", "--scene", "flat:0.3",
                          "--count", "2", "--out", str(tmp_path), "--roi", "100,200,64,32", "--exposure-us", "2000"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    files = sorted(tmp_path.glob("*.dng"))
    assert len(files) == 2
    for path in files:
        with rawpy.imread(str(path)) as raw:
            assert raw.raw_image_visible.shape == (32, 64)
        assert load_raw(path).exposure_us == 2000
