"""docs/quickstart.md runs as written: its python blocks, in order, in one namespace, in a temporary folder."""

import re
from pathlib import Path

import numpy as np

QUICKSTART = Path(__file__).resolve().parents[1] / "docs" / "quickstart.md"


def python_blocks(markdown: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", markdown, re.S)


def test_quickstart_code_runs_and_writes_what_it_says(tmp_path, monkeypatch):
    blocks = python_blocks(QUICKSTART.read_text())
    assert len(blocks) >= 4, "the quickstart lost its code"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for i, block in enumerate(blocks):
        exec(compile(block, f"{QUICKSTART.name} block {i + 1}", "exec"), namespace)
    assert isinstance(namespace["meta"], dict) and namespace["meta"]["roi"]["width_px"] == 96
    assert (tmp_path / "frame.dng").is_file() and (tmp_path / "frame.json").is_file()
    for name in ("aif.png", "depth.npy", "depth_z.npy", "depth_preview.png", "points.ply"):
        assert (tmp_path / "out" / name).is_file(), name
    assert np.isfinite(np.load(tmp_path / "out" / "depth.npy")).any()
    assert (tmp_path / "job" / "report.json").is_file()
    assert (tmp_path / "job-classical" / "depth_sigma.npy").is_file()   # the frame's result's 1σ reached the files
