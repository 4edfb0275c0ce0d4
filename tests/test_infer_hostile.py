"""`bmi infer` and its Python API under hostile input (issue 37): option values that would exhaust memory or that no
decoder can use, concurrent runs into one folder, left-over staging folders, frames whose sidecar lies, and a
summary a user can read."""

from __future__ import annotations

import pytest

from bmi_sdk.cli import main
from devices import Roi, open_camera
from firmware_sim import FirmwareDevice, make_source

ROI = Roi(2980, 2240, 96, 64)


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    with open_camera("sim://", device=FirmwareDevice(source=make_source("chart"), seed=1)) as cam:
        cam.settings.roi = ROI
        cam.capture().save_dng(path)
    return path


@pytest.fixture
def no_decode(monkeypatch):
    """Fail the test if any frame is decoded: every refusal here comes before the decode."""
    import bmi_sdk.decode.classical as classical
    import bmi_sdk.runtime.tiling as tiling

    def must_not_run(*args, **kw):
        raise AssertionError("the frame was decoded before the option was refused")
    monkeypatch.setattr(classical.ClassicalDecoder, "decode", must_not_run)
    monkeypatch.setattr(tiling.TilePlan, "tiles", must_not_run)


def _infer(capsys, *args) -> tuple[int, str]:
    try:
        code = main(["infer", *map(str, args), "--quiet"])
    except SystemExit as exc:  # argparse's refusal of a value its type rejects
        code = exc.code
    return code, capsys.readouterr().err


NUMERIC_OPTIONS = {"--tile-px": "cnn", "--overlap-px": "cnn", "--threads": "cnn", "--ply-step": "cnn",
                   "--window-px": "classical", "--stride-px": "classical", "--candidates": "classical",
                   "--noise-sigma": "classical", "--pool-sigma-px": "classical", "--exact-model-below": "classical",
                   "--weak-texture-below": "classical", "--clipped-planes-per-frame": "classical"}
HOSTILE = ("100000", "1e6", "-10", "0", "nan", "inf")
ACCEPTED = {("--overlap-px", "0"), ("--pool-sigma-px", "0"), ("--ply-step", "100000"), ("--exact-model-below", "0"),
            ("--weak-texture-below", "0"), ("--clipped-planes-per-frame", "0")}
"""Hostile-looking values that are valid: no overlap, no pooling, one point in the point cloud, no window scored
with the exact model, none without its lowest ring, no clipped plane scored."""


@pytest.mark.parametrize("option", NUMERIC_OPTIONS)
def test_every_numeric_option_refuses_huge_negative_zero_nan_and_inf_in_one_line_naming_it(option, dng, tmp_path,
                                                                                           capsys, no_decode):
    """--window-px 100000 allocated 23.5 GB and was OOM-killed; --stride-px 100000 and --pool-sigma-px 1e6 ended
    in numpy tracebacks; --noise-sigma 1e9 decoded to one depth everywhere. Each is refused before the decode,
    exit 2, its last line naming the option and its value, and nothing is left in --out."""
    for value in HOSTILE:
        if (option, value) in ACCEPTED:
            continue
        out = tmp_path / "out"
        code, err = _infer(capsys, dng, "--out", out, "--decoder", NUMERIC_OPTIONS[option], option, value)
        last = err.strip().splitlines()[-1] if err.strip() else ""
        assert code == 2 and option in last and "Traceback" not in err, (option, value, err)
        assert not out.exists(), (option, value)


def test_a_tile_size_that_is_not_a_multiple_of_4_is_an_option_error(dng, tmp_path, capsys, no_decode):
    """--tile-px 90 was refused by the network's tiling after the frame was read, exit 1; it is a usage error."""
    code, err = _infer(capsys, dng, "--out", tmp_path / "out", "--decoder", "cnn", "--tile-px", "90")
    assert code == 2 and "argument --tile-px: 90 is outside [4, inf), a multiple of 4" in err, err
    assert not (tmp_path / "out").exists()


