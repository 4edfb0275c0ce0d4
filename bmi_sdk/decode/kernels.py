"""The camera's kernels at the candidate depths, per zone, and the evidence models derived from them.

A zone is a field position (θ, φ) rounded to ``ZONE_STEP_DEG``: kernels change slowly with the
field (``bmi bench render``), and neighbouring tiles of a frame share their zone's kernels. The
kernels come from a ``render.PsfMap``, so the decoder sees exactly what the renderer (or the
calibrated camera: an exact-mode map with the calibration's ``Perturbation``) puts into frames.
Only the candidates a tile asks for are computed.
"""

from __future__ import annotations

import threading

import numpy as np

from .bayer import PLANE_CHANNELS
from .model_cache import ModelCache, model_function

ZONE_STEP_DEG = 0.5


class ZoneKernels:
    """Memoised (C, D, K, K) kernels and folded evidence models for (θ, φ) zones of one ``PsfMap``.

    Safe to share between the decoder's block threads: a zone's kernels and evidence models are made under that
    zone's lock (once), other zones' at the same time (a camera's first frame traces two zones at once on two
    threads: ``PsfMap.kernel_sets`` allows it for distinct field positions), and memoised entries are read
    without a lock. With a ``psf_map`` that keeps its kernels on disk (``exact_cache_dir``), a zone's evidence models
    are read from and written to its ``model_cache.ModelCache``."""

    def __init__(self, psf_map, candidates, slopes: tuple[float, ...], window_px: int):
        if window_px % 2 or window_px < 8:
            raise ValueError(f"window_px must be even and >= 8, got {window_px}")
        self.psf_map = psf_map
        self.candidates = candidates
        self.slopes = tuple(float(a) for a in slopes)
        self.window_px = window_px
        self._kernels: dict[tuple, np.ndarray] = {}
        self._models: dict[tuple, np.ndarray] = {}  # (θ, φ, candidate, exact) → (C, slopes, n, m)
        self.kernel_sets_computed = 0
        self._count_lock = threading.Lock()  # around ``kernel_sets_computed`` and ``models_computed``
        self._zone_locks: dict[tuple, threading.RLock] = {}
        cache_dir = getattr(psf_map, "exact_cache_dir", None)
        self.model_cache = None if cache_dir is None else ModelCache(
            cache_dir, window_px, self.slopes, psf_map.n_channels, len(psf_map.tensor.spec.depth_m))
        self._shards_read: set[tuple] = set()  # (θ, φ, exact) whose model shard was read
        self._foreign: dict[tuple, dict[int, np.ndarray]] = {}  # (θ, φ, exact) → a shard's models of other candidates
        self.models_computed = 0  # (zone, candidate) models made here, not read from memory or disk

    def __getstate__(self) -> dict:
        """Pickled without its locks (a decoder travels to scale-out workers): each copy makes its own."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_count_lock", "_zone_locks")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._count_lock = threading.Lock()
        self._zone_locks = {}

    def _zone_lock(self, zone: tuple) -> threading.RLock:
        """The zone's lock (re-entrant: ``models`` asks ``kernels`` under it); setdefault makes one per zone
        atomically."""
        return self._zone_locks.setdefault(zone, threading.RLock())

    @staticmethod
    def zone(theta_deg: float, phi_deg: float) -> tuple[float, float]:
        """The zone key of a field position: θ and φ rounded to the zone step (φ wrapped to (−180, 180])."""
        step = ZONE_STEP_DEG
        theta = round(float(theta_deg) / step) * step
        phi = round(((float(phi_deg) + 180.0) % 360.0 - 180.0) / step) * step
        return round(theta, 6), round(0.0 if theta == 0 else phi, 6)

    @staticmethod
    def zone_at(geometry, row_px: float, col_px: float) -> tuple[float, float]:
        """The zone of sensor pixel (row, col); beyond the geometry's mapping, the image circle's edge."""
        theta, phi = geometry.field_angles(np.array([row_px]), np.array([col_px]))
        return ZoneKernels.zone(float(np.nan_to_num(theta[0], nan=geometry.max_field_deg)), float(phi[0]))

    @staticmethod
    def field_reads(geometry, rows_px: np.ndarray, cols_px: np.ndarray, centre_zone: tuple[float, float],
                    theta_step_deg: float | None) -> list[tuple[tuple[float, float], np.ndarray, np.ndarray]]:
        """The zones a block's windows are read with, and how much: [(zone, window indices, weights)], the weights of
        each window summing to 1. The windows are centred at the sensor pixels of the grid ``rows_px`` × ``cols_px``
        (row-major, as ``evidence.window_spectra`` orders them).

        ``theta_step_deg`` None: every window reads the block's ``centre_zone``. Otherwise each window reads the two
        zones of a θ grid of that step around its own θ, weighted linearly (at the φ of the block's centre): a
        built camera's kernels can change fast with θ (a sensor-radius error defocuses the field edge by a
        θ-dependent amount; +0.5 % reads a 6.4 m plane 1° off its zone as 5.5 or 7.7 m, ``bmi bench decoder``),
        while a block spans about 2° of field.
        """
        count = len(rows_px) * len(cols_px)
        if theta_step_deg is None:
            return [(centre_zone, np.arange(count), np.ones(count))]
        rows, cols = np.meshgrid(np.asarray(rows_px, float), np.asarray(cols_px, float), indexing="ij")
        theta, _ = geometry.field_angles(rows.ravel(), cols.ravel())
        theta = np.clip(np.nan_to_num(theta, nan=geometry.max_field_deg), 0.0, geometry.max_field_deg)
        lower = np.floor(theta / theta_step_deg)
        frac = theta / theta_step_deg - lower
        reads = []
        for grid in np.unique(np.concatenate([lower, lower + 1])):
            weight = np.where(lower == grid, 1.0 - frac, 0.0) + np.where(lower + 1 == grid, frac, 0.0)
            idx = np.flatnonzero(weight > 1e-9)
            if len(idx):
                zone = ZoneKernels.zone(grid * theta_step_deg, centre_zone[1])
                reads.append((zone, idx, weight[idx]))
        return reads

    def kernels(self, zone: tuple[float, float], which: np.ndarray) -> np.ndarray:
        """(C, len(which), K, K) unit-sum kernels of candidates ``which`` (indices into ``candidates``)."""
        which = np.atleast_1d(np.asarray(which, dtype=int))
        if any(zone + (int(j),) not in self._kernels for j in which):
            with self._zone_lock(zone):  # another thread may have made them meanwhile: look again under the lock
                missing = [int(j) for j in which if zone + (int(j),) not in self._kernels]
                if missing:  # the map's own arrays where it memoises them (exact mode): no second copy
                    sets = self.psf_map.kernel_sets(zone[0], zone[1], self.candidates.index[missing])
                    for j, kernel in zip(missing, sets):
                        self._kernels[zone + (j,)] = kernel
                    with self._count_lock:
                        self.kernel_sets_computed += len(missing)
        return np.stack([self._kernels[zone + (int(j),)] for j in which], axis=1)

    def models(self, zone: tuple[float, float], which: np.ndarray, exact: bool = False) -> np.ndarray:
        """(planes, slopes, len(which), n, n//2+1) model power of each Bayer plane (``evidence``): the taper-smoothed
        ``folded_model``, or with ``exact`` the ``expected_periodogram`` (the mean's removal held as well). From
        memory, else the zone's model shard on disk, else made from the kernels (and the shard written again)."""
        which = np.atleast_1d(np.asarray(which, dtype=int))
        n_plane = self.window_px // 2
        if any(zone + (int(j), exact) not in self._models for j in which):
            with self._zone_lock(zone):
                self._read_models(zone, exact)
                missing = [int(j) for j in which if zone + (int(j), exact) not in self._models]
                if missing:
                    model = model_function(exact)
                    k = self.kernels(zone, np.asarray(missing))                       # (C, m, K, K)
                    per_channel = np.stack([[model(k[c], n_plane, a) for a in self.slopes]
                                            for c in range(k.shape[0])])               # (C, A, m, n, n/2+1)
                    for n, j in enumerate(missing):
                        self._models[zone + (j, exact)] = per_channel[:, :, n].astype(np.float32)
                    with self._count_lock:
                        self.models_computed += len(missing)
                    self._write_models(zone, exact)
        stacked = np.stack([self._models[zone + (int(j), exact)] for j in which], axis=2)  # (C, A, D, n, m)
        return stacked[list(PLANE_CHANNELS)]

    def _read_models(self, zone: tuple[float, float], exact: bool) -> None:
        """Take the zone's model shard from disk (once per zone and kind; under the zone's lock)."""
        if self.model_cache is None or zone + (exact,) in self._shards_read:
            return
        self._shards_read.add(zone + (exact,))
        grid_index = self.candidates.index
        position = {int(g): j for j, g in enumerate(grid_index)}
        foreign = self._foreign.setdefault(zone + (exact,), {})
        for g, model in self.model_cache.read(zone, exact).items():
            if g in position:
                self._models.setdefault(zone + (position[g], exact), model)
            else:  # another decoder's candidate: kept, so that rewriting the shard does not drop it
                foreign[g] = model

    def _write_models(self, zone: tuple[float, float], exact: bool) -> None:
        """Write the zone's model shard with every model of that kind this zone holds (under the zone's lock)."""
        if self.model_cache is None:
            return
        grid_index = self.candidates.index
        held = dict(self._foreign.get(zone + (exact,), {}))
        held.update({int(grid_index[j]): self._models[zone + (j, exact)] for j in range(len(grid_index))
                     if zone + (j, exact) in self._models})
        self.model_cache.write(zone, exact, held)
