"""The evidence models of a camera's zones kept on disk, beside the kernels they are made from.

A frame's decode scores every window against the evidence model of each candidate depth at its zone
(``kernels.ZoneKernels.models``): the kernels' power, folded onto the Bayer plane and smoothed by the window's
taper. A full frame needs ~430 zones × 28 candidates of them, about 20 s of one core, on every frame, while the
kernels themselves come from the PSF cache in well under a second. This cache keeps the models too, one shard per
zone and model kind (tapered or exact), so a process decoding a camera's second frame reads them instead.

A shard lives in a folder of the kernel cache (``render.PsfMap.exact_cache_dir``, itself named by the kernels'
identity) named by everything else a model depends on: the window, the texture slopes, the model kind and a fingerprint of the model code
(``model_fingerprint``: the models of one fixed test kernel, so a change to how models are made changes the folder
and never reads a stale shard). It holds the depths computed so far (sparse, as the kernel shards do), written
atomically with a SHA-256 of its arrays; a shard failing its checks is never used: a ``PsfCacheWarning`` names it
and its models are recomputed and written again.
"""

from __future__ import annotations

import hashlib
import json
import threading
import warnings
from pathlib import Path

import numpy as np

from ..io_atomic import atomic_path
from ..optics.cache_store import mark_used
from ..optics.tensor import PsfCacheWarning, arrays_digest, read_npz_arrays
from .evidence import expected_periodogram, folded_model


def model_function(exact: bool):
    """The evidence model of a kernel stack: ``expected_periodogram`` (``exact``) or the taper-smoothed
    ``folded_model``."""
    return expected_periodogram if exact else folded_model


def _fingerprint_kernel() -> np.ndarray:
    """A fixed, asymmetric, unit-sum 21 × 21 kernel (a seeded random blob) whose models fingerprint the model code."""
    rng = np.random.default_rng(20261129)
    y, x = np.mgrid[-10:11, -10:11]
    blob = np.exp(-((x - 1.5) ** 2 + (0.7 * (y + 2.0)) ** 2) / 18.0) * (1.0 + 0.3 * rng.random((21, 21)))
    return (blob / blob.sum()).astype(np.float32)


_FINGERPRINTS: dict[tuple, str] = {}
_FINGERPRINT_LOCK = threading.Lock()


def model_fingerprint(n_plane: int, slope: float, exact: bool) -> str:
    """SHA-256 (16 hex digits) of the models ``model_function(exact)`` makes of one fixed kernel at this window and
    slope: two codes that make other models of it have other fingerprints. Computed once per process."""
    key = (int(n_plane), float(slope), bool(exact))
    with _FINGERPRINT_LOCK:
        if key not in _FINGERPRINTS:
            model = model_function(exact)(_fingerprint_kernel(), int(n_plane), float(slope))
            _FINGERPRINTS[key] = hashlib.sha256(np.ascontiguousarray(model, "<f4").tobytes()).hexdigest()[:16]
        return _FINGERPRINTS[key]


def _digest(models: np.ndarray, depth_index: np.ndarray) -> str:
    """SHA-256 of a shard's arrays (shape and bytes), recorded in it when it is written."""
    return arrays_digest([np.ascontiguousarray(models, "<f4"), np.ascontiguousarray(depth_index, "<i8")])


