"""The decoder interface (``runtime.decoders``): a decoder is one registered class, opened once per camera; and the
``--json`` record of ``bmi bench`` / ``bmi eval`` (``bench.record``)."""

import json

import numpy as np
import pytest

from bmi_sdk.bench.record import check_record_path, markdown_tables, write_record
from bmi_sdk.runtime import DECODERS, BuiltCamera, DecodedFrame, open_decoder, run_job
from bmi_sdk.runtime.decoders import decoder_kind


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    from devices import Roi, open_camera

    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    with open_camera("sim://decoders-test?scene=chart&seed=1") as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(path)
    return path


class PlaneDecoder:
    """A decoder that reads every pixel at 2 m: enough to show what adding a decoder takes."""

    kind = "plane"
    title = "plane at 2 m"
    model_kind = None
    takes_config = False
    takes_texture_exponent = False

    def __init__(self, camera, model, config, options):
        self.camera = camera

    def decode(self, frame, progress=False):
        shape = frame.data.shape
        valid = np.ones(shape, bool)
        return DecodedFrame(np.zeros((*shape, 3), np.float32), np.full(shape, 2.0, np.float32), valid,
                            np.full(shape, 0.1, np.float32), {"valid_fraction": 1.0})

    def head(self):
        return {"decoder": self.kind, "calibration_id": self.camera.calibration_id}


def test_a_registered_class_is_a_decoder_every_entry_point_runs(dng, tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="unknown decoder 'plane'"):
        decoder_kind("plane")
    monkeypatch.setitem(DECODERS, "plane", PlaneDecoder)
    _, report = run_job(dng, tmp_path / "job", decoder="plane")
    assert report["decoder"] == "plane" and report["execution_provider"] is None
    assert np.all(np.load(tmp_path / "job" / "depth.npy") == 2.0)
    assert (tmp_path / "job" / "depth_sigma.npy").is_file()  # a decoder with a 1σ gets the σ outputs

    from bmi_sdk.runtime.batch import DecodeOptions, plan_outputs, run_batch

    summaries = run_batch(plan_outputs([dng], tmp_path / "batch"), DecodeOptions(decoder="plane"), progress=False)
    assert summaries[0]["ok"] and summaries[0]["decoder"] == "plane"
    for name in ("depth.npy", "points.ply", "aif.png"):
        assert (tmp_path / "job" / name).read_bytes() == (tmp_path / "batch" / name).read_bytes()


def test_an_opened_decoder_refuses_another_cameras_frame(dng, tmp_path, monkeypatch):
    monkeypatch.setitem(DECODERS, "plane", PlaneDecoder)
    decoder = open_decoder(BuiltCamera(lens_name="fisheye"), "plane")
    with pytest.raises(ValueError, match="opened for camera"):
        run_job(dng, tmp_path / "o", decoder=decoder)
    assert not (tmp_path / "o").exists()


def test_a_decoder_without_a_network_or_options_refuses_them():
    with pytest.raises(ValueError, match="--model names a network"):
        open_decoder(BuiltCamera(), "classical", model="default.onnx")
    with pytest.raises(ValueError, match="takes no classical decoder options"):
        from bmi_sdk.decode import ClassicalConfig

        open_decoder(BuiltCamera(), "cnn", config=ClassicalConfig())


def test_a_benchmark_text_becomes_a_record(tmp_path):
    text = ("### Seams, 512² tiles\n\nThe window run whole and tiled.\n\n| tile px | AiF MAD | note |\n|---|---|---|\n"
            "| 256 | 0.0012 | – |\n| 512 | 3e-05 | whole |\n\nMeasured on one core.\n\n### Cost\n\n| what | s |\n"
            "|---|---|\n| one tile | 0.5 |\n")
    table, cost = markdown_tables(text)
    assert table == {"title": "Seams, 512² tiles", "columns": ["tile px", "AiF MAD", "note"],
                     "rows": [[256, 0.0012, None], [512, 3e-05, "whole"]],
                     "notes": "The window run whole and tiled. Measured on one core."}
    assert cost == {"title": "Cost", "columns": ["what", "s"], "rows": [["one tile", 0.5]], "notes": ""}
    (table,) = markdown_tables(text[:text.index("### Cost")])  # text after the last table joins its notes too
    assert table["notes"] == "The window run whole and tiled. Measured on one core."
    path = write_record(tmp_path / "r" / "bench.json", [table], ["bench", "infer", "--json", "r/bench.json"])
    record = json.loads(path.read_text())
    assert record["command"] == "bmi bench infer --json r/bench.json" and record["tables"] == [table]
    assert set(record["machine"]) == {"platform", "cores", "python", "load_average"}
    assert len(record["date"]) == 10 and (record["commit"] is None or len(record["commit"]) == 40)


