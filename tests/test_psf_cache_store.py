"""The PSF cache's folders, their last use and pruning (``optics.cache_store``, ``bmi psf cache``)."""

import json
import os
import time
import warnings

import numpy as np
import pytest

from bmi_sdk.optics import cache_store
from bmi_sdk.optics.cache_store import LAST_USED, cache_entries, prune
from bmi_sdk.optics.tensor import usable_kernel_shard, write_kernel_shard

DAY_S = 86400.0


@pytest.fixture(autouse=True)
def _forget_marks(monkeypatch):
    """Each test starts as a new process would: no folder marked used yet."""
    monkeypatch.setattr(cache_store, "_marked", {})


def _kernels(n: int = 2) -> tuple[np.ndarray, np.ndarray]:
    psf = np.full((3, n, 5, 5), 1.0 / 25, np.float32)
    return psf, np.ones((3, n), bool)


def _folder(path, size_bytes: int, days_ago: float, now: float, marker: bool = True):
    """A cache folder holding one file of ``size_bytes``, last used ``days_ago`` days before ``now``."""
    path.mkdir(parents=True)
    (path / "shard.npz").write_bytes(b"x" * size_bytes)
    stamp = now - days_ago * DAY_S
    if marker:
        (path / LAST_USED).touch()
        os.utime(path / LAST_USED, (stamp, stamp))
    os.utime(path / "shard.npz", (stamp, stamp))
    return path


def test_reading_and_writing_a_shard_marks_its_folder_used(tmp_path):
    shard = tmp_path / "psf" / "tensor-key" / "theta_0000.npz"
    write_kernel_shard(shard, *_kernels())
    marker = shard.parent / LAST_USED
    assert marker.exists()
    os.utime(marker, (1.0e9, 1.0e9))  # long ago
    cache_store._marked.clear()
    assert usable_kernel_shard(shard, (3, 2, 5, 5)) is not None
    assert marker.stat().st_mtime > time.time() - 60
    [entry] = cache_entries(tmp_path / "psf")
    assert entry.kind == "tensor" and entry.size_bytes == shard.stat().st_size  # the marker is empty