def test_a_texture_exponent_is_refused_by_a_decoder_whose_network_holds_its_own_and_an_unknown_one_by_name(
        dng, tmp_path, capsys, no_decode):
    out = tmp_path / "out"
    for decoder in ("learned", "cnn"):
        code, err = _infer(capsys, dng, "--out", out, "--decoder", decoder, "--texture-exponent", "profiled")
        assert code == 2 and "--texture-exponent profiled: the " in err and "classical, evidence decoders take it" in err, err
        assert "Traceback" not in err and not out.exists()
    code, err = _infer(capsys, dng, "--out", out, "--decoder", "classical", "--pool-sigma-px", "0",
                       "--texture-exponent", "profiled")  # it profiles each pool's exponent: no pools, no profile
    assert code == 2 and "--texture-exponent profiled" in err and "--pool-sigma-px" in err and not out.exists(), err
    for value in ("natural", "", "nan"):
        code, err = _infer(capsys, dng, "--out", out, "--texture-exponent", value)
        assert code == 2 and "--texture-exponent" in err and "Traceback" not in err, err
        assert not out.exists()


def test_a_memory_refusal_names_the_option_its_value_the_estimate_and_the_limit(dng, tmp_path, capsys, no_decode):
    for option in ("--window-px", "--stride-px", "--pool-sigma-px"):
        code, err = _infer(capsys, dng, "--out", tmp_path / "o", "--decoder", "classical", option, "100000")
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"{option} 100000" in err and "GiB, more than the" in err and "GiB limit" in err, err


def test_the_memory_estimate_refuses_no_default_decode_and_follows_each_option(monkeypatch):
    from dataclasses import replace

    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.memory_budget import MemoryBudgetError
    from bmi_sdk.runtime.classical import check_classical_memory, classical_peak_bytes

    default = ClassicalConfig()
    check_classical_memory(default, 4500, 6000)  # a full frame with the defaults
    for name, bigger in (("window_px", 128), ("stride_px", 4), ("candidates", 96), ("pool_sigma_px", 200.0)):
        grown = replace(default, **{name: bigger})
        assert classical_peak_bytes(grown, 4500, 6000) > classical_peak_bytes(default, 4500, 6000), name
    with pytest.raises(MemoryBudgetError, match=r"--window-px 100000 needs about") as caught:
        check_classical_memory(replace(default, window_px=100000))  # before the decoder allocates its taper
    assert caught.value.option == "--window-px"
    # the profiled texture exponent holds each slope's curves and their pooled stack as well: counted, and a stride
    # the prior's curves fit in is refused for it on a full frame
    from bmi_sdk.decode.classical import with_texture_exponent

    monkeypatch.setenv("BMI_MAX_MEMORY_MB", "4096")  # the default cap, whatever this machine has free
    profiled = with_texture_exponent(default, "profiled")
    assert classical_peak_bytes(profiled, 4500, 6000) > classical_peak_bytes(default, 4500, 6000)
    check_classical_memory(profiled, 4500, 6000)
    check_classical_memory(replace(default, stride_px=4), 4500, 6000)
    with pytest.raises(MemoryBudgetError, match=r"--stride-px 4 needs about"):
        check_classical_memory(replace(profiled, stride_px=4), 4500, 6000)


def test_overlap_is_reported_as_given(capsys, dng, tmp_path):
    """--overlap-px -10 was reported as -8 (rounded up to the model's step first)."""
    from bmi_sdk.runtime.tiling import TilePlan

    with pytest.raises(ValueError, match="got -10"):
        TilePlan.for_model(64, 96, 64, 20, step_px=4, overlap_px=-10)
    with pytest.raises(ValueError, match="overlap of 62 px"):
        TilePlan.for_model(64, 96, 64, 20, step_px=4, overlap_px=62)
    code, err = _infer(capsys, dng, "--out", tmp_path / "o", "--overlap-px", "-10")
    assert code == 2 and "--overlap-px: -10 is outside" in err


def test_noise_sigma_beyond_half_the_range_is_refused_in_the_api_too():
    from bmi_sdk.decode import ClassicalConfig

    with pytest.raises(ValueError, match=r"noise_sigma must lie in \(0, 0.5\].*got 1000000000.0"):
        ClassicalConfig(noise_sigma=1e9)
    ClassicalConfig(noise_sigma=0.5)


