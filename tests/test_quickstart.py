"""docs/quickstart.md runs as written: its python blocks, in order, in one namespace, in a temporary folder; and
run a second time into the same folder, as a reader re-running it does, every block replaces its first run's files."""

import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

QUICKSTART = Path(__file__).resolve().parents[1] / "docs" / "quickstart.md"


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", markdown, re.S)


def run_blocks(blocks: list[str], run: int) -> dict:
    namespace: dict = {}
    for i, block in enumerate(blocks):
        exec(compile(block, f"{QUICKSTART.name} block {i + 1} (run {run})", "exec"), namespace)
    return namespace


def test_quickstart_code_runs_twice_into_one_folder_and_each_run_replaces_the_last(tmp_path, monkeypatch):
    from bmi_sdk.runtime import DEFAULT_DECODER

    blocks = python_blocks(QUICKSTART.read_text())
    assert len(blocks) >= 4, "the quickstart lost its code"
    monkeypatch.chdir(tmp_path)
    run_blocks(blocks, 1)
    second_started_ns = time.time_ns()
    second = run_blocks(blocks, 2)  # the same folder: every block meets its first run's files

    assert isinstance(second["meta"], dict) and second["meta"]["roi"]["width_px"] == 96
    assert second["decoder"].kind == DEFAULT_DECODER  # the page shows the SDK's default decoder
    # every file the page writes is the second run's: none of the first run's is left beside them
    stale = [str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")
             if p.is_file() and p.stat().st_mtime_ns < second_started_ns]
    assert not stale, f"left from the first run: {stale}"
    sidecar = json.loads((tmp_path / "frame.json").read_text())
    assert sidecar["host_timestamp_ns"] == second["frame"].host_timestamp_ns
    assert np.array_equal(np.load(tmp_path / "out" / "depth.npy"), second["decoded"].depth_m, equal_nan=True)

    for name in ("aif.png", "depth.npy", "depth_z.npy", "depth_preview.png", "depth_sigma.npy", "points.ply"):
        assert (tmp_path / "out" / name).is_file(), name
    assert np.isfinite(np.load(tmp_path / "out" / "depth.npy")).any()
    assert json.loads((tmp_path / "job" / "report.json").read_text())["decoder"] == DEFAULT_DECODER
    assert (tmp_path / "job-classical" / "depth_sigma.npy").is_file()   # the frame's result's 1σ reached the files
    assert not list(tmp_path.glob("*/.bmi-infer-*")), "a replaced result set left its staging folder"

    # as the page says: without overwrite=True each writing call refuses the earlier files, and changes nothing
    writers = [i for i, block in enumerate(blocks) if "overwrite=True" in block]
    assert len(writers) >= 3, "a block that writes files lost its overwrite=True"
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}
    for i in writers:
        with pytest.raises(FileExistsError):
            exec(compile(blocks[i].replace(", overwrite=True", ""), f"block {i + 1} without overwrite", "exec"),
                 dict(second))
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()} == before