def test_a_folder_is_marked_at_most_once_an_hour_by_one_process(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    cache_store.mark_used(folder)
    os.utime(folder / LAST_USED, (1.0e9, 1.0e9))
    cache_store.mark_used(folder)  # within the hour: not touched again
    assert (folder / LAST_USED).stat().st_mtime == 1.0e9


def test_entries_name_tensors_cameras_and_their_models_and_read_old_folders_by_their_files(tmp_path):
    now = time.time()
    root = tmp_path / "psf"
    _folder(root / "abc", 100, 1.0, now)
    _folder(root / "exact-cam", 200, 2.0, now)
    _folder(root / "exact-cam" / "models-tapered-k1", 50, 3.0, now, marker=False)  # written before the marker
    (root / ".pruning-old-1234").mkdir()  # a killed prune's leftover: not an entry
    entries = {str(e.path.relative_to(root)): e for e in cache_entries(root)}
    assert sorted(entries) == ["abc", "exact-cam", "exact-cam/models-tapered-k1"]
    assert [entries[k].kind for k in sorted(entries)] == ["tensor", "camera", "models"]
    assert entries["exact-cam"].size_bytes == 200  # its models are an entry of their own
    assert entries["exact-cam/models-tapered-k1"].last_used == pytest.approx(now - 3 * DAY_S, abs=1)
    assert cache_entries(tmp_path / "absent") == []


def test_prune_by_age_keeps_a_camera_whose_models_were_used_and_deletes_a_killed_prunes_leftovers(tmp_path):
    now = time.time()
    root = tmp_path / "psf"
    _folder(root / "old-tensor", 100, 40, now)
    _folder(root / "new-tensor", 100, 1, now)
    _folder(root / "exact-cam", 300, 40, now)
    _folder(root / "exact-cam" / "models-exact-old", 30, 50, now)
    _folder(root / "exact-cam" / "models-tapered-new", 20, 2, now)
    _folder(root / "exact-gone", 10, 60, now)
    _folder(root / "exact-gone" / "models-tapered-x", 5, 60, now)
    (root / ".pruning-killed-1").mkdir()
    would = prune(root, older_than_s=30 * DAY_S, dry_run=True, now=now)
    assert (root / "old-tensor").exists() and (root / ".pruning-killed-1").exists()  # a dry run removes nothing
    removed = prune(root, older_than_s=30 * DAY_S, now=now)
    assert [e.path for e in removed] == [e.path for e in would]
    assert sorted(str(e.path.relative_to(root)) for e in removed) == [
        "exact-cam/models-exact-old", "exact-gone", "exact-gone/models-tapered-x", "old-tensor"]
    assert sorted(p.name for p in root.iterdir()) == ["exact-cam", "new-tensor"]
    assert sorted(p.name for p in (root / "exact-cam").iterdir()) == [LAST_USED, "models-tapered-new", "shard.npz"]


def test_prune_to_a_size_removes_the_least_recently_used_first(tmp_path):
    now = time.time()
    root = tmp_path / "psf"
    _folder(root / "a", 100, 5, now)
    _folder(root / "b", 100, 3, now)
    _folder(root / "exact-c", 100, 9, now)
    _folder(root / "exact-c" / "models-tapered-1", 100, 1, now)  # the camera was used a day ago, through its models
    removed = prune(root, max_bytes=250, now=now)
    assert [e.path.name for e in removed] == ["a", "b"]
    assert sum(e.size_bytes for e in cache_entries(root)) == 200
    assert prune(root, max_bytes=200, now=now) == []
    assert [e.path.name for e in prune(root, max_bytes=0, now=now)] == ["exact-c", "models-tapered-1"]
    assert list(root.iterdir()) == []


def test_a_shard_pruned_under_a_reader_reads_as_absent_without_a_warning(tmp_path):
    shard = tmp_path / "psf" / "key" / "theta_0001.npz"
    write_kernel_shard(shard, *_kernels())
    prune(tmp_path / "psf", max_bytes=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert usable_kernel_shard(shard, (3, 2, 5, 5)) is None
    write_kernel_shard(shard, *_kernels())  # the next write makes the folder again
    assert usable_kernel_shard(shard, (3, 2, 5, 5)) is not None


def test_bmi_psf_cache_lists_and_prunes(tmp_path, monkeypatch, capsys, exit_code):
    monkeypatch.setenv("BMI_CACHE_DIR", str(tmp_path))
    now = time.time()
    _folder(tmp_path / "psf" / "old", 2_000_000, 10, now)
    _folder(tmp_path / "psf" / "new", 1_000_000, 0, now)
    assert exit_code(["psf", "cache", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert sorted(e["folder"] for e in listing["entries"]) == ["new", "old"] and listing["size_bytes"] == 3_000_000
    assert exit_code(["psf", "cache", "--prune", "--older-than-days", "5", "--dry-run"]) == 0
    assert "would remove old (tensor, 2.0 MB" in capsys.readouterr().out and (tmp_path / "psf" / "old").exists()
    assert exit_code(["psf", "cache", "--prune", "--max-gb", "0.0015", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [e["folder"] for e in report["removed"]] == ["old"] and [e["folder"] for e in report["entries"]] == ["new"]
    assert not (tmp_path / "psf" / "old").exists()
    for argv, option in ((["--prune"], "--prune"), (["--max-gb", "1"], "--prune"),
                         (["--prune", "--max-gb", "nan"], "--max-gb"), (["--prune", "--older-than-days", "-1"],
                                                                         "--older-than-days"),
                         (["--prune", "--max-gb", "1e30"], "--max-gb")):
        assert exit_code(["psf", "cache", *argv]) == 2
        assert option in capsys.readouterr().err
    assert (tmp_path / "psf" / "new").exists()
