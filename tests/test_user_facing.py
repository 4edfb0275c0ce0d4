"""What a user expects of the SDK (issue 14): a version, traceable reports, execution providers, usable outputs."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import bmi_sdk
from bmi_sdk.runtime import Model, run_job


@pytest.fixture(scope="module")
def model_path(passthrough_model):
    return passthrough_model


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    from devices import Roi, open_camera

    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    with open_camera("sim://user-test?scene=chart&seed=1") as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(path)
    return path


def test_version_flag_prints_the_sdk_version(bmi):
    assert bmi("--version").stdout.strip() == f"bmi-sdk {bmi_sdk.__version__}"


def test_cnn_report_records_versions_provider_and_input_path(model_path, dng, tmp_path):
    import onnxruntime as ort

    from devices import load_raw

    _, report = run_job(dng, tmp_path / "a", model_path=model_path, tile_px=64, threads=1)
    on_disk = json.loads((tmp_path / "a" / "report.json").read_text())
    assert on_disk["software"]["bmi_sdk"] == bmi_sdk.__version__
    assert on_disk["software"]["onnxruntime"] == ort.__version__
    assert on_disk["execution_provider"] == "CPUExecutionProvider" == on_disk["model"]["execution_provider"]
    assert on_disk["input_path"] == os.path.abspath(dng)
    _, in_memory = run_job(load_raw(dng), tmp_path / "b", model_path=model_path, tile_px=64, threads=1)
    assert in_memory["input_path"] is None
    _, told = run_job(load_raw(dng), tmp_path / "c", model_path=model_path, tile_px=64, threads=1, input_path=dng)
    assert told["input_path"] == os.path.abspath(dng)


def test_classical_report_records_versions_and_no_provider(dng, tmp_path):
    from bmi_sdk.decode import ClassicalConfig

    run_job(dng, tmp_path, decoder="classical", classical_config=ClassicalConfig(candidates=8))
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["software"]["bmi_sdk"] == bmi_sdk.__version__ and report["software"]["onnxruntime"]
    assert report["execution_provider"] is None and report["input_path"] == os.path.abspath(dng)


def test_batch_reports_record_each_frames_path(model_path, dng, tmp_path):
    from bmi_sdk.runtime.batch import DecodeOptions, run_batch

    jobs = [(dng, tmp_path / "one")]
    summaries = run_batch(jobs, DecodeOptions(model_path=str(model_path), tile_px=64, threads=1), progress=False)
    assert summaries[0]["ok"], summaries
    assert json.loads((tmp_path / "one" / "report.json").read_text())["input_path"] == os.path.abspath(dng)


# -- execution providers -------------------------------------------------------------------------------------

def test_provider_by_short_or_full_name_and_session_options(model_path):
    import onnxruntime as ort

    assert Model(model_path, tile_px=64, threads=1, providers="cpu").provider == "CPUExecutionProvider"
    assert Model(model_path, tile_px=64, threads=1,
                 providers=["CPUExecutionProvider"]).describe()["execution_provider"] == "CPUExecutionProvider"
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    assert Model(model_path, tile_px=64, sess_options=opts).threads == 1


def test_unavailable_provider_is_refused_naming_the_available_ones(model_path, dng, tmp_path, bmi):
    with pytest.raises(ValueError, match="'WarpDrive'.*available: .*CPUExecutionProvider"):
        Model(model_path, tile_px=64, providers="WarpDrive")
    run = bmi("infer", dng, "--out", tmp_path / "o", "--model", model_path, "--tile-px", 64, "--provider",
              "WarpDrive", check=False)
    assert run.returncode == 1 and "available: " in run.stderr and "CPUExecutionProvider" in run.stderr
    assert not (tmp_path / "o").exists()
    run = bmi("infer", dng, "--out", tmp_path / "o", "--decoder", "classical", "--provider", "cpu", check=False)
    assert run.returncode == 1 and "classical decoder runs none" in run.stderr


def test_default_provider_is_the_best_available(monkeypatch):
    import onnxruntime as ort

    from bmi_sdk.runtime.model import choose_providers

    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    assert choose_providers() == ["CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert choose_providers() == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers",
                        lambda: ["CUDAExecutionProvider", "TensorrtExecutionProvider", "CPUExecutionProvider"])
    assert choose_providers() == ["TensorrtExecutionProvider", "CPUExecutionProvider"]
    assert choose_providers("cuda") == ["CUDAExecutionProvider", "CPUExecutionProvider"]


def test_cli_infer_runs_on_the_provider_asked_for(model_path, dng, tmp_path, bmi):
    bmi("infer", dng, "--out", tmp_path, "--model", model_path, "--tile-px", 64, "--threads", 1, "--provider", "cpu",
        "--quiet")
    assert json.loads((tmp_path / "report.json").read_text())["execution_provider"] == "CPUExecutionProvider"


# -- outputs a person can use ----------------------------------------------------------------------------------

def _read_ply_xyz(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    return np.frombuffer(data[end:], dtype)


def test_depth_z_is_planar_depth_beside_range_and_matches_the_point_cloud(tmp_path):
    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.runtime import write_outputs

    rng = np.random.default_rng(0)
    h, w, row0, col0 = 24, 32, 400, 600   # far off-axis: cos θ well below 1
    depth = rng.uniform(0.8, 9.0, (h, w)).astype(np.float32)
    depth[3, 5] = np.nan
    aif = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    written = write_outputs(tmp_path, aif, depth, BMI_SENSOR, row0, col0)
    assert "depth_z.npy" in written["files"]
    z = np.load(tmp_path / "depth_z.npy")
    rows, cols = np.mgrid[row0:row0 + h, col0:col0 + w]
    theta, _ = BMI_SENSOR.field_angles(rows, cols)
    assert z.dtype == np.float32 and np.isnan(z[3, 5]) and np.isfinite(np.delete(z.ravel(), 3 * w + 5)).all()
    np.testing.assert_allclose(z, depth * np.cos(np.radians(theta)), rtol=1e-6)
    assert np.nanmax(z / depth) < 0.9   # not the range again
    points = _read_ply_xyz(tmp_path / "points.ply")
    np.testing.assert_allclose(np.sort(points["z"]), np.sort(z[np.isfinite(z)]), rtol=1e-5)


def test_classical_job_writes_depth_z_too(dng, tmp_path):
    from bmi_sdk.decode import ClassicalConfig

    _, report = run_job(dng, tmp_path, decoder="classical", classical_config=ClassicalConfig(candidates=8))
    z, d = np.load(tmp_path / "depth_z.npy"), np.load(tmp_path / "depth.npy")
    assert "depth_z.npy" in report["files"] and np.array_equal(np.isnan(z), np.isnan(d))
    assert np.all(z[np.isfinite(z)] <= d[np.isfinite(d)])


def test_fixed_depth_range_colours_the_preview_the_same_in_every_frame(tmp_path):
    import cv2

    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.runtime import write_outputs

    aif = np.full((16, 16, 3), 0.5, np.float32)
    near, far = 0.7, 10.0
    colours = []
    for i, depth_m in enumerate((2.0, 5.0)):
        depth = np.full((16, 16), depth_m, np.float32)
        depth[0, 0] = 2.0        # the same 2 m pixel in two frames of different content
        write_outputs(tmp_path / str(i), aif, depth, BMI_SENSOR, 2000, 2800, depth_range_m=(near, far))
        colours.append(cv2.imread(str(tmp_path / str(i) / "depth_preview.png"))[0, 0])
    t = (1 / 2.0 - 1 / far) / (1 / near - 1 / far)
    expected = cv2.applyColorMap(np.array([[int(t * 255)]], np.uint8), cv2.COLORMAP_TURBO)[0, 0]
    assert np.array_equal(colours[0], expected) and np.array_equal(colours[1], expected)
    with pytest.raises(ValueError, match="0 < NEAR < FAR"):
        write_outputs(tmp_path / "bad", aif, depth, BMI_SENSOR, depth_range_m=(10, 0.7))


def test_cli_depth_range(model_path, dng, tmp_path, bmi):
    bmi("infer", dng, "--out", tmp_path / "o", "--model", model_path, "--tile-px", 64, "--threads", 1,
        "--depth-range", "0.7,10", "--quiet")
    assert (tmp_path / "o" / "depth_preview.png").is_file() and (tmp_path / "o" / "depth_z.npy").is_file()
    for bad in ("10,0.7", "0.7", "near,far"):
        run = bmi("infer", dng, "--out", tmp_path / "x", "--model", model_path, "--depth-range", bad, check=False)
        assert run.returncode == 2 and "--depth-range" in run.stderr, (bad, run.stderr)
        assert not (tmp_path / "x").exists()


def test_psf_export_writes_a_png_when_the_name_says_png(tmp_path, capsys):
    import cv2

    from bmi_sdk.cli import main

    args = ["psf", "export", "--wavelength-nm", "587.6", "--depth-m", "2", "--field-deg", "30"]
    assert main(args + ["--out", str(tmp_path / "k.npy")]) == 0
    assert main(args + ["--out", str(tmp_path / "k.png")]) == 0
    kernel = np.load(tmp_path / "k.npy")
    png = cv2.imread(str(tmp_path / "k.png"), cv2.IMREAD_UNCHANGED)
    assert (tmp_path / "k.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.dtype == np.uint16 and png.shape == kernel.shape and png.max() == 65535
    np.testing.assert_allclose(png / 65535, kernel / kernel.max(), atol=1 / 65535)
    assert "normalised to the peak" in capsys.readouterr().out
    assert main(args + ["--out", str(tmp_path / "k.tif")]) == 1
    assert "name it .npy" in capsys.readouterr().err and not (tmp_path / "k.tif").exists()
    # an existing kernel is kept unless --overwrite says otherwise
    other = ["psf", "export", "--wavelength-nm", "450", "--depth-m", "1", "--field-deg", "50"]
    assert main(other + ["--out", str(tmp_path / "k.npy")]) == 1
    assert "--overwrite" in capsys.readouterr().err
    np.testing.assert_array_equal(np.load(tmp_path / "k.npy"), kernel)
    assert main(other + ["--out", str(tmp_path / "k.npy"), "--overwrite"]) == 0
    assert not np.array_equal(np.load(tmp_path / "k.npy"), kernel)


def test_simulate_save_truth_writes_the_window_the_frame_shows(tmp_path, bmi):
    from bmi_sdk.scenes import generate_scene

    rng = np.random.default_rng(1)
    rgb = rng.uniform(0, 1, (66, 67, 3)).astype(np.float32)      # odd width: the frame keeps whole RGGB cells
    depth = rng.uniform(1, 5, (66, 67)).astype(np.float32)
    depth[2, 3] = 0                                               # unknown
    np.save(tmp_path / "rgb.npy", rgb)
    np.save(tmp_path / "d.npy", depth)
    bmi("simulate", "--rgb", tmp_path / "rgb.npy", "--depth", tmp_path / "d.npy", "--psf-mode", "tensor",
        "--field-deg", 20, "--noise", 0.005, "--out", tmp_path / "f.dng", "--save-truth")
    sidecar = json.loads((tmp_path / "f.json").read_text())
    truth_range = np.load(tmp_path / "f_truth_range.npy")
    truth_rgb = np.load(tmp_path / "f_truth_rgb.npy")
    assert list(truth_range.shape) == sidecar["shape"] == [66, 66] and truth_rgb.shape == (66, 66, 3)
    assert np.isnan(truth_range[2, 3]) and np.array_equal(np.delete(truth_range.ravel(), 2 * 66 + 3),
                                                          np.delete(depth[:, :66].ravel(), 2 * 66 + 3))
    np.testing.assert_array_equal(truth_rgb, rgb[:, :66])

    bmi("simulate", "--procedural", 5, "--size", 64, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "p.dng", "--save-truth")
    scene = generate_scene(64, 64, 5)
    np.testing.assert_array_equal(np.load(tmp_path / "p_truth_range.npy"), scene.range_m)
    np.testing.assert_array_equal(np.load(tmp_path / "p_truth_rgb.npy"), scene.rgb)


def test_simulate_and_calibrate_refuse_an_earlier_runs_files_before_their_work(tmp_path, capsys):
    """A repeated `bmi simulate`, `bmi calibrate` or `bmi psf build` command line would silently replace a rendered
    frame, a calibration or a PSF tensor (and its metadata JSON, which may be a calibration's name): each refuses, naming every file, before rendering or capturing (so the refusal is quick),
    and leave the files as they were; --overwrite replaces them."""
    from bmi_sdk.cli import main

    out = tmp_path / "p.dng"
    simulate = ["simulate", "--procedural", "5", "--size", "64", "--psf-mode", "tensor", "--noise", "0.005",
                "--save-truth", "--out", str(out)]
    assert main(simulate) == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(before) == {"p.dng", "p.json", "p_truth_range.npy", "p_truth_rgb.npy"}
    capsys.readouterr()
    assert main(simulate + ["--seed", "1"]) == 1
    err = capsys.readouterr().err
    assert all(name in err for name in before) and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert main(simulate + ["--seed", "1", "--overwrite"]) == 0
    assert (tmp_path / "p.dng").read_bytes() != before["p.dng"]  # another noise draw
    assert (tmp_path / "p_truth_range.npy").read_bytes() == before["p_truth_range.npy"]  # the same scene

    calib = tmp_path / "c.json"
    calib.write_text('{"an": "earlier calibration"}')
    capsys.readouterr()
    assert main(["calibrate", "--simulate", "decenter_um=8,0", "--out", str(calib)]) == 1
    err = capsys.readouterr().err
    assert "c.json already exists" in err and "simulated" not in capsys.readouterr().out
    assert calib.read_text() == '{"an": "earlier calibration"}'
    captures = tmp_path / "caps"
    captures.mkdir()
    (captures / "captures.json").write_text("{}")
    assert main(["calibrate", "--simulate", "decenter_um=8,0", "--out", str(tmp_path / "d.json"),
                 "--save-captures", str(captures)]) == 1
    assert "is not empty" in capsys.readouterr().err and not (tmp_path / "d.json").exists()
    # `bmi psf build --out c.npz` writes its metadata to c.json: the calibration above would have been replaced
    assert main(["psf", "build", "--out", str(tmp_path / "c.npz")]) == 1
    assert "c.json already exists" in capsys.readouterr().err
    assert calib.read_text() == '{"an": "earlier calibration"}' and not (tmp_path / "c.npz").exists()


# -- logging -----------------------------------------------------------------------------------------------------

def test_diagnostics_go_through_logging_and_follow_v_and_q(model_path, tmp_path, capsys):
    import warnings

    from bmi_sdk.cli import main
    from devices import Roi, open_camera
    from firmware_sim import FirmwareDevice, make_source

    with open_camera("sim://", device=FirmwareDevice(source=make_source("dark"), seed=1)) as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(tmp_path / "dark.dng")
    infer = ["infer", str(tmp_path / "dark.dng"), "--model", str(model_path), "--tile-px", "64", "--quiet"]
    outputs = {}
    for flags in ([], ["-q"], ["-v"]):
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            code = main(flags + infer + ["--out", str(tmp_path / ("o" + "".join(flags)))])
        outputs[tuple(flags)] = (code, capsys.readouterr())
    code, captured = outputs[()]
    assert code == 0 and "bmi infer: warning: median signal" in captured.err and "bmi infer: info" not in captured.err
    assert "warning" not in captured.out and "decoded with the" in captured.out       # results stay on stdout
    code, captured = outputs[("-q",)]
    assert code == 0 and captured.err == "" and "decoded with the" in captured.out
    code, captured = outputs[("-v",)]
    assert code == 0 and "bmi infer: info: input " in captured.err and "execution provider CPU" in captured.err
    assert main(["-q", "infer", str(tmp_path / "missing.dng"), "--out", str(tmp_path / "m")]) == 1
    assert "bmi infer: error: no raw file" in capsys.readouterr().err      # -q never hides an error
    bars = {}
    for flags in ([], ["-q"]):  # infer's progress bar draws on stderr too: -q leaves errors only there
        assert main(flags + infer[:-1] + ["--out", str(tmp_path / ("bar" + "".join(flags)))]) == 0
        bars[tuple(flags)] = capsys.readouterr().err
    assert "infer: 100%" in bars[()] and bars[("-q",)] == ""


# -- DNG colour ----------------------------------------------------------------------------------------------------

def test_dng_colour_tags_make_raw_viewers_render_the_scenes_colours(tmp_path):
    """A flat patch of linear sRGB (0.2, 0.4, 0.1), saved as DNG and developed by LibRaw (rawpy) with the
    camera's white balance into linear sRGB, keeps its colour: R/G 0.5, B/G 0.25. With the identity
    ColorMatrix the DNG used to carry, LibRaw rendered it grey (R/G 1.01, B/G 1.00)."""
    import rawpy
    import tifffile

    from devices import Roi, open_camera
    from devices.dng import XYZ_TO_CAMERA
    from firmware_sim import FirmwareDevice, make_source

    with open_camera("sim://", device=FirmwareDevice(source=make_source("flat:0.2,0.4,0.1"), seed=1)) as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(tmp_path / "flat.dng")
    with tifffile.TiffFile(tmp_path / "flat.dng") as tif:
        tags = tif.pages[0].tags
        matrix = np.asarray(tags["ColorMatrix1"].value, float).reshape(-1, 2)
        neutral = np.asarray(tags["AsShotNeutral"].value, float).reshape(-1, 2)
        assert tags["CalibrationIlluminant1"].value == 21                       # D65
    np.testing.assert_allclose((matrix[:, 0] / matrix[:, 1]).reshape(3, 3), XYZ_TO_CAMERA, atol=1e-6)
    np.testing.assert_allclose(neutral[:, 0] / neutral[:, 1], 1.0)
    np.testing.assert_allclose(XYZ_TO_CAMERA @ [0.95047, 1.0, 1.08883], 1.0, atol=1e-3)  # D65 white → (1, 1, 1)
    with rawpy.imread(str(tmp_path / "flat.dng")) as raw:
        assert list(raw.camera_whitebalance[:3]) == pytest.approx([1.0, 1.0, 1.0])
        np.testing.assert_allclose(raw.color_matrix[:, :3], np.eye(3), atol=1e-5)   # camera RGB is sRGB
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, use_camera_wb=True, output_bps=16,
                              output_color=rawpy.ColorSpace.sRGB)
    mean = rgb[16:-16, 16:-16].reshape(-1, 3).mean(axis=0)
    assert mean[0] / mean[1] == pytest.approx(0.5, abs=0.02) and mean[2] / mean[1] == pytest.approx(0.25, abs=0.02)
