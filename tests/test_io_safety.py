"""Files and metadata a user can trust (issue 14): no capture or calibration file is replaced, sidecars and
listings are checked against the frames, and camera or file errors reach the user as one line, not a traceback."""

import json

import numpy as np
import pytest

from bmi_sdk.cli import main
from devices import RawFileError, Roi, load_raw, open_camera
from firmware_sim import FirmwareDevice, FirmwareServer, FlatField

SMALL = Roi(2968, 2226, 64, 48)


def _frame(seed=0, serial=1):
    with open_camera("sim://", device=FirmwareDevice(source=FlatField(), seed=seed, serial=serial)) as cam:
        cam.settings.roi = SMALL
        return cam.capture()


def _acquire(out, capsys, count=2):
    # ?seed= builds the simulated camera anew: a new device session whose frame ids restart at 0
    code = main(["acquire", "--device", "sim://?seed=1", "--scene", "flat:0.3", "--count", str(count),
                 "--out", str(out), "--roi", "100,200,64,32"])
    return code, capsys.readouterr().err


def test_two_acquire_runs_into_one_folder_keep_every_capture(tmp_path, capsys, monkeypatch):
    import bmi_sdk.cli.device as device_cli

    assert _acquire(tmp_path, capsys)[0] == 0
    first = {p.name: p.read_bytes() for p in tmp_path.glob("*.dng")}
    assert len(first) == 2
    assert _acquire(tmp_path, capsys)[0] == 0
    assert len(list(tmp_path.glob("*.dng"))) == 4
    for name, data in first.items():
        assert (tmp_path / name).read_bytes() == data, f"{name} was replaced"
    # two runs with the same start stamp would reuse names: the second is refused, one line, nothing replaced
    monkeypatch.setattr(device_cli, "_run_stamp", lambda: "20260101T000000000Z")
    assert _acquire(tmp_path, capsys)[0] == 0
    kept = {p.name: p.read_bytes() for p in tmp_path.glob("frame_20260101T000000000Z_*.dng")}
    code, err = _acquire(tmp_path, capsys, count=1)
    assert code == 1 and "refusing to replace" in err and "Traceback" not in err
    assert {p.name: p.read_bytes() for p in tmp_path.glob("frame_20260101T000000000Z_*.dng")} == kept


def test_dng_sidecar_never_replaces_a_json_that_is_not_its_sidecar(tmp_path):
    frame = _frame()
    calib = tmp_path / "X.json"
    calib.write_text('{"schema": "bmi-calibration/1", "precious": true}\n')
    with pytest.raises(FileExistsError, match="not the sidecar"):
        frame.save_dng(tmp_path / "X.dng")
    assert json.loads(calib.read_text())["precious"] is True
    assert not (tmp_path / "X.dng").exists()
    # its own sidecar is replaced when the DNG is written again with overwrite=True; by default nothing is
    frame.save_dng(tmp_path / "Y.dng")
    frame.save_dng(tmp_path / "Y.dng", overwrite=True)
    assert load_raw(tmp_path / "Y.dng").frame_id == frame.frame_id
    with pytest.raises(FileExistsError, match=r"refusing to replace it \(overwrite=True replaces it\)"):
        frame.save_dng(tmp_path / "Y.dng")


@pytest.mark.parametrize("roi, match", [
    ({"x_px": 5990, "y_px": 2226, "width_px": 64, "height_px": 48}, "outside the 6000×4500 sensor"),
    ({"x_px": -2, "y_px": 2226, "width_px": 64, "height_px": 48}, "x_px must be ≥ 0 px, got -2"),
    ({"x_px": 100, "y_px": 100, "width_px": 32, "height_px": 48}, "does not match"),
    ([1, 2, 3, 4], "expected an object"),
])
def test_sidecar_roi_off_the_sensor_or_off_the_pixels_is_refused(tmp_path, roi, match):
    _frame().save_dng(tmp_path / "f.dng")
    side = tmp_path / "f.json"
    meta = json.loads(side.read_text())
    meta["roi"] = roi
    side.write_text(json.dumps(meta))
    with pytest.raises(RawFileError, match=match):
        load_raw(tmp_path / "f.dng")