def _files(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_a_second_run_into_a_folder_being_written_is_refused_not_silently_replaced(passthrough_model, dng, tmp_path,
                                                                                   capsys):
    """Two `bmi infer … --out SAME` started together both exited 0 and the first set was replaced. A run holds
    the folder's lock until its set is in place; another run into it is refused, naming the holder."""
    from bmi_sdk.runtime import run_job
    from bmi_sdk.runtime.output_set import OutputFolderBusyError, OutputSet

    out = tmp_path / "out"
    with OutputSet(out) as first:
        with pytest.raises(OutputFolderBusyError, match=r"being written by another run \(process \d+\)"):
            run_job(dng, out, model_path=passthrough_model, tile_px=64, threads=1, overwrite=True)
        code, err = _infer(capsys, dng, "--out", out, "--model", passthrough_model, "--tile-px", 64, "--overwrite")
        assert code == 1 and "being written by another run" in err and len(err.strip().splitlines()) == 1, err
        assert sorted(p.name for p in out.iterdir()) == sorted([first.staging.name, ".bmi-infer.lock"])
    assert not out.exists()  # the first run made the folder and wrote nothing: none is left, lock file included


def test_a_killed_run_s_lock_is_taken_over_and_its_staging_folder_removed_with_a_warning(passthrough_model, dng,
                                                                                        tmp_path):
    """A run killed by SIGKILL or the OOM killer left a `.bmi-infer-*` folder that no later run removed."""
    import subprocess
    import sys
    import warnings

    from bmi_sdk.runtime import run_job
    from bmi_sdk.runtime.output_set import LeftoverStagingWarning, OutputFolderBusyError

    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\n"
                               "from bmi_sdk.runtime.output_set import OutputSet\n"
                               "s = OutputSet(sys.argv[1]).__enter__()\n"
                               "(s.staging / 'aif.npy').write_bytes(b'half')\n"
                               "print(s.staging.name, flush=True)\n"
                               "time.sleep(600)\n", str(out)], stdout=subprocess.PIPE, text=True)
    try:
        staging = holder.stdout.readline().strip()
        assert staging.startswith(".bmi-infer-")
        with pytest.raises(OutputFolderBusyError, match=f"process {holder.pid}"):
            run_job(dng, out, model_path=passthrough_model, tile_px=64, threads=1)
    finally:
        holder.kill()
        holder.wait()
    assert (out / staging).is_dir() and (out / ".bmi-infer.lock").is_file()  # what a SIGKILL leaves
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _, report = run_job(dng, out, model_path=passthrough_model, tile_px=64, threads=1)
    assert any(issubclass(w.category, LeftoverStagingWarning) and staging in str(w.message) for w in caught)
    assert report["removed_staging"] == [staging]
    assert not any(p.name.startswith(".bmi-infer") for p in out.iterdir())  # no staging folder, no lock file


def test_write_frame_outputs_refuses_an_earlier_run_s_folder_unless_overwrite_and_then_replaces_the_set(
        passthrough_model, dng, tmp_path):
    """The Python API wrote into an earlier run's folder file by file: a cnn depth.npy beside a classical
    depth_sigma.npy, with a report saying classical."""
    import json

    import numpy as np

    from bmi_sdk.runtime import Model, infer_frame, run_job, write_frame_outputs
    from devices import load_raw

    out = tmp_path / "out"
    decoded, _ = run_job(dng, out, decoder="classical", threads=1)
    assert (out / "depth_sigma.npy").is_file()
    before = _files(out)
    frame = load_raw(dng)
    result = infer_frame(Model(passthrough_model, tile_px=64, threads=1), frame)
    with pytest.raises(FileExistsError, match="earlier run's results.*overwrite=True"):
        write_frame_outputs(out, result, frame)
    assert _files(out) == before
    written = write_frame_outputs(out, result, frame, overwrite=True)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(written["files"]) and "depth_sigma.npy" not in names and "report.json" not in names
    assert np.array_equal(np.load(out / "depth.npy"), result.depth_m, equal_nan=True)
    assert json.loads(json.dumps(written["files"]))["depth.npy"] == str(out / "depth.npy")


