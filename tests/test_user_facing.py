"""What a user expects of the SDK (issue 14): a version, traceable reports, execution providers, usable outputs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch import nn

import bmi_sdk
from bmi_sdk.runtime import Model, export_model, run_job


class PassThrough(nn.Module):
    def forward(self, x):
        return x[:, :3] * 1.0, 1.0 + x[:, 3:4]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return export_model(PassThrough(), tmp_path_factory.mktemp("m") / "pass.onnx", preset="test-pass")


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    from devices import Roi, open_camera

    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    with open_camera("sim://user-test?scene=chart&seed=1") as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(path)
    return path


def _bmi(*args):
    return subprocess.run([sys.executable, "-m", "bmi_sdk.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_version_flag_prints_the_sdk_version():
    run = _bmi("--version")
    assert run.returncode == 0 and run.stdout.strip() == f"bmi-sdk {bmi_sdk.__version__}"


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


def test_unavailable_provider_is_refused_naming_the_available_ones(model_path, dng, tmp_path):
    with pytest.raises(ValueError, match="'WarpDrive'.*available: .*CPUExecutionProvider"):
        Model(model_path, tile_px=64, providers="WarpDrive")
    run = _bmi("infer", dng, "--out", tmp_path / "o", "--model", model_path, "--tile-px", 64, "--provider",
               "WarpDrive")
    assert run.returncode == 1 and "available: " in run.stderr and "CPUExecutionProvider" in run.stderr
    assert not (tmp_path / "o").exists()
    run = _bmi("infer", dng, "--out", tmp_path / "o", "--decoder", "classical", "--provider", "cpu")
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


def test_cli_infer_runs_on_the_provider_asked_for(model_path, dng, tmp_path):
    run = _bmi("infer", dng, "--out", tmp_path, "--model", model_path, "--tile-px", 64, "--threads", 1,
               "--provider", "cpu", "--quiet")
    assert run.returncode == 0, run.stderr
    assert json.loads((tmp_path / "report.json").read_text())["execution_provider"] == "CPUExecutionProvider"
