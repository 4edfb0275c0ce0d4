"""Hostile values on the command lines of simulate, acquire, calibrate, firmware-sim, psf, lens and crlb (issue 37).

Every refusal is one line naming the option, before any rendering, capture or fitting: exit 2 for a bad option
value (argparse's usage errors and ``OptionError``), the frames and files a user has kept never replaced.
"""

from __future__ import annotations

import numpy as np
import pytest

from bmi_sdk.cli import main


def _refusal(capsys, argv: list[str]) -> str:
    """Run ``bmi ARGV``; it must exit 2 with one line on stderr, which is returned."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, (code, err)
    return err[-1]


# -- memory -----------------------------------------------------------------------------------------------------

def test_simulate_size_past_the_memory_limit_is_refused_naming_option_estimate_and_limit(capsys, tmp_path):
    line = _refusal(capsys, ["simulate", "--procedural", "0", "--size", "100000", "--out", str(tmp_path / "s.dng")])
    assert "--size 100000 needs about 1303.9 GiB" in line and "GiB limit" in line
    assert not list(tmp_path.iterdir())


def test_check_allocation_names_option_value_estimate_and_limit(monkeypatch):
    from bmi_sdk.memory_budget import MemoryBudgetError, check_allocation

    monkeypatch.setenv("BMI_MAX_MEMORY_MB", "100")
    check_allocation("--window-px", 64, 50 * 2**20)
    with pytest.raises(MemoryBudgetError) as err:
        check_allocation("--window-px", 100000, 200 * 2**30)
    assert err.value.option == "--window-px"
    assert str(err.value).startswith("--window-px 100000 needs about 200.0 GiB, more than the 0.1 GiB limit "
                                     "(BMI_MAX_MEMORY_MB=100")
    with pytest.raises(MemoryBudgetError):
        check_allocation("--window-px", "nan", float("nan"))


# -- simulate: values that rendered a wrong frame, or failed late -------------------------------------------------

@pytest.mark.parametrize("option, value, expected", [
    ("--field-deg", "-20", "argument --field-deg: -20 is outside [0, 60]"),
    ("--field-deg", "nan", "argument --field-deg: nan is not a finite number"),
    ("--field-deg", "inf", "argument --field-deg: inf is not a finite number"),
    ("--azimuth-deg", "1e9", "argument --azimuth-deg: 1e9 is outside"),
    ("--noise", "1e6", "argument --noise: 1e6 is outside [0, 1]"),
    ("--noise", "-0.1", "argument --noise: -0.1 is outside [0, 1]"),
    ("--procedural", "-1", "argument --procedural: -1 is outside [0, 4294967295]"),
    ("--seed", "-1", "argument --seed: -1 is outside [0, 4294967295]"),
    ("--size", "0", "argument --size: 0 is outside [2, inf) px"),
    ("--size", "5000", "--size"),
])
def test_simulate_refuses_out_of_range_options_naming_them(capsys, tmp_path, option, value, expected):
    argv = ["simulate", "--out", str(tmp_path / "s.dng"), option, value]
    if option != "--procedural":
        argv += ["--procedural", "0"]
    assert expected in _refusal(capsys, argv)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("term, expected", [
    ("decenter_um=1e9,0", "|decenter_um| is at most 1000 um"),
    ("tilt_arcmin=0,1e6", "|tilt_arcmin| is at most 60 arcmin"),
    ("decenter_um=nan,0", "decenter_um needs 2 finite number(s)"),
    ("stray_light_fraction=2", "stray_light_fraction must lie in"),
    ("nonsense=1", "expected NAME=VALUE"),
])
def test_simulate_perturbation_names_the_option_and_its_range(capsys, tmp_path, term, expected):
    line = _refusal(capsys, ["simulate", "--procedural", "0", "--size", "64", "--perturb", term,
                             "--out", str(tmp_path / "s.dng")])
    assert f"--perturb {term}" in line and expected in line and "surface" not in line


def test_a_perturbation_that_sends_rays_past_the_sensor_names_the_option_not_a_surface(monkeypatch):
    from bmi_sdk.cli import _options

    assert _options.perturbation_option("--perturb", ["decenter_um=10,0"]).decenter_um == (10.0, 0.0)
    # every value within the limits forms an image; the trace behind them is the last word on what does
    assert _options.perturbation_option("--simulate", ["decenter_um=1000,0", "tilt_arcmin=0,60",
                                                       "sensor_radius_error_pct=-49"]).tilt_arcmin == (0.0, 60.0)
    monkeypatch.setitem(_options.PERTURBATION_LIMITS, "decenter_um", 1e10)
    with pytest.raises(_options.OptionError, match=r"^--simulate decenter_um=1e9,0: with these errors no image "
                                                   r"forms \(the chief ray .*\); use smaller values$"):
        _options.perturbation_option("--simulate", ["decenter_um=1e9,0"])


@pytest.mark.parametrize("depth, expected", [
    (np.full((64, 64), np.nan, np.float32), "no pixel holds a finite range > 0 m"),
    (np.full((64, 64), -2.0, np.float32), "no pixel holds a finite range > 0 m"),
    (np.full((64, 64), np.inf, np.float32), "no pixel holds a finite range > 0 m"),
    (np.full((64, 64), 1e-6, np.float32), "nearer than 0.7 m"),
    (np.ones((32, 64), np.float32), "does not match the image"),
])
def test_simulate_refuses_a_depth_map_that_would_render_a_wrong_frame(capsys, tmp_path, depth, expected):
    np.save(tmp_path / "rgb.npy", np.full((64, 64, 3), 0.5, np.float32))
    np.save(tmp_path / "d.npy", depth)
    line = _refusal(capsys, ["simulate", "--rgb", str(tmp_path / "rgb.npy"), "--depth", str(tmp_path / "d.npy"),
                             "--out", str(tmp_path / "s.dng")])
    assert line.startswith(f"bmi simulate: error: --depth {tmp_path / 'd.npy'}: ") and expected in line


@pytest.mark.parametrize("level", [np.nan, -0.5, np.inf, 1e7, 3e38])
def test_simulate_refuses_a_float_scene_outside_its_levels(capsys, tmp_path, level):
    rgb = np.full((64, 64, 3), 0.5, np.float32)
    rgb[10, 10, 1] = level
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "d.npy", np.full((64, 64), 2.0, np.float32))
    line = _refusal(capsys, ["simulate", "--rgb", str(tmp_path / "rgb.npy"), "--depth", str(tmp_path / "d.npy"),
                             "--out", str(tmp_path / "s.dng")])
    assert line.startswith(f"bmi simulate: error: --rgb {tmp_path / 'rgb.npy'}: linear RGB must be finite and "
                           "within [0, 1e+06]")
    assert not (tmp_path / "s.dng").exists()


def test_simulate_depth_that_is_not_a_npy_array_is_named(capsys, tmp_path):
    np.save(tmp_path / "rgb.npy", np.full((64, 64, 3), 0.5, np.float32))
    (tmp_path / "x.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    line = _refusal(capsys, ["simulate", "--rgb", str(tmp_path / "rgb.npy"), "--depth", str(tmp_path / "x.png"),
                             "--out", str(tmp_path / "s.dng")])
    assert "--depth" in line and "not a NumPy .npy array" in line and "allow_pickle" not in line


def test_a_depth_map_with_some_unknown_pixels_is_loaded_with_a_warning(caplog):
    from bmi_sdk.cli.simulate import _load_depth

    depth = np.full((4, 4), 2.0, np.float32)
    depth[0] = np.nan
    depth[1, 0] = -1
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        np.save(Path(folder) / "d.npy", depth)
        loaded = _load_depth(str(Path(folder) / "d.npy"), (4, 4), nearest_m=0.7)
    assert np.isnan(loaded[1, 0]) and np.count_nonzero(np.isnan(loaded)) == 5
    assert "31.2% of the pixels have no finite range" in caplog.text


@pytest.mark.parametrize("out, expected", [
    ("X", "--out {tmp}/X: name it *.dng"),
    ("afile/s.dng", "--out {tmp}/afile/s.dng: cannot create the folder"),
])
def test_simulate_checks_its_output_before_rendering(capsys, tmp_path, out, expected):
    (tmp_path / "afile").write_text("a file, not a folder")
    line = _refusal(capsys, ["simulate", "--procedural", "0", "--size", "64", "--out", str(tmp_path / out)])
    assert expected.format(tmp=tmp_path) in line and ".dng." not in line  # no hidden temp name


# -- the fisheye's frames name the lens its model and decoders take ------------------------------------------------

def test_a_fisheye_camera_names_the_lens_profile_its_shipped_model_was_trained_for():
    import json
    from importlib.resources import files

    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from devices import Roi, open_camera
    from firmware_sim import FirmwareDevice, FlatField, RenderedScene

    manifest = json.loads(files("bmi_sdk.models").joinpath("fisheye.manifest.json").read_text())
    device = FirmwareDevice(source=FlatField(), geometry=lens_geometry("fisheye"), lens="fisheye")
    with open_camera("sim://", device=device) as cam:
        cam.settings.roi = Roi(2968, 2226, 64, 48)
        frame = cam.capture()
    assert frame.lens["name"] == manifest["lens"] == "fisheye"
    scene = RenderedScene(np.zeros((4, 4, 3)), np.ones((4, 4)), tensor=lens_tensor("fisheye"))
    assert scene.metadata()["lens"] == "fisheye"


def test_the_classical_decoder_widens_a_window_too_narrow_for_the_fisheye_kernel_and_says_so():
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.runtime.classical import WindowFitWarning, classical_decoder, window_holding

    assert window_holding(161, 64) == 164 and window_holding(41, 64) == 64 and window_holding(41, 40) == 44
    with pytest.warns(WindowFitWarning, match="--window-px 64 holds no 161-px kernel of the fisheye lens; "
                                              "reading with 164-px windows"):
        decoder = classical_decoder(BuiltCamera(lens_name="fisheye"), ClassicalConfig())
    assert decoder.config.window_px == 164 and decoder.zones.window_px == 164


def test_a_decoder_without_a_model_for_the_lens_names_only_the_decoders_that_read_it():
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.model_manifest import ModelError
    from bmi_sdk.runtime import open_decoder

    with pytest.raises(ModelError, match="no evidence model .* for lens 'fisheye'; decode this frame with "
                                         "--decoder cnn, --decoder classical$"):
        open_decoder(BuiltCamera(lens_name="fisheye"), "evidence")


@pytest.mark.slow  # a fisheye render on a cold PSF cache: minutes on 2 cores
def test_a_simulated_fisheye_frame_decodes_end_to_end_through_the_cli(tmp_path):
    import json

    dng = tmp_path / "fish.dng"
    assert main(["simulate", "--lens", "fisheye", "--procedural", "1", "--size", "64", "--field-deg", "20",
                 "--psf-mode", "tensor", "--out", str(dng)]) == 0
    assert main(["infer", str(dng), "--decoder", "cnn", "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["model"]["lens"] == "fisheye" and np.isfinite(np.load(tmp_path / "out" / "depth.npy")).any()
    assert main(["infer", str(dng), "--decoder", "classical", "--out", str(tmp_path / "classical")]) == 0
    assert np.isfinite(np.load(tmp_path / "classical" / "depth.npy")).any()


# -- the Python API ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("values, expected", [
    ((-2, 0, 64, 48), "Roi x_px must be ≥ 0 px, got -2"),
    (("a", 0, 64, 48), "Roi x_px must be a whole number of pixels, got 'a'"),
    ((0, 0, 0, 48), "Roi width_px must be ≥ 1 px, got 0"),
    ((0, 0, 64, 2.5), "Roi height_px must be a whole number of pixels, got 2.5"),
    ((0, True, 64, 48), "Roi y_px must be a whole number of pixels, got True"),
])
def test_roi_is_validated_when_made_not_at_capture(values, expected):
    from devices import ConfigurationError, Roi

    with pytest.raises(ConfigurationError, match=f"^{expected}$"):
        Roi(*values)
    assert Roi(np.int64(2), 4, 6, 8) == Roi(2, 4, 6, 8)


def test_save_dng_refuses_an_existing_frame_unless_asked(tmp_path):
    from devices import open_camera

    with open_camera("sim://?scene=flat") as cam:
        cam.settings.roi = (2968, 2226, 16, 16)
        first, second = cam.capture(), cam.capture()
    first.save_dng(tmp_path / "f.dng")
    kept = (tmp_path / "f.dng").read_bytes()
    with pytest.raises(FileExistsError, match="f.dng exists; refusing to replace it"):
        second.save_dng(tmp_path / "f.dng")
    assert (tmp_path / "f.dng").read_bytes() == kept
    second.save_dng(tmp_path / "f.dng", overwrite=True)


# -- acquire: disk, replay folders, the default scene ---------------------------------------------------------------

def _replay_folder(folder, count: int):
    from devices import open_camera

    folder.mkdir()
    with open_camera("sim://?scene=flat") as cam:
        cam.settings.roi = (2968, 2226, 64, 48)  # LibRaw reads no raw file much smaller
        for i in range(count):
            cam.capture().save_dng(folder / f"f{i}.dng")
    return folder


@pytest.mark.parametrize("option, value, expected", [
    ("--count", "1000000000", "argument --count: 1000000000 is outside [1, 100000]"),
    ("--count", "0", "argument --count: 0 is outside [1, 100000]"),
    ("--gain", "nan", "--gain nan: analog_gain=nan is outside its range [1.0, 16.0]"),
    ("--exposure-us", "-5", "--exposure-us -5: exposure_us=-5 is outside its range"),
    ("--roi", "1,2", "--roi takes X,Y,WIDTH,HEIGHT"),
    ("--roi", "0,0,7000,48", "--roi 0,0,7000,48: roi Roi(x_px=0, y_px=0, width_px=7000, height_px=48) does not fit"),
    ("--timeout-s", "-1", "argument --timeout-s: -1 is outside (0, 86400] s"),
    ("--device", "bogus://", "--device bogus://: a camera URI is sim://, tcp://HOST:PORT or replay://DIR"),
    ("--device", "tcp://127.0.0.1:99999", "--device tcp://127.0.0.1:99999: "),
    ("--scene", "nosuch", "--scene nosuch: sim://sim0: unknown scene 'nosuch'"),
])
def test_acquire_refuses_out_of_range_options_naming_them(capsys, tmp_path, option, value, expected):
    assert expected in _refusal(capsys, ["acquire", "--out", str(tmp_path / "o"), f"{option}={value}"])
    assert not list((tmp_path / "o").glob("*.dng"))


def test_acquire_checks_the_free_disk_space_before_the_first_frame(capsys, tmp_path):
    line = _refusal(capsys, ["acquire", "--out", str(tmp_path / "o"), "--count", "100000", "--roi", "0,0,6000,4500"])
    assert "--count 100000: 100000 frames of 6000×4500 px need about 5400.82 GB" in line and "GB free" in line
    assert not list((tmp_path / "o").iterdir())


def test_acquire_stops_cleanly_when_the_disk_fills(capsys, tmp_path, monkeypatch):
    import errno

    from devices import RawFrame

    save = RawFrame.save_dng
    room = {"frames": 2}

    def a_disk_with_room_for_two_frames(frame, path, overwrite=False):
        if room["frames"] == 0:  # the DNG goes in, its sidecar finds no room
            path.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        room["frames"] -= 1
        save(frame, path, overwrite)

    monkeypatch.setattr(RawFrame, "save_dng", a_disk_with_room_for_two_frames)
    code = main(["acquire", "--device", "sim://?scene=flat", "--roi", "2968,2226,16,16", "--count", "5",
                 "--out", str(tmp_path)])
    captured = capsys.readouterr()
    assert code == 1 and "wrote 2 DNG files" in captured.out
    assert "is full (No space left on device): stopped after 2 of 5 frames" in captured.err
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".dng", ".dng", ".json", ".json"]


def test_a_junk_file_in_a_replay_folder_is_skipped_and_reported(capsys, tmp_path):
    from devices import load_raw

    folder = _replay_folder(tmp_path / "rec", 2)
    (folder / "e_junk.dng").write_bytes(b"not a raw file at all")
    out = tmp_path / "out"
    code = main(["acquire", "--device", f"replay://{folder}", "--count", "2", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 1 and "wrote 2 DNG files" in captured.out
    assert "1 unreadable file skipped: e_junk.dng (" in captured.err.splitlines()[-1]
    assert len([load_raw(p) for p in out.glob("*.dng")]) == 2


def test_a_replay_folder_with_no_readable_frame_is_refused_naming_a_file(tmp_path):
    from devices import DeviceNotFoundError, open_camera
    from devices.replay import UnreadableFrameWarning

    (tmp_path / "a.dng").write_bytes(b"")
    with pytest.raises(DeviceNotFoundError, match=r"none of the 1 .dng files .* is a readable BMI frame "
                                                  r"\(a.dng: is empty \(0 bytes\): not a DNG"), \
            pytest.warns(UnreadableFrameWarning, match="skipped a.dng"):
        open_camera(f"replay://{tmp_path}")


def test_a_zero_byte_dng_is_called_empty(tmp_path):
    from devices import RawFileError, load_raw

    (tmp_path / "z.dng").write_bytes(b"")
    with pytest.raises(RawFileError, match=r"z.dng is empty \(0 bytes\): not a DNG"):
        load_raw(tmp_path / "z.dng")


def test_acquire_from_sim_without_a_scene_says_it_captures_the_chart(capsys, tmp_path):
    assert main(["acquire", "--roi", "2968,2226,16,16", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "sim:// shows its calibration chart; to capture a scene give --scene image:PATH" in out


# -- firmware-sim serve ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, expected", [
    ("--port", "-5", "argument --port: -5 is outside [0, 65535]"),
    ("--port", "70000", "argument --port: 70000 is outside [0, 65535]"),
    ("--duration-s", "-1", "argument --duration-s: -1 is outside [0, inf) s"),
    ("--duration-s", "inf", "argument --duration-s: inf is not a finite number"),
    ("--idle-timeout-s", "0", "argument --idle-timeout-s: 0 is outside (0, 86400] s"),
    ("--seed", "-1", "argument --seed: -1 is outside"),
    ("--serial", "1e20", "argument --serial: '1e20' is not a whole number"),
    ("--faults", "drop=nan", "--faults drop=nan: fault probability drop=nan is outside [0, 1]"),
    ("--faults", "seed=x", "--faults seed=x: bad fault spec item 'seed=x': seed takes a whole number"),
])
def test_firmware_sim_serve_refuses_what_would_run_forever_or_fail_later(capsys, option, value, expected):
    assert expected in _refusal(capsys, ["firmware-sim", "serve", f"{option}={value}"])


# -- --scheduler -------------------------------------------------------------------------------------------------------

def test_scheduler_local_workers_are_capped_with_a_clear_error(capsys):
    from bmi_sdk.scaleout.scheduler import max_local_workers, parse_scheduler

    assert parse_scheduler(f"local:{max_local_workers()}").n_workers == max_local_workers()
    with pytest.raises(ValueError, match=r"local:N takes 1 … \d+ workers here \(4 per CPU core\); for more, .* "
                                         r"tcp://HOST:PORT"):
        parse_scheduler("local:100000")
    assert "argument --scheduler: --scheduler 'local:100000': local:N takes" in _refusal(
        capsys, ["infer", "x.dng", "--out", "o", "--scheduler", "local:100000"])


_DASK_RUN = """
import sys
from bmi_sdk.cli._logging import configure
from bmi_sdk.scaleout import open_client

