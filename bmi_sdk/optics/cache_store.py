"""What the PSF cache holds, when each part was last used, and pruning it (``bmi psf cache``).

The cache (``$BMI_CACHE_DIR/psf``, ``tensor.default_cache_dir``) grows by one folder per lens tensor, one per camera
(``exact-<key>``: a built lens's or the design's exact kernels, one shard per zone) and, inside a camera's folder, one
per evidence-model kind and model code (``models-<kind>-<key>``, ``decode.model_cache``). Nothing in it expires on its
own: a camera recalibrated, or model code changed by an upgrade, leaves folders that nothing reads again.

Every read or write of a shard marks its folder used (``mark_used``: the modification time of a ``.last-used`` file
in it, at most once an hour per folder and process), so a folder's last use survives a file system mounted without
access times. A folder from before the marker reads the newest modification time of its files.

Pruning removes whole folders, least recently used first. A folder is renamed to a hidden name in the same place
(one atomic step) and then deleted, so a decode running meanwhile finds a shard either whole or absent, and
recomputes what is absent; a prune killed midway leaves a hidden folder that the next prune deletes.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

LAST_USED = ".last-used"
PRUNING_PREFIX = ".pruning-"
MARK_INTERVAL_S = 3600.0  # a folder's marker is touched at most this often by one process

_marked: dict[str, float] = {}
_marked_lock = threading.Lock()


def mark_used(folder: Path) -> None:
    """Record that ``folder``'s shards were used now (the modification time of its ``LAST_USED`` file), at most once
    per ``MARK_INTERVAL_S`` per process. A cache that cannot be written to (read-only) is left as it is."""
    key = str(folder)
    now = time.monotonic()
    with _marked_lock:
        if now - _marked.get(key, -MARK_INTERVAL_S) < MARK_INTERVAL_S:
            return
        _marked[key] = now
    try:
        (Path(folder) / LAST_USED).touch()
    except OSError:
        pass  # a read-only or vanished folder: its last use stays what it was


@dataclass(frozen=True)
class CacheEntry:
    """One folder of the cache: ``kind`` "tensor" (a lens's PSF tensor), "camera" (a camera's exact kernels) or
    "models" (a camera's evidence models of one kind and model code, inside its camera's folder); ``size_bytes`` its
    own files (a camera's without its models folders, each an entry of its own); ``last_used`` seconds since the
    epoch."""

    path: Path
    kind: str
    size_bytes: int
    last_used: float

    def to_dict(self, root: Path) -> dict:
        return {"folder": str(self.path.relative_to(root)), "kind": self.kind, "size_bytes": self.size_bytes,
                "last_used": self.last_used}


def _files(folder: Path) -> list[os.DirEntry]:
    with os.scandir(folder) as it:
        return [e for e in it if e.is_file(follow_symlinks=False)]


def _entry(folder: Path, kind: str) -> CacheEntry:
    files = _files(folder)
    size = sum(e.stat(follow_symlinks=False).st_size for e in files)
    marker = [e for e in files if e.name == LAST_USED]
    stamps = [e.stat(follow_symlinks=False).st_mtime for e in (marker or files)]
    return CacheEntry(folder, kind, size, max(stamps) if stamps else folder.stat().st_mtime)


def cache_entries(root: Path) -> list[CacheEntry]:
    """Every folder of the cache at ``root`` (``CacheEntry``), sorted by path; hidden folders (a prune's leftovers)
    are not entries. An absent root holds none."""
    root = Path(root)
    if not root.is_dir():
        return []
    out = []
    for top in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if top.name.startswith("exact-"):
            out.append(_entry(top, "camera"))
            out.extend(_entry(sub, "models") for sub in sorted(top.iterdir())
                       if sub.is_dir() and sub.name.startswith("models-"))
        else:
            out.append(_entry(top, "tensor"))
    return out


def _remove(folder: Path) -> None:
    """Rename ``folder`` to a hidden name beside it, then delete it (module doc). Already gone: nothing to do."""
    hidden = folder.with_name(f"{PRUNING_PREFIX}{folder.name}-{uuid.uuid4().hex[:8]}")
    try:
        folder.rename(hidden)
    except FileNotFoundError:
        return
    shutil.rmtree(hidden, ignore_errors=True)


def prune(root: Path, older_than_s: float | None = None, max_bytes: int | None = None,
          dry_run: bool = False, now: float | None = None) -> list[CacheEntry]:
    """Remove the cache's folders (``cache_entries``) unused for more than ``older_than_s``, then the least recently
    used until the rest holds at most ``max_bytes``; returns the entries removed (``dry_run``: would remove). A
    camera's folder goes with its models folders, and counts as used when any of them was. Hidden folders a killed
    prune left are deleted too."""
    root = Path(root)
    now = time.time() if now is None else now
    entries = cache_entries(root)
    children = {e.path: [c for c in entries if c.kind == "models" and c.path.parent == e.path]
                for e in entries if e.kind == "camera"}

    def last_use(e: CacheEntry) -> float:
        return max([e.last_used] + [c.last_used for c in children.get(e.path, [])])

    removed: list[CacheEntry] = []
    gone: set[Path] = set()

    def take(e: CacheEntry) -> None:
        for item in [e] + children.get(e.path, []):
            if item.path not in gone:
                gone.add(item.path)
                removed.append(item)

    if older_than_s is not None:
        for e in entries:
            if e.path not in gone and now - last_use(e) > older_than_s:
                take(e)
    if max_bytes is not None:
        total = sum(e.size_bytes for e in entries if e.path not in gone)
        for e in sorted(entries, key=last_use):
            if total <= max_bytes:
                break
            if e.path in gone:
                continue
            before = len(removed)
            take(e)
            total -= sum(item.size_bytes for item in removed[before:])
    if not dry_run:
        for e in removed:
            if e.path.parent not in gone:  # a camera's models go with its folder
                _remove(e.path)
        if root.is_dir():
            for left in root.glob(f"{PRUNING_PREFIX}*"):
                shutil.rmtree(left, ignore_errors=True)
            for left in root.glob(f"exact-*/{PRUNING_PREFIX}*"):
                shutil.rmtree(left, ignore_errors=True)
    return removed