def test_a_sidecar_of_the_wrong_json_shape_is_a_clear_error(tmp_path, capsys):
    _frame().save_dng(tmp_path / "f.dng")
    (tmp_path / "f.json").write_text("[1, 2]")
    with pytest.raises(RawFileError, match="holds a JSON list, expected an object"):
        load_raw(tmp_path / "f.dng")
    assert main(["infer", str(tmp_path / "f.dng"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "expected an object" in err and "Traceback" not in err


def test_camera_errors_reach_the_user_as_one_line(tmp_path, capsys):
    # replay of a missing folder: DeviceNotFoundError (a CameraError, not a ValueError)
    assert main(["acquire", "--device", f"replay://{tmp_path / 'missing'}", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("bmi acquire: error:") and "no folder" in err and len(err.strip().splitlines()) == 1
    # a camera held by another host: DeviceBusyError
    with FirmwareServer(FirmwareDevice(source=FlatField())) as server, open_camera(server.uri):
        assert main(["acquire", "--device", server.uri, "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("bmi acquire: error:") and len(err.strip().splitlines()) == 1


def test_a_bug_still_shows_its_traceback(monkeypatch):
    import bmi_sdk.cli.lens as lens_cli

    def broken(args):
        raise AttributeError("a bug, not a user error")
    monkeypatch.setattr(lens_cli, "_run", broken)
    with pytest.raises(AttributeError, match="a bug"):
        main(["lens"])


def _listing_with(folder, **device):
    listing = json.loads((folder / "captures.json").read_text())
    listing["device"].update(device)
    (folder / "captures.json").write_text(json.dumps(listing))


def test_calibration_takes_the_camera_from_the_frames(tmp_path):
    from bmi_sdk.optics.perturb import Perturbation
    from calibration.targets import CalibrationError, CapturePlan, PointSource, Target, load_captures, simulate_captures

    target = Target((PointSource(0.0, 0.0, 4.0), PointSource(30.0, 0.0, 4.0)))
    captures = simulate_captures(target, CapturePlan(kernel_px=21, roi_margin_px=10), Perturbation(), seed=2,
                                 serial=7)
    folder = captures.save(tmp_path / "caps")
    frame_serial = load_raw(next(folder.glob("*.dng"))).device["serial"]
    assert load_captures(folder).device["serial"] == frame_serial
    # a listing copied from another camera's session: refused, naming both serials
    _listing_with(folder, serial="BMI-00000099")
    with pytest.raises(CalibrationError, match=f"BMI-00000099.*{frame_serial}"):
        load_captures(folder)
    # a listing with no serial: the frames' serial is used
    listing = json.loads((folder / "captures.json").read_text())
    del listing["device"]["serial"]
    (folder / "captures.json").write_text(json.dumps(listing))
    assert load_captures(folder).device["serial"] == frame_serial
    # a listing that is a JSON array: a clear error
    (folder / "captures.json").write_text("[]")
    with pytest.raises(CalibrationError, match="expected an object"):
        load_captures(folder)


def test_calibration_file_of_the_wrong_json_shape_is_a_clear_error(tmp_path):
    from calibration.io import load_calibration
    from calibration.targets import CalibrationError

    path = tmp_path / "c.json"
    path.write_text("[]")
    with pytest.raises(CalibrationError, match="JSON list, expected an object"):
        load_calibration(path)


def test_frames_from_two_cameras_are_not_one_calibration():
    from calibration.targets import CalibrationError, device_from_frames

    a, b = _frame(serial=1), _frame(serial=2)
    with pytest.raises(CalibrationError, match="several cameras"):
        device_from_frames("captures.json", {}, [a, b])
    assert device_from_frames("captures.json", {"lens": {"name": "x"}}, [a])["serial"] == a.device["serial"]
    np.testing.assert_equal(a.device["serial"] != b.device["serial"], True)


def _point_captures(perturbation, peak_fill=0.5, seed=4):
    from calibration.targets import CapturePlan, PointSource, Target, simulate_captures

    target = Target(tuple(PointSource(t, a, 4.0, peak_fill=peak_fill) for t, a in ((0.0, 0.0), (30.0, 0.0),
                                                                                 (30.0, 90.0))))
    return simulate_captures(target, CapturePlan(kernel_px=21, roi_margin_px=10), perturbation, seed=seed)


@pytest.mark.parametrize("case, cause", [
    ("decenter_500um", "landed outside the ROIs"),
    ("swapped", "light and dark frames are swapped"),
    ("dim", "raise the exposure"),
])
def test_calibration_names_the_real_cause_when_no_spot_is_seen(case, cause):
    from bmi_sdk.optics.perturb import Perturbation
    from calibration.extract import extract_spots
    from calibration.targets import CalibrationError

    if case == "decenter_500um":
        captures = _point_captures(Perturbation(decenter_um=(500.0, 0.0)))
    elif case == "dim":
        captures = _point_captures(Perturbation(), peak_fill=0.008)  # lit, but no pixel 20 DN above dark
    else:
        captures = _point_captures(Perturbation())
        swap = {"light": "dark", "dark": "light"}
        captures.frames = [[(swap[kind], e, f) for kind, e, f in spot] for spot in captures.frames]
    with pytest.raises(CalibrationError) as info:
        extract_spots(captures)
    assert cause in str(info.value)
    others = {"landed outside the ROIs", "light and dark frames are swapped", "raise the exposure"} - {cause}
    assert not any(o in str(info.value) for o in others)
