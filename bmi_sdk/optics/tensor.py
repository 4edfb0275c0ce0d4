"""The PSF tensor PSF(c, θ, d): lazily built, cached on disk, saved as npz + JSON.

Layout: ``psf[c, i_theta, i_depth, row, col]`` float32 (float16 at rest as an
option), rows sagittal, columns radial with +col pointing away from the
optical centre; each kernel odd-sized, centred on the chief ray, unit sum per
channel. Default grid (paper §3.3): θ 0–60° every 0.6° (101), d 0.7–10 m
every 0.1 m (94), 3 channels at 656.3 / 587.6 / 486.1 nm.

Only the entries a request touches are computed (:meth:`PsfTensor.ensure`);
computed entries go to a disk cache keyed by the lens's optical hash, the
hardware errors of the built lens (``optics.perturb``; none for the design)
and every setting that changes a kernel, one shard per field angle, written
atomically.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..io_atomic import atomic_path, write_json
from ..json_files import read_json_object
from ..parallel import map_jobs
from . import spectral
from .cache_store import mark_used
from .prescription import Lens, load_lens
from .psf import DEFAULT_GUARD, DEFAULT_OVERSAMPLE, psf_from_pupil
from .pupil import fit_pupils

SCHEMA = "bmi-psf-tensor/1"
DEFAULT_KERNEL_PX = 41
ENERGY_CRITERION = 0.99
BATCH_ENTRIES = 600


def default_field_deg() -> tuple:
    return tuple(np.round(np.arange(0, 101) * 0.6, 6).tolist())


def default_depth_m() -> tuple:
    return tuple(np.round(0.7 + np.arange(0, 94) * 0.1, 6).tolist())


@dataclass(frozen=True)
class TensorSpec:
    """Everything besides the lens that changes the kernels."""

    field_deg: tuple = field(default_factory=default_field_deg)
    depth_m: tuple = field(default_factory=default_depth_m)
    channels: tuple = field(default_factory=lambda: tuple(tuple(c) for c in spectral.representative()))
    kernel_px: int = DEFAULT_KERNEL_PX
    pitch_um: float = 2.0
    oversample: int = DEFAULT_OVERSAMPLE
    guard: float = DEFAULT_GUARD
    fit_grid: int = 20
    fit_degree: int = 10

    def __post_init__(self):
        if self.kernel_px % 2 == 0 or self.kernel_px < 1:
            raise ValueError(f"kernel_px must be odd, got {self.kernel_px}")
        if any(not (d > 0) for d in self.depth_m):
            raise ValueError("depths must be > 0 m (math.inf allowed)")
        if any(not (0 <= t <= 90) for t in self.field_deg):
            raise ValueError("field angles must lie in [0, 90] degrees")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["depth_m"] = [None if math.isinf(x) else x for x in self.depth_m]
        d["channels"] = [[list(p) for p in c] for c in self.channels]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TensorSpec":
        d = dict(d)
        d["field_deg"] = tuple(d["field_deg"])
        d["depth_m"] = tuple(math.inf if x is None else x for x in d["depth_m"])
        d["channels"] = tuple(tuple(tuple(p) for p in c) for c in d["channels"])
        return cls(**d)

    def cache_key(self, lens: Lens, perturbation=None) -> str:
        """Identity of the kernels this spec makes for ``lens`` (built with ``perturbation``, None: the design)."""
        identity = {"lens": lens.sha256(), "spec": self.to_dict(), "schema": SCHEMA}
        if perturbation is not None:
            identity["perturbation"] = perturbation.to_dict()
        text = json.dumps(identity, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:20]


def compute_kernels(lens: Lens, spec: TensorSpec, field_deg, depth_m, perturbation=None) -> np.ndarray:
    """Kernels (C, n, K, K) for n (θ, d) pairs, batched through the exact pupil trace.

    ``perturbation`` (an ``optics.perturb.Perturbation``; None is the design): the kernels of
    that built lens along the meridian φ = 0 instead (``perturb.perturbed_kernels``).
    """
    field_deg = np.atleast_1d(np.asarray(field_deg, dtype=np.float64))
    depth_m = np.atleast_1d(np.asarray(depth_m, dtype=np.float64))
    if perturbation is not None:
        from .perturb import perturbed_kernels

        return perturbed_kernels(lens, spec, perturbation, field_deg, depth_m)
    lam_nm = spectral.wavelengths_nm(spec.channels)
    pairs = [(i, lam) for i in range(len(field_deg)) for lam in lam_nm]
    mono = {lam: np.empty((len(field_deg), spec.kernel_px, spec.kernel_px)) for lam in lam_nm}
    for start in range(0, len(pairs), BATCH_ENTRIES):
        chunk = pairs[start:start + BATCH_ENTRIES]
        idx = np.array([i for i, _ in chunk])
        lam = np.array([lam for _, lam in chunk]) * 1e-3
        fits = fit_pupils(lens, field_deg[idx], depth_m[idx], lam, grid=spec.fit_grid, degree=spec.fit_degree)
        for (i, lam_i), fit in zip(chunk, fits):
            mono[lam_i][i] = psf_from_pupil(fit, spec.kernel_px, spec.pitch_um, spec.oversample, spec.guard).kernel
    return spectral.channel_kernels(mono, spec.channels).astype(np.float32)


class PsfCacheWarning(UserWarning):
    """A cached PSF shard failed its checks and is being recomputed."""


def arrays_digest(arrays: list[np.ndarray]) -> str:
    """SHA-256 of arrays' shapes and bytes, in order: what a cache shard records when it is written and is checked
    against when it is read (the caller fixes each array's dtype)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(repr(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def read_npz_arrays(path: Path) -> dict[str, np.ndarray]:
    """{name: array} of an npz file, or ``ValueError`` "unreadable: …" (zip CRCs catch truncation and bit flips)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile, zlib and numpy raise many types for a damaged file
        raise ValueError(f"unreadable: {type(exc).__name__}: {exc}") from None


def _shard_digest(psf: np.ndarray, filled: np.ndarray, depth_index: np.ndarray | None = None) -> str:
    """SHA-256 of a shard's arrays (shape, dtype and bytes), recorded in the shard when it is written."""
    arrays = [np.ascontiguousarray(psf, dtype="<f4"), np.ascontiguousarray(filled, dtype=bool)]
    if depth_index is not None:
        arrays.append(np.ascontiguousarray(depth_index, dtype="<i8"))
    return arrays_digest(arrays)


def read_kernel_shard(path: Path, psf_shape: tuple,
                      sparse: bool = False) -> tuple[np.ndarray, np.ndarray, bool, np.ndarray | None]:
    """(psf, filled, legacy, depth_index) of a cache shard (kernels (C, n, K, K), filled (C, n)), or ``ValueError``
    saying what is wrong with it.

    ``sparse``: the shard holds only some of the grid's ``psf_shape[1]`` depths, ``depth_index`` naming each
    kernel column's (``write_kernel_shard(depth_index=...)``); otherwise it holds every depth of the grid
    (``depth_index`` None).

    Checks: a readable npz (zip CRCs catch truncation and bit flips), the
    expected arrays and shapes, the SHA-256 recorded at write time (``legacy``:
    none recorded, from before it was), and that every filled kernel is finite
    with unit sum: a shard that would decode to NaN or to an all-zero frame is
    never used.
    """
    arrays = read_npz_arrays(path)
    needed = {"psf", "filled"} | ({"depth_index", "sha256"} if sparse else set())
    if not needed <= set(arrays):
        raise ValueError(f"arrays {sorted(arrays)}, expected {sorted(needed)}")
    psf, filled = arrays["psf"], arrays["filled"]
    depth_index = arrays["depth_index"] if sparse else None
    expected = (psf_shape[0], psf.shape[1] if sparse else psf_shape[1]) + tuple(psf_shape[2:])
    if psf.shape != expected or filled.shape != expected[:2] or filled.dtype != bool:
        raise ValueError(f"psf {psf.shape}, filled {filled.shape} {filled.dtype}; expected {psf_shape}")
    if sparse and (depth_index.shape != psf.shape[1:2] or depth_index.dtype.kind != "i"
                   or len(set(depth_index.tolist())) != len(depth_index) or np.any(depth_index < 0)
                   or np.any(depth_index >= psf_shape[1])):
        raise ValueError(f"depth_index {depth_index.dtype} {depth_index.shape} does not name distinct depths of the "
                         f"grid's {psf_shape[1]}")
    legacy = "sha256" not in arrays
    if not legacy and str(arrays["sha256"]) != _shard_digest(psf, filled, depth_index):
        raise ValueError("content does not match the SHA-256 recorded when it was written")
    kernels = psf[filled].astype(np.float64)
    if not np.isfinite(kernels).all():
        raise ValueError("non-finite kernel values")
    sums = kernels.sum(axis=(-2, -1))
    if kernels.size and not np.allclose(sums, 1.0, atol=1e-3):
        raise ValueError(f"kernel sums {sums.min():.4g}..{sums.max():.4g}, expected 1")
    return psf, filled, legacy, depth_index


def usable_kernel_shard(path: Path, psf_shape: tuple, stacklevel: int = 2, sparse: bool = False):
    """``read_kernel_shard``'s (psf, filled, legacy, depth_index), or None: when there is no shard, and when it
    fails its checks.

    A failing shard (truncated, edited, non-finite, another shape) is never used: a ``PsfCacheWarning``
    names it (``stacklevel`` counts from the caller), and its entries are recomputed and written again. A shard
    read marks its folder used (``cache_store.mark_used``).
    """
    if not path.exists():
        return None
    try:
        shard = read_kernel_shard(path, psf_shape, sparse)
    except ValueError as exc:
        if not path.exists():  # pruned meanwhile (``cache_store``): as if it had never been there
            return None
        warnings.warn(f"PSF cache shard {path} is unusable ({exc}); recomputing it", PsfCacheWarning,
                      stacklevel=stacklevel + 1)
        return None
    mark_used(path.parent)
    return shard


def write_kernel_shard(path: Path, psf: np.ndarray, filled: np.ndarray, depth_index: np.ndarray | None = None) -> None:
    """Write a cache shard atomically, with the SHA-256 ``read_kernel_shard`` checks; ``depth_index``: a sparse
    shard's depth of each kernel column."""
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = {} if depth_index is None else {"depth_index": np.asarray(depth_index, dtype=np.int64)}
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, psf=psf, filled=filled, sha256=np.array(_shard_digest(psf, filled, depth_index)), **extra)
    mark_used(path.parent)