class ModelCache:
    """The on-disk evidence models of one ``PsfMap``'s zones (module doc), for windows of ``window_px`` at ``slopes``.

    ``read(zone, exact)`` gives {depth index: (C, slopes, n, n//2+1) float32 models} of a zone's shard (empty
    without one, or when it fails its checks); ``write(zone, exact, models)`` replaces the shard with those. The
    depth index is the kernel grid's (``Candidates.index``), so decoders with other candidates share shards."""

    def __init__(self, kernel_cache_dir: str | Path, window_px: int, slopes: tuple[float, ...], n_channels: int,
                 depth_count: int):
        self.root = Path(kernel_cache_dir)
        self.n_plane = int(window_px) // 2
        self.slopes = tuple(float(a) for a in slopes)
        self.n_channels = int(n_channels)
        self.depth_count = int(depth_count)
        self.writable = True  # False once a write failed (a read-only or full disk): the models then stay in memory
        self._folders: dict[bool, Path] = {}  # model kind → ``folder``, named once

    def folder(self, exact: bool) -> Path:
        """The folder of this window's, slopes' and model kind's shards, named by what they depend on (once per kind:
        the code's fingerprint costs a model)."""
        exact = bool(exact)
        if exact not in self._folders:
            identity = {"n_plane": self.n_plane, "slopes": self.slopes, "exact": exact,
                        "code": [model_fingerprint(self.n_plane, a, exact) for a in self.slopes]}
            digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:20]
            self._folders[exact] = self.root / f"models-{'exact' if exact else 'tapered'}-{digest}"
        return self._folders[exact]

    def path(self, zone: tuple[float, float], exact: bool) -> Path:
        return self.folder(exact) / f"theta{zone[0]:+010.5f}_phi{zone[1]:+011.5f}.npz"

    def shape(self) -> tuple[int, int, int, int]:
        """(C, slopes, n, n//2+1): one depth's models."""
        return self.n_channels, len(self.slopes), self.n_plane, self.n_plane // 2 + 1

    def read(self, zone: tuple[float, float], exact: bool) -> dict[int, np.ndarray]:
        path = self.path(zone, exact)
        if not path.exists():
            return {}
        try:
            models, depth_index = self._checked(path)
        except ValueError as exc:
            if not path.exists():  # pruned meanwhile (``optics.cache_store``)
                return {}
            warnings.warn(f"evidence model cache shard {path} is unusable ({exc}); recomputing it", PsfCacheWarning,
                          stacklevel=2)
            return {}
        mark_used(path.parent)
        return {int(j): models[n].copy() for n, j in enumerate(depth_index)}  # copies: no view keeps the shard

    def _checked(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        """(models (n, C, slopes, n_plane, m) float32, depth_index (n,)) of a shard, or ``ValueError`` saying what is
        wrong with it: unreadable, other arrays or shapes, a SHA-256 other than the one written, repeated or
        out-of-grid depths, non-finite values."""
        arrays = read_npz_arrays(path)
        if set(arrays) != {"models", "depth_index", "sha256"}:
            raise ValueError(f"arrays {sorted(arrays)}, expected ['depth_index', 'models', 'sha256']")
        models, depth_index = arrays["models"], arrays["depth_index"]
        if models.dtype != np.float32 or models.shape[1:] != self.shape() or depth_index.shape != models.shape[:1]:
            raise ValueError(f"models {models.dtype} {models.shape}, depth_index {depth_index.shape}; expected "
                             f"float32 (n,) + {self.shape()}")
        if depth_index.dtype.kind != "i" or len(set(depth_index.tolist())) != len(depth_index) \
                or np.any(depth_index < 0) or np.any(depth_index >= self.depth_count):
            raise ValueError(f"depth_index does not name distinct depths of the grid's {self.depth_count}")
        if str(arrays["sha256"]) != _digest(models, depth_index):
            raise ValueError("content does not match the SHA-256 recorded when it was written")
        if not np.isfinite(models).all():
            raise ValueError("non-finite model values")
        return models, depth_index

    def write(self, zone: tuple[float, float], exact: bool, models: dict[int, np.ndarray]) -> None:
        """Write the zone's shard atomically with ``models`` ({depth index: one depth's models}, one or more); another process
        writing the same shard at once leaves one of the two whole. A cache it cannot write to (read-only, full) is
        named once in a ``PsfCacheWarning`` and not written again: the decode goes on with the models in memory."""
        if not self.writable:
            return
        held = sorted(models)
        stacked = np.stack([np.asarray(models[j], np.float32) for j in held])
        depth_index = np.asarray(held, np.int64)
        path = self.path(zone, exact)
        try:
            with atomic_path(path, suffix=".npz") as tmp:
                np.savez(tmp, models=stacked, depth_index=depth_index, sha256=np.array(_digest(stacked, depth_index)))
            mark_used(path.parent)
        except OSError as exc:
            self.writable = False
            warnings.warn(f"cannot write the evidence model cache at {path.parent} ({exc}); this decoder keeps its "
                          f"models in memory only", PsfCacheWarning, stacklevel=2)
