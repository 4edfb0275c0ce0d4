"""`bmi infer` without traps (issue 14): the output set is all-or-nothing and never silently replaced, the
output folder is checked before inference, and frames that cannot carry depth are flagged or refused."""

from __future__ import annotations

import errno
import json
import warnings

import numpy as np
import pytest
import torch

from bmi_sdk.cli import main
from bmi_sdk.runtime import run_job
from bmi_sdk.runtime.quality import (
    MAX_SATURATED_FRACTION,
    MIN_SIGNAL_FRACTION,
    MIN_STRUCTURE,
    FrameQualityWarning,
    TestPatternFrameError,
    assess_frame,
)
from devices import Roi, open_camera
from firmware_sim import FirmwareDevice, make_source

ROI = Roi(2980, 2240, 96, 64)


@pytest.fixture(scope="module")
def model(passthrough_model):
    return passthrough_model


def _capture(scene="chart", test_pattern=0, exposure_us=None):
    with open_camera("sim://", device=FirmwareDevice(source=make_source(scene), seed=1)) as cam:
        cam.settings.roi = ROI
        cam.settings.test_pattern = test_pattern
        if exposure_us:
            cam.settings.exposure_us = exposure_us
        return cam.capture()


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    _capture().save_dng(path)
    return path


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_earlier_results_are_refused_without_overwrite(model, dng, tmp_path):
    out = tmp_path / "out"
    run_job(dng, out, model_path=model, tile_px=64, threads=1)
    before = _snapshot(out)
    with pytest.raises(FileExistsError, match="earlier run's results.*--overwrite"):
        run_job(dng, out, model_path=model, tile_px=64, threads=1)
    assert _snapshot(out) == before
    _, report = run_job(dng, out, model_path=model, tile_px=64, threads=1, overwrite=True)
    assert json.loads((out / "report.json").read_text())["stage_timings_s"] == report["stage_timings_s"]
    assert report["files"]["depth.npy"] == str(out / "depth.npy") and (out / "depth.npy").is_file()
    assert sorted(p.name for p in out.iterdir()) == sorted(before)  # no staging folder left


def test_a_run_that_fails_while_writing_leaves_the_earlier_set_untouched(model, dng, tmp_path, monkeypatch):
    import bmi_sdk.runtime.outputs as outputs

    out = tmp_path / "out"
    run_job(dng, out, model_path=model, tile_px=64, threads=1)
    before = _snapshot(out)

    def disk_full(path, *args, **kw):  # the point cloud is written after the images and depth maps
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(outputs, "write_ply", disk_full)
    with pytest.raises(OSError, match="No space left"):
        run_job(dng, out, model_path=model, tile_px=64, threads=1, overwrite=True)
    assert _snapshot(out) == before  # not one new file beside the old ones, no staging folder


def test_an_unwritable_out_is_refused_before_inference(model, dng, tmp_path, monkeypatch, capsys):
    import bmi_sdk.runtime.job as job

    def must_not_run(*args, **kw):
        raise AssertionError("inference ran before the output folder was checked")
    monkeypatch.setattr(job, "open_decoder", must_not_run)
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(OSError):
        run_job(dng, tmp_path / "a_file" / "out", model_path=model, tile_px=64)
    with pytest.raises(OSError, match="is a file"):
        run_job(dng, tmp_path / "a_file", model_path=model, tile_px=64)
    code = main(["infer", str(dng), "--out", str(tmp_path / "a_file" / "out"), "--model", str(model)])
    err = capsys.readouterr().err
    assert code == 1 and err.startswith("bmi infer: error: cannot write the outputs") and "Traceback" not in err


def test_a_point_cloud_step_or_thread_count_below_one_is_refused_before_inference(model, dng, tmp_path, monkeypatch,
                                                                                    capsys):
    """`--ply-step 0` failed only when the point cloud was written, after the whole decode; `--threads -2` was
    handed to onnxruntime as it was. Both are refused first (argparse, exit 2; ``run_job`` for the API), for every
    decoder, and nothing is written."""
    import bmi_sdk.runtime.job as job

    def must_not_run(*args, **kw):
        raise AssertionError("inference ran before its options were checked")
    monkeypatch.setattr(job, "open_decoder", must_not_run)
    for decoder in ("cnn", "classical", "learned"):
        for flags, named in ((["--ply-step", "0"], "--ply-step"), (["--threads", "-2"], "--threads")):
            model_flags = ["--model", str(model)] if decoder == "cnn" else []
            with pytest.raises(SystemExit) as refused:
                main(["infer", str(dng), "--out", str(tmp_path / "o"), "--decoder", decoder, *model_flags, *flags])
            err = capsys.readouterr().err
            assert refused.value.code == 2 and named in err and "Traceback" not in err, (decoder, flags, err)
            assert not (tmp_path / "o").exists()
        for option, value in (("ply_step_px", 0), ("threads", -2)):
            with pytest.raises(ValueError, match=option):
                run_job(dng, tmp_path / "o", decoder=decoder, **{option: value})
            assert not (tmp_path / "o").exists()