def _field_kernels(_state, job) -> np.ndarray:
    """``parallel.map_jobs``'s job: ``compute_kernels(lens, spec, field_deg, depth_m, perturbation)`` of one field."""
    return compute_kernels(*job)


def default_cache_dir() -> Path:
    return Path(os.environ.get("BMI_CACHE_DIR", Path.home() / ".cache" / "bmi_sdk")) / "psf"


class PsfTensor:
    """A lazily filled PSF tensor of one lens as built, on one spec (see module doc).

    It holds only kernels it can reproduce: those of ``lens`` with the hardware errors
    ``perturbation`` (``optics.perturb.Perturbation``; None or all zero is the design), traced
    on demand and cached on disk under ``key``, which covers all three. A perturbed tensor
    holds the built lens's kernels along the meridian φ = 0, each centred where the design's
    chief ray lands (``perturb.perturbed_kernels``); an exact-mode ``render.PsfMap`` over it
    traces the same errors at every (θ, φ). Kernels that come from elsewhere (a synthetic
    test kernel) enter through :meth:`from_kernels`: keyed by their content, never
    computed, and refused by exact mode.
    """

    def __init__(self, lens: Lens | str = "bmi_monocentric", spec: TensorSpec | None = None,
                 cache_dir: str | os.PathLike | None = None, use_cache: bool = True, perturbation=None):
        self.lens = load_lens(lens) if isinstance(lens, str) else lens
        self.spec = spec or TensorSpec()
        self.perturbation = None if perturbation is None or perturbation.is_design else perturbation
        self.key = self.spec.cache_key(self.lens, self.perturbation)
        shape = (len(self.spec.channels), len(self.spec.field_deg), len(self.spec.depth_m))
        self.data = np.zeros(shape + (self.spec.kernel_px,) * 2, dtype=np.float32)
        self.filled = np.zeros(shape, dtype=bool)
        self.reproducible = True
        self.cache_dir = None
        if use_cache:
            root = Path(cache_dir) if cache_dir is not None else default_cache_dir()
            self.cache_dir = root / self.key
        self._shards_loaded: set[int] = set()

    @classmethod
    def from_kernels(cls, lens: Lens | str, spec: TensorSpec, psf: np.ndarray) -> "PsfTensor":
        """A complete tensor of given kernels (C, n_θ, n_d, K, K), unit sum each; keyed by their content.

        For kernels the optics did not make (an analytic test kernel): the tensor cannot
        compute or trace them, so it is never cached and ``PsfMap`` refuses it in exact mode.
        """
        tensor = cls(lens, spec, use_cache=False)
        psf = np.asarray(psf, dtype=np.float32)
        if psf.shape != tensor.data.shape:
            raise ValueError(f"kernels of shape {psf.shape}, the spec needs {tensor.data.shape}")
        sums = psf.astype(np.float64).sum(axis=(-2, -1))
        if not (np.isfinite(psf).all() and np.allclose(sums, 1.0, atol=1e-4)):
            raise ValueError("given kernels must be finite with unit sum each")
        tensor.data[...] = psf
        tensor.filled[...] = True
        tensor.reproducible = False
        tensor.key = "given-" + hashlib.sha256(np.ascontiguousarray(psf).tobytes()).hexdigest()[:14]
        return tensor

    # -- access -------------------------------------------------------------
    @property
    def field_deg(self) -> np.ndarray:
        return np.asarray(self.spec.field_deg)

    @property
    def depth_m(self) -> np.ndarray:
        return np.asarray(self.spec.depth_m)

    def kernel(self, channel: int, field_index: int, depth_index: int) -> np.ndarray:
        self.ensure([field_index], [depth_index])
        return self.data[channel, field_index, depth_index]

    def ensure(self, field_indices, depth_indices) -> int:
        """Make every (θ, d) in the outer product available; returns how many were computed."""
        fi = np.unique(np.atleast_1d(np.asarray(field_indices, dtype=int)))
        di = np.unique(np.atleast_1d(np.asarray(depth_indices, dtype=int)))
        for i in fi:
            self._load_shard(int(i))
        missing = [(i, j) for i in fi for j in di if not self.filled[:, i, j].all()]
        if not missing:
            return 0
        theta = self.field_deg[[i for i, _ in missing]]
        depth = self.depth_m[[j for _, j in missing]]
        if not self.reproducible:
            raise ValueError(f"tensor {self.key} holds given kernels only; entries {missing[:3]} cannot be computed")
        kernels = compute_kernels(self.lens, self.spec, theta, depth, self.perturbation)
        for n, (i, j) in enumerate(missing):
            self.data[:, i, j] = kernels[:, n]
            self.filled[:, i, j] = True
        for i in sorted({i for i, _ in missing}):
            self._store_shard(int(i))
        return len(missing)

    def ensure_all(self, progress: bool = False, workers: int | None = None) -> None:
        """Fill every entry (``ensure_fields`` of every field angle)."""
        self.ensure_fields(range(len(self.spec.field_deg)), progress, workers)

    def ensure_fields(self, field_indices, progress: bool = False, workers: int | None = None) -> None:
        """Fill every depth of these field angles, one field angle per task, spread over ``workers`` processes.

        Each process runs numpy single-threaded on its own shard, which uses
        the cores better than BLAS threads on these small transforms.
        """
        fields = sorted({int(i) for i in field_indices})
        for i in fields:
            self._load_shard(i)
        todo = [i for i in fields if not self.filled[:, i].all()]
        if not todo:
            return
        workers = max(1, min(workers or os.cpu_count() or 1, len(todo)))
        depths = np.asarray(self.spec.depth_m)
        jobs = [(self.lens, self.spec, np.full(len(depths), self.spec.field_deg[i]), depths, self.perturbation)
                for i in todo]
        for i, kernels in zip(todo, map_jobs(_field_kernels, jobs, workers, desc="PSF tensor", unit="field",
                                             progress=progress)):
            self.data[:, i] = kernels
            self.filled[:, i] = True
            self._store_shard(i)

    # -- disk cache -----------------------------------------------------------
    def _shard_path(self, i: int) -> Path:
        return self.cache_dir / f"theta_{i:04d}.npz"

    def _load_shard(self, i: int) -> None:
        """Take the cached kernels of field index ``i``, if its shard is usable (``usable_kernel_shard``); the
        entries of a failing one stay unfilled, so ``ensure`` recomputes them and rewrites the shard."""
        if self.cache_dir is None or i in self._shards_loaded:
            return
        self._shards_loaded.add(i)
        expected = (len(self.spec.channels), len(self.spec.depth_m))
        shard = usable_kernel_shard(self._shard_path(i), expected + (self.spec.kernel_px,) * 2, stacklevel=3)
        if shard is None:
            return
        psf, filled, legacy, _ = shard
        self.data[:, i][filled] = psf[filled]
        self.filled[:, i] |= filled
        if legacy:  # written before shards carried a hash: record one now that its values passed the checks
            self._store_shard(i)

    def _store_shard(self, i: int) -> None:
        if self.cache_dir is None:
            return
        write_kernel_shard(self._shard_path(i), self.data[:, i], self.filled[:, i])

    # -- files ----------------------------------------------------------------
    def metadata(self) -> dict:
        return {
            "schema": SCHEMA,
            "layout": "psf[channel, theta_index, depth_index, row (sagittal), col (radial, +col away from centre)]",
            "units": {"field_deg": "degree", "depth_m": "metre (range from the lens centre)", "pitch_um": "micrometre"},
            "lens": {"name": self.lens.name, "sha256": self.lens.sha256(), "prescription": self.lens.to_dict()},
            "spec": self.spec.to_dict(),
            "perturbation": None if self.perturbation is None else self.perturbation.to_dict(),
            "key": self.key,
            "kernels": "traced" if self.reproducible else "given",
            "channel_names": list(spectral.CHANNELS),
            "code_version": __version__,
            "complete": bool(self.filled.all()),
        }

    def save(self, path: str | os.PathLike, float16: bool = False) -> Path:
        """Write ``path`` (.npz: psf, filled) and its JSON metadata beside it, atomically."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        arr = self.data.astype(np.float16) if float16 else self.data
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez(tmp, psf=arr, filled=self.filled)
        meta = self.metadata()
        meta["dtype_at_rest"] = str(arr.dtype)
        meta["npz_sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
        write_json(path.with_suffix(".json"), meta)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "PsfTensor":
        """Read a saved tensor, checking schema and the npz hash recorded in its JSON."""
        path = Path(path)
        meta_path = path.with_suffix(".json")
        if not meta_path.exists():
            raise FileNotFoundError(f"{meta_path}: PSF tensor metadata missing")
        meta = read_json_object(meta_path)
        if meta.get("schema") != SCHEMA:
            raise ValueError(f"{meta_path}: schema {meta.get('schema')!r}, expected {SCHEMA!r}")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != meta.get("npz_sha256"):
            raise ValueError(f"{path}: content hash does not match its metadata (file changed or corrupt)")
        lens = Lens.from_dict(meta["lens"]["prescription"])
        perturbation = None
        if meta.get("perturbation") is not None:
            from .perturb import Perturbation

            perturbation = Perturbation.from_dict(meta["perturbation"])
        spec = TensorSpec.from_dict(meta["spec"])
        with np.load(path, allow_pickle=False) as z:
            psf, filled = z["psf"].astype(np.float32), z["filled"]
        if meta.get("kernels") == "given":
            return cls.from_kernels(lens, spec, psf)
        tensor = cls(lens, spec, use_cache=False, perturbation=perturbation)
        tensor.data[...] = psf
        tensor.filled[...] = filled
        return tensor