def test_an_earlier_record_is_never_replaced_unasked(tmp_path):
    """``--json PATH``: a path that holds a file is refused before the run (``check_record_path``) and at the write
    itself (another run may have written it meanwhile), the earlier file kept byte for byte; ``--overwrite``
    replaces it."""
    table = {"title": "t", "columns": ["a"], "rows": [[1]], "notes": ""}
    path = write_record(tmp_path / "r.json", [table], ["bench", "x"])
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="--overwrite"):
        check_record_path(path, overwrite=False)
    check_record_path(path, overwrite=True)
    check_record_path(tmp_path / "new.json", overwrite=False)
    for not_a_file in ("", tmp_path):
        with pytest.raises(ValueError, match="not a folder"):
            check_record_path(not_a_file, overwrite=True)
    check_record_path(tmp_path / "new" / "deeper" / "r.json", overwrite=False)
    assert (tmp_path / "new" / "deeper").is_dir()  # made before the run, not after its work
    with pytest.raises(ValueError, match="cannot be made"):
        check_record_path(path / "r.json", overwrite=False)  # a file where its folder would be
    with pytest.raises(FileExistsError, match="another run wrote meanwhile"):
        write_record(path, [dict(table, rows=[[2]])], ["bench", "y"])
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new", "r.json"]  # no temporary file left behind
    write_record(path, [dict(table, rows=[[2]])], ["bench", "y"], overwrite=True)
    assert json.loads(path.read_text())["tables"][0]["rows"] == [[2]]


def test_a_record_names_the_revision_its_run_started_from(tmp_path, monkeypatch):
    """A checkout that moves on to another commit during a long run: the record names the revision the run started
    from (``check_record_path`` reads it before the work), not the one the checkout holds at the end."""
    import subprocess

    from bmi_sdk.bench import record

    revisions = iter(["a" * 40, "b" * 40])
    monkeypatch.setattr(record.subprocess, "run",
                        lambda *a, **k: subprocess.CompletedProcess(a, 0, stdout=next(revisions) + "\n"))
    record.commit.cache_clear()
    try:
        path = tmp_path / "r.json"
        check_record_path(path, overwrite=False)
        write_record(path, [{"title": "t", "columns": ["a"], "rows": [[1]], "notes": ""}], ["bench", "x"])
        assert json.loads(path.read_text())["commit"] == "a" * 40
    finally:
        record.commit.cache_clear()


def test_bench_and_eval_refuse_an_earlier_record_before_running(tmp_path, bmi):
    """Run twice into one ``--json`` path: the second run stops at once (no minutes of benchmark lost first) with
    a one-line error naming ``--overwrite``, and the earlier record is untouched."""
    earlier = tmp_path / "r.json"
    earlier.write_text("{}\n")
    for command in (["bench", "evidence"], ["eval", "--decoder", "classical"], ["bench", "device"], ["bench", "infer"],
                    ["bench", "scaleout"]):
        done = bmi(*command, "--json", earlier, check=False)
        assert done.returncode == 1 and "holds an earlier run's record" in done.stderr and "--overwrite" in done.stderr
        assert earlier.read_text() == "{}\n"


def test_bench_frame_times_a_cameras_first_frame_and_its_next_from_an_empty_cache(dng, tmp_path, bmi):
    """``bmi bench frame``: per camera, the first run traces the zone kernels its frame reads into an empty PSF
    cache and the next run reads every one of them back (0 traced); each row has the run's own wall time and peak
    memory. A missing frame or calibration is refused before any run."""
    import json

    record_path = tmp_path / "frame.json"
    bmi("bench", "frame", dng, "--json", record_path)
    (table,) = json.loads(record_path.read_text())["tables"]
    rows = [dict(zip(table["columns"], row)) for row in table["rows"]]
    assert [(r["camera"], r["run"]) for r in rows] == [("design", "first frame"), ("design", "next frame")]
    assert rows[0]["kernel sets traced"] > 0 and rows[1]["kernel sets traced"] == 0
    assert all(r["whole command s"] > 0 and 0.05 < r["peak RSS GB"] < 24 for r in rows)
    for args in (["nosuch.dng"], [dng, "--calibration", tmp_path / "nosuch.json"]):
        done = bmi("bench", "frame", *args, check=False)
        assert done.returncode == 1 and "no such file" in done.stderr