def test_quality_metrics_tell_bad_frames_from_images():
    good = assess_frame(_capture("chart"))
    assert good.warnings == [] and good.structure > MIN_STRUCTURE
    dark = assess_frame(_capture("dark"))
    assert dark.signal_fraction < MIN_SIGNAL_FRACTION and any("black" in w for w in dark.warnings)
    saturated = assess_frame(_capture("chart", exposure_us=1_000_000))
    assert saturated.saturated_fraction > MAX_SATURATED_FRACTION and any("saturated" in w for w in saturated.warnings)
    flat = assess_frame(_capture("flat:0.3"))
    assert flat.structure < MIN_STRUCTURE and any("no optical structure" in w for w in flat.warnings)
    noise_frame = _capture("chart")
    noise_frame.data = torch.randint(noise_frame.black_level_dn, noise_frame.white_level_dn,
                                     noise_frame.data.shape, generator=torch.Generator().manual_seed(0)).numpy()
    noise = assess_frame(noise_frame)
    assert abs(noise.structure) < 0.1 and any("noise" in w for w in noise.warnings)


def test_neighbour_correlation_in_bands_equals_numpy_s_over_every_pair():
    """The gate's structure number, summed band by band on shifted raw values, against np.corrcoef of the same-colour
    pairs inside the circle taken at once (a frame of three bands, a smooth image plus noise, a disc mask)."""
    from bmi_sdk.runtime import quality

    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:1100, 0:300]
    data = (2000 + 800 * np.sin(rows / 37.0) * np.cos(cols / 23.0) + rng.normal(0, 40, rows.shape)).astype(np.uint16)
    mask = (rows - 550) ** 2 + (cols - 150) ** 2 < 500 ** 2
    both = mask[:, :-2] & mask[:, 2:]
    expected = np.corrcoef(data[:, :-2][both].astype(float), data[:, 2:][both].astype(float))[0, 1]
    assert data.shape[0] > 2 * quality.CORRELATION_ROWS
    for offset_dn in (0.0, 2000.0):
        assert quality._neighbour_correlation(data, mask, offset_dn) == pytest.approx(expected, rel=1e-12)
    assert quality._neighbour_correlation(np.full((4, 4), 7, np.uint16), np.ones((4, 4), bool)) == 0.0


def test_test_pattern_frames_are_refused_unless_asked(model, tmp_path, capsys):
    frame = _capture("chart", test_pattern=1)
    assert frame.test_pattern
    with pytest.raises(TestPatternFrameError, match="--allow-test-pattern"):
        run_job(frame, tmp_path / "a", model_path=model, tile_px=64)
    assert not (tmp_path / "a" / "report.json").exists()
    with pytest.warns(FrameQualityWarning, match="test pattern"):
        _, report = run_job(frame, tmp_path / "b", model_path=model, tile_px=64, allow_test_pattern=True)
    assert report["frame_quality"]["test_pattern"] is True
    frame.save_dng(tmp_path / "tp.dng")
    assert main(["infer", str(tmp_path / "tp.dng"), "--out", str(tmp_path / "c"), "--model", str(model)]) == 1
    err = capsys.readouterr().err
    assert "test pattern" in err and "Traceback" not in err


def test_a_black_frame_is_decoded_with_a_warning_on_stderr_and_in_the_report(model, tmp_path, capsys):
    _capture("dark").save_dng(tmp_path / "dark.dng")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        code = main(["infer", str(tmp_path / "dark.dng"), "--out", str(tmp_path / "o"), "--model", str(model),
                     "--tile-px", "64", "--quiet"])
    err = capsys.readouterr().err
    assert code == 0 and "bmi infer: warning: median signal" in err
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["frame_quality"]["signal_fraction"] < MIN_SIGNAL_FRACTION
    assert any("black" in w for w in report["frame_quality"]["warnings"])


def test_an_incomplete_frame_is_one_line_not_a_traceback(model, tmp_path, capsys):
    from devices import FrameStatus

    frame = _capture("chart")
    frame.status = FrameStatus.INCOMPLETE
    frame.save_dng(tmp_path / "cut.dng")
    code = main(["infer", str(tmp_path / "cut.dng"), "--out", str(tmp_path / "o"), "--model", str(model)])
    err = capsys.readouterr().err
    assert code == 1 and "incomplete" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