if __name__ == "__main__":  # Dask's worker processes import this file again
    configure(int(sys.argv[1]), 0, "infer")
    with open_client("local:1") as client:
        assert client.submit(sum, [1, 2]).result() == 3
"""


@pytest.mark.parametrize("verbose", [0, 2])
def test_dask_logs_stay_at_warning_unless_asked_for_with_vv(tmp_path, verbose):
    import os
    import subprocess
    import sys

    script = tmp_path / "run.py"
    script.write_text(_DASK_RUN)
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    run = subprocess.run([sys.executable, str(script), str(verbose)], capture_output=True, text=True, env=env,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    dask_info = [line for line in run.stderr.splitlines() if line.startswith("distributed.") and ": info: " in line]
    assert (len(dask_info) > 5) if verbose == 2 else not dask_info, run.stderr


# -- the TCP link's messages -----------------------------------------------------------------------------------------

def test_a_camera_that_wants_a_token_says_how_to_give_one():
    from devices import AccessDeniedError, open_camera
    from firmware_sim import FirmwareDevice, FirmwareServer, FlatField

    with FirmwareServer(FirmwareDevice(source=FlatField()), token=b"s3cret") as server:
        with pytest.raises(AccessDeniedError, match=r"^this camera needs a token: add \?token_file=FILE .* to the "
                                                    r"tcp:// URI") as err:
            open_camera(server.uri)
    assert "AUTH" not in str(err.value) and "HELLO" not in str(err.value)


def test_a_camera_that_closes_the_link_is_named_as_the_cause():
    from devices import DeviceRemovedError, open_camera
    from firmware_sim import FirmwareDevice, FirmwareServer, FlatField

    server = FirmwareServer(FirmwareDevice(source=FlatField()))
    server.start()
    with open_camera(server.uri) as cam:
        cam.settings.roi = (2968, 2226, 64, 48)
        server.close()
        with pytest.raises(DeviceRemovedError, match="the camera closed the link") as err:
            for _ in range(50):  # the host notices the hang-up on its next read
                cam.capture(timeout_s=2)
    assert "bytes" not in str(err.value)


# -- calibrate --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("args, expected", [
    (["--simulate", "decenter_um=1e9,0"], "--simulate decenter_um=1e9,0: |decenter_um| is at most 1000 um"),
    (["--simulate", "decenter_um=nan,0"], "--simulate decenter_um=nan,0: decenter_um needs 2 finite number(s)"),
    (["--simulate", "decenter_um=1", "--points", "1e9"], "argument --points: '1e9' is not a whole number"),
    (["--simulate", "decenter_um=1,0", "--points", "-1"], "argument --points: -1 is outside [4, 21]"),
    (["--simulate", "decenter_um=1,0", "--held-out", "100"], "argument --held-out: 100 is outside [0, 6]"),
    (["--simulate", "decenter_um=1,0", "--max-outer", "0"], "argument --max-outer: 0 is outside [1, 20]"),
    (["--simulate", "decenter_um=1,0", "--seed", "-1"], "argument --seed: -1 is outside"),
    (["--captures", "no/such/folder"], "--captures no/such/folder: no such folder"),
])
def test_calibrate_refuses_out_of_range_options_before_capturing(capsys, tmp_path, args, expected):
    assert expected in _refusal(capsys, ["calibrate", "--out", str(tmp_path / "c.json"), *args])
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("out, expected", [
    ("c.txt", "--out {tmp}/c.txt: name it *.json"),
    ("afile/c.json", "--out {tmp}/afile/c.json: cannot create the folder"),
])
def test_calibrate_checks_its_output_before_capturing(capsys, tmp_path, out, expected):
    (tmp_path / "afile").write_text("a file, not a folder")
    line = _refusal(capsys, ["calibrate", "--simulate", "decenter_um=1,0", "--out", str(tmp_path / out)])
    assert expected.format(tmp=tmp_path) in line


@pytest.mark.parametrize("value, expected", [
    ("-1", "argument --depth-m: -1 is outside (0, inf) m (or inf)"),
    ("nan", "argument --depth-m: nan is not a finite number"),
])
def test_psf_export_refuses_a_depth_that_is_not_a_positive_range(capsys, tmp_path, value, expected):
    assert expected in _refusal(capsys, ["psf", "export", f"--depth-m={value}", "--out", str(tmp_path / "k.npz")])
    assert not list(tmp_path.iterdir())


# -- crlb and lens ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, expected", [
    ("--depths-m", "1e12", "argument --depths-m: 1e12 is outside [0.1, 100] m (or inf)"),
    ("--depths-m", "nan", "argument --depths-m: nan is not a finite number"),
    ("--depths-m", "2,,3", "argument --depths-m: '2,,3' is not a comma list of numbers"),
    ("--fields-deg", "85", "argument --fields-deg: 85 is outside [0, 80]"),
    ("--patch-px", "1000000", "argument --patch-px: 1000000 is outside [2, 4096] px"),
    ("--rms-contrast", "0", "argument --rms-contrast: 0 is outside (0, 1]"),
    ("--noise-sigma", "inf", "argument --noise-sigma: inf is not a finite number"),
    ("--inverse-step-per-m", "-1", "argument --inverse-step-per-m: -1 is outside (0, 0.1]"),
    ("--kernel-px-fisheye", "40", "argument --kernel-px-fisheye: 40 is outside [1, 401] px, odd"),
    ("--lenses", "zoom", "argument --lenses: a comma list of monocentric, fisheye, got 'zoom'"),
])
def test_crlb_refuses_out_of_range_options_naming_them(capsys, option, value, expected):
    assert expected in _refusal(capsys, ["crlb", f"{option}={value}"])


def test_lens_names_its_option(capsys, tmp_path):
    assert "--lens nan: no lens called 'nan'" in _refusal(capsys, ["lens", "--lens", "nan"])
    line = _refusal(capsys, ["lens", "--write-sensor-mapping", str(tmp_path / "map.txt")])
    assert "--write-sensor-mapping" in line and "name it *.json" in line


def test_options_that_would_be_ignored_or_name_a_missing_file_are_refused(capsys, tmp_path):
    line = _refusal(capsys, ["simulate", "--procedural", "0", "--rgb", "x.png", "--out", str(tmp_path / "s.dng")])
    assert "--procedural renders its own scene" in line
    line = _refusal(capsys, ["firmware-sim", "serve", "--token-file", str(tmp_path / "none")])
    assert f"--token-file {tmp_path / 'none'}: cannot read it (No such file or directory)" in line


def test_a_replay_folder_shorter_than_count_is_copied_whole_and_reported(capsys, tmp_path):
    folder = _replay_folder(tmp_path / "rec", 2)
    code = main(["acquire", "--device", f"replay://{folder}", "--count", "3", "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert code == 1 and "wrote 2 DNG files" in captured.out
    assert "played 2 of the 3 frames asked for" in captured.err and "no frame for" not in captured.err


# -- fit-fusion ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, expected", [
    ("--tiles", "1000000", "--tiles 1000000 needs about"),   # its reads alone: ~33 TB
    ("--tiles", "0", "argument --tiles: 0 is outside [1, inf)"),
    ("--threads", "-1", "argument --threads: -1 is outside [1, 1024]"),
    ("--pixels", "nan", "argument --pixels: 'nan' is not a whole number"),
    ("--seed", "-1", "argument --seed: -1 is outside [0, 4294967295]"),
    ("--scales", "nan", "--scales must be a comma list of numbers ≥ 1"),
    ("--sigmas", "-1", "--sigmas must be a comma list of noise σs in (0, 1)"),
])
def test_fit_fusion_refuses_hostile_values_before_any_tile_renders(capsys, option, value, expected):
    assert expected in _refusal(capsys, ["fit-fusion", "--dry-run", option, value])


# -- train ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value, expected", [
    ("--steps", "-1", "argument --steps: -1 is outside [1, inf)"),        # ran, then exported an untrained network
    ("--samples", "-1", "argument --samples: -1 is outside [1, inf)"),    # a KeyError traceback
    ("--samples", "1000000000", "--samples 1000000000: 1000000000 pairs of 128² px need about"),  # disk
    ("--batch", "100000", "--batch/--crop 100000/128 needs about"),      # ~3.5 TB a step
    ("--lr", "nan", "argument --lr: nan is not a finite number"),
    ("--threads", "0", "argument --threads: 0 is outside [1, 1024]"),     # a RuntimeError traceback
    ("--sigma", "-1", "argument --sigma: -1 is outside (0, 1)"),
    ("--scene-scale-max", "1e9", "--scene-scale-max 1000000000.0 needs about"),
    ("--preset", "nosuch", "--preset nosuch: unknown preset"),
    ("--crop", "90", "argument --crop: 90 is outside [4, inf) px, a multiple of 4"),
])
def test_train_refuses_hostile_values_before_any_pair_renders(capsys, tmp_path, option, value, expected):
    line = _refusal(capsys, ["train", "--out", str(tmp_path / "run"), "--cache", str(tmp_path / "cache"), option,
                             value])
    assert expected in line
    assert not list(tmp_path.iterdir())   # no run folder, no cache


# -- bench targets -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, expected", [
    (["device", "--sim-frames", "-1"], "argument --sim-frames: -1 is outside [1, 1000]"),   # an UnboundLocalError
    (["device", "--frames", "0"], "argument --frames: 0 is outside [1, 10000]"),
    (["calibrate", "--seeds", "-1"], "argument --seeds: -1 is outside [1, inf)"),            # an IndexError
    (["scaleout", "--shard-samples", "0"], "argument --shard-samples: 0 is outside [1, inf)"),  # a ZeroDivisionError
    (["scaleout", "--crop", "90"], "argument --crop: 90 is outside [16, 1024] px, a multiple of 4"),
    (["scaleout", "--frame-px", "99999999x5"], "argument --frame-px: 99999999 is outside [64, 6000] px"),
    (["infer", "--seam-frame", "512"], "argument --seam-frame: '512' is not a size written HxW"),
    (["infer", "--frame-tiles", "512,-5"], "argument --frame-tiles: -5 is outside [64, 4096] px"),
    (["infer", "--peak-gflops", "nan"], "argument --peak-gflops: nan is not a finite number"),
    (["model", "--tiles", "1000000000"], "argument --tiles: 1000000000 is outside [1, 1000]"),
])
def test_bench_targets_refuse_hostile_values_before_measuring(capsys, argv, expected):
    assert expected in _refusal(capsys, ["bench", *argv])


def test_a_second_train_into_a_folder_another_run_is_writing_is_refused_before_rendering(capsys, tmp_path):
    """Two `bmi train --out RUN` at once both rendered, trained and wrote their checkpoints and model over each
    other's. The run holds RUN/.bmi-train.lock until its model is exported; a second is refused, naming the first's
    process, before a pair renders."""
    import os

    from bmi_sdk.cli.train import LOCK_NAME
    from bmi_sdk.io_atomic import lock_folder, unlock_folder

    run = tmp_path / "run"
    run.mkdir()
    fd = lock_folder(run / LOCK_NAME)  # another run's lock
    try:
        code = main(["train", "--out", str(run), "--cache", str(tmp_path / "cache"), "--steps", "1"])
    finally:
        unlock_folder(run / LOCK_NAME, fd)
    err = capsys.readouterr().err
    assert code == 1 and f"{run} is being written by another run (process {os.getpid()})" in err, err
    assert not (tmp_path / "cache").exists() and not list(run.iterdir())


def test_psf_warm_names_an_unknown_lens_as_one_not_as_a_missing_model(capsys):
    """`bmi psf warm --lens nosuch` said no evidence model was shipped for that lens."""
    line = _refusal(capsys, ["psf", "warm", "--lens", "nosuch"])
    assert "argument --lens: invalid choice: 'nosuch'" in line and "bmi_monocentric" in line