SIDECAR_EDITS = {
    "exposure_us": lambda meta: meta.update(exposure_us=float("nan")),
    "analog_gain": lambda meta: meta.update(analog_gain=-1.0),
    "SHA-256": lambda meta: meta["lens"].update(sha256="0" * 64),
    "calibration cal-0123456789ab": lambda meta: meta.update(calibration_id="cal-0123456789ab"),
}


@pytest.mark.parametrize("named", SIDECAR_EDITS)
def test_a_sidecar_that_cannot_be_true_is_warned_about_on_stderr_and_in_the_report(named, passthrough_model, dng,
                                                                                    tmp_path, capsys):
    """A sidecar edited to hold exposure NaN, gain -1, a zeroed lens hash or an unknown calibration id was decoded
    without a word, with nominal PSFs."""
    import json
    import shutil

    edited = tmp_path / "edited.dng"
    shutil.copy(dng, edited)
    meta = json.loads(dng.with_suffix(".json").read_text())
    SIDECAR_EDITS[named](meta)
    edited.with_suffix(".json").write_text(json.dumps(meta))
    code, err = _infer(capsys, edited, "--out", tmp_path / "o", "--model", passthrough_model, "--tile-px", 64,
                       "--threads", 1)
    assert code == 0 and "warning:" in err and named in err, err
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert any(named in w for w in report["frame_quality"]["warnings"]), report["frame_quality"]


def test_a_sidecar_whose_shape_is_not_the_dng_s_is_refused(dng, tmp_path, capsys):
    import json
    import shutil

    edited = tmp_path / "edited.dng"
    shutil.copy(dng, edited)
    meta = json.loads(dng.with_suffix(".json").read_text())
    meta["shape"] = [32, 96]
    edited.with_suffix(".json").write_text(json.dumps(meta))
    code, err = _infer(capsys, edited, "--out", tmp_path / "o", "--decoder", "classical")
    assert code == 1 and "sidecar shape [32, 96]" in err and not (tmp_path / "o").exists(), err


def test_infer_frame_takes_a_dng_path_and_names_what_it_takes_otherwise(passthrough_model, dng):
    """infer_frame(model, "x.dng") raised AttributeError."""
    import numpy as np

    from bmi_sdk.runtime import Model, infer_frame
    from devices import load_raw

    model = Model(passthrough_model, tile_px=64, threads=1)
    by_path = infer_frame(model, str(dng))
    assert np.array_equal(by_path.depth_m, infer_frame(model, load_raw(dng)).depth_m, equal_nan=True)
    with pytest.raises(TypeError, match=r"devices.RawFrame .*devices.load_raw\(PATH\)"):
        infer_frame(model, np.zeros((64, 96)))


def test_the_summary_speaks_a_user_s_language_and_the_report_keeps_the_internals(dng, tmp_path, capsys):
    """bmi infer printed hashes, block counts and candidate evaluations; it says what was decoded, how long it took,
    the depth range, how much of it is confident and where the files are. Internals go to -v and report.json."""
    import json
    import re

    import numpy as np

    out = tmp_path / "o"
    code = main(["infer", str(dng), "--out", str(out), "--decoder", "classical", "--quiet"])
    printed = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    depth, sigma = np.load(out / "depth.npy"), np.load(out / "depth_sigma.npy")
    ok = np.isfinite(depth)
    assert report["confident_coverage"] == pytest.approx(np.mean(sigma[ok] <= 0.1 * depth[ok]))
    assert report["depth_range_m"] == pytest.approx(np.percentile(depth[ok], [1, 99]), abs=1e-4)
    assert code == 0 and "decoded with the classical decoder" in printed and " s\n" in printed
    assert f"of the frame; confident (1σ ≤ 10% of the depth) on {report['confident_coverage']:.0%}" in printed
    assert f"wrote {out}/:" in printed and "report.json" in printed
    assert not re.search(r"[0-9a-f]{12}…", printed) and "blocks run" not in printed  # no hashes or internals
    main(["-v", "infer", str(dng), "--out", str(tmp_path / "v"), "--decoder", "classical", "--quiet"])
    assert re.search(r"bmi infer: info: camera [0-9a-f]{12}…", capsys.readouterr().err)
