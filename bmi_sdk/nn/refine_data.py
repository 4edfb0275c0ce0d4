"""Training pairs of the learned refinement: a render cache's pairs, each decoded once by the classical decoder.

The refinement network (``--decoder learned``) reads the classical decoder's channels
(``decode.features``) beside the usual input. Decoding a 144² crop costs 0.2–0.8 s, a training step
~0.3 s, so the decode cannot run per step as the noise draw does for the end-to-end network
(``data.PairCache``). Each cached render is therefore given one raw frame (its own noise σ, drawn
log-uniform over [``sigma_min``, ``sigma_max``] so the network learns how noise changes the evidence)
and decoded once; the raw frame and the channels are stored (npz shards, atomic, resumable) beside the
render cache. Per step: random crop at even offsets (the Bayer phase is kept), demosaic of the stored
raw crop, dihedral augmentation of the RGB, the classical channels, the targets and the field
channels (``data.dihedral_field``).

The decoder reads the kernels the pair was rendered with: the nominal camera's (``psf_mode="tensor"``,
as a nominal render cache is made), or, in a cache of sampled cameras (``CacheSpec.camera_errors``), the
exact kernels of the pair's own camera (its stored errors, centre calibrated, as it was rendered): one
model then learns to read the classical channels of every calibrated camera, which is what ``bmi infer
--calibration`` gives it.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bmi_sdk.io_atomic import write_json
from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.model_io import field_channels, raw_to_rgb, window_cfa
from bmi_sdk.nn.data import PairCache, dihedral, dihedral_field, simulate_raw
from bmi_sdk.parallel import map_jobs
from bmi_sdk.sensor import BLACK_LEVEL_DN, CFA_PATTERN, WHITE_LEVEL_DN, NoiseProfile

REFINE_SCHEMA = "bmi-refine-cache/1"


@dataclass(frozen=True)
class RefineSpec:
    """How the pairs of a render cache are decoded for the refinement: noise range, seed, decoder knobs."""

    sigma_min: float = 0.003
    sigma_max: float = 0.012
    seed: int = 0
    decoder: dict = field(default_factory=dict)  # ClassicalConfig fields that differ from the defaults

    def __post_init__(self):
        if not 0 < self.sigma_min <= self.sigma_max:
            raise ValueError(f"the refinement's noise range needs 0 < sigma_min <= sigma_max, "
                             f"got {self.sigma_min} and {self.sigma_max}")
        self.classical_config()  # unknown or bad decoder knobs fail here, not after hours of decoding

    def classical_config(self, threads: int | None = None):
        from bmi_sdk.decode import ClassicalConfig

        return ClassicalConfig(**{**self.decoder, "slopes": tuple(self.decoder.get("slopes", (2.0,))),
                                  "threads": threads})

    def to_dict(self) -> dict:
        return asdict(self)

    def key(self) -> str:
        """Hash of the spec and of the whole decoder configuration it resolves to, so a changed decoder default
        (e.g. the noise model) gives a new folder instead of reusing pairs decoded the old way."""
        import hashlib

        resolved = {**self.to_dict(), "classical": self.classical_config().to_dict()}
        return hashlib.sha256(json.dumps(resolved, sort_keys=True).encode()).hexdigest()[:12]


def refine_dir(cache_dir: str | Path, spec: RefineSpec) -> Path:
    """Where the decoded pairs of ``cache_dir`` under ``spec`` live."""
    return Path(cache_dir) / f"refine-{spec.key()}"


@dataclass(frozen=True)
class ShardDecoder:
    """What decoding a shard needs besides its files: the classical decoder of ``lens`` under ``spec`` and the
    lens's geometry. Calling it builds them; ``parallel.map_jobs`` does so once per process, so every shard a
    process decodes reuses one decoder (and its memo of zone kernels)."""

    lens: str
    spec: RefineSpec
    threads: int | None = None

    def __call__(self) -> dict:
        from bmi_sdk.decode import ClassicalDecoder
        from bmi_sdk.render import PsfMap

        psf_map = PsfMap(lens_tensor(self.lens), lens_geometry(self.lens), mode="tensor")
        config = self.spec.classical_config(self.threads)
        return {"decoder": ClassicalDecoder.for_psf_map(psf_map, config), "geometry": lens_geometry(self.lens),
                "lens": self.lens, "config": config}


def pair_decoder(decoding: dict, perturbation: np.ndarray | None):
    """The classical decoder of one pair: the shared nominal one, or over the exact kernels (centre calibrated, as
    the pair was rendered) of the camera whose errors ``perturbation`` (``Perturbation.to_vector``) the pair
    stores."""
    if perturbation is None:
        return decoding["decoder"]
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalDecoder
    from bmi_sdk.optics.perturb import Perturbation

    camera = BuiltCamera(decoding["lens"], Perturbation.from_vector(np.asarray(perturbation, np.float64)))
    return ClassicalDecoder.for_psf_map(camera.psf_map(mode="exact", centre_calibrated=True), decoding["config"])


def decode_pair(decoder, geometry, optical: np.ndarray, origin, spec: RefineSpec, index: int) -> dict:
    """One stored pair: the raw frame of cached render ``index`` (its σ drawn with (seed, index)) and the
    classical channels of its decode."""
    from bmi_sdk.decode.features import refinement_features

    rng = np.random.default_rng([spec.seed, 31, index])
    sigma = float(np.exp(rng.uniform(np.log(spec.sigma_min), np.log(spec.sigma_max))))
    row0, col0 = int(origin[0]), int(origin[1])
    raw = simulate_raw(optical.astype(np.float32), sigma, rng, row0, col0)
    result = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, CFA_PATTERN,
                            noise_profile=NoiseProfile.additive(sigma))
    feats = refinement_features(result, decoder.config.stride_px)
    return {"raw": raw, "features": feats.astype(np.float16), "sigma": np.float32(sigma)}


def decode_shard(decoding: dict, job: tuple) -> int:
    """Decode render shard ``job = (cache_dir, spec, shard_file, first_index)`` into the refine folder
    (published once) with ``decoding`` (``ShardDecoder()``); returns the pairs written."""
    from bmi_sdk.scaleout import publish_once

    cache_dir, spec, shard_file, first_index = job
    out = refine_dir(cache_dir, spec) / shard_file
    if out.exists():
        return 0
    with np.load(Path(cache_dir) / shard_file, allow_pickle=False) as z:
        optical, origin = z["optical"], z["origin"]
        cameras = z["perturbation"] if "perturbation" in z.files else [None] * len(optical)
    items = [decode_pair(pair_decoder(decoding, cameras[k]), decoding["geometry"], optical[k], origin[k], spec,
                         first_index + k)
             for k in range(len(optical))]
    arrays = {k: np.stack([it[k] for it in items]) for k in items[0]}
    return len(items) if publish_once(out, lambda tmp: np.savez(tmp, **arrays), suffix=".npz") else 0


def build_refine_cache(cache_dir: str | Path, spec: RefineSpec, workers: int = 1, progress: bool = True) -> Path:
    """Decode every render shard of ``cache_dir`` not yet decoded under ``spec`` (resumable); returns the folder.

    ``workers`` > 1 decodes shards in that many single-threaded processes.
    """
    cache_dir = Path(cache_dir)
    meta = json.loads((cache_dir / "cache.json").read_text())
    lens = meta["spec"]["lens"]
    out = refine_dir(cache_dir, spec)
    out.mkdir(exist_ok=True)
    meta_path = out / "refine.json"
    identity = {"schema": REFINE_SCHEMA, "spec": spec.to_dict(), "renders": meta}
    if meta_path.exists() and json.loads(meta_path.read_text()) != identity:
        raise ValueError(f"{out} holds another refinement cache; remove it")
    write_json(meta_path, identity)
    shards = sorted(p.name for p in cache_dir.glob("shard_*.npz"))
    todo = [s for s in shards if not (out / s).exists()]
    firsts = [int(s.removeprefix("shard_").removesuffix(".npz")) * meta["shard_samples"] for s in todo]
    workers = min(workers, len(todo))  # one shard: decoded here, with the decoder's own threads
    state = ShardDecoder(lens, spec, threads=1 if workers > 1 else None)
    jobs = [(cache_dir, spec, s, f) for s, f in zip(todo, firsts)]
    for _ in map_jobs(decode_shard, jobs, workers, state=state, desc="classical decode of the training pairs",
                      unit="shard", progress=progress):
        pass  # each shard is published by its job
    return out


class RefinePairs:
    """The decoded pairs in memory and the per-step batch assembly (the ``PairCache`` interface)."""

    def __init__(self, cache_dir: str | Path, spec: RefineSpec):
        self.renders = PairCache(cache_dir)
        self.spec = self.renders.spec
        self.geometry = self.renders.geometry
        folder = refine_dir(cache_dir, spec)
        shards = sorted(folder.glob("shard_*.npz"))
        expected = len(sorted(Path(cache_dir).glob("shard_*.npz")))
        if len(shards) != expected:
            raise ValueError(f"{folder}: {len(shards)} of {expected} decoded shards; run build_refine_cache")
        parts: dict = {}
        for path in shards:
            with np.load(path, allow_pickle=False) as z:
                for k in z.files:
                    parts.setdefault(k, []).append(z[k])
        self.arrays = {k: np.concatenate(v) for k, v in parts.items()}
        if len(self.arrays["raw"]) != len(self.renders):
            raise ValueError(f"{folder}: {len(self.arrays['raw'])} decoded pairs for {len(self.renders)} renders")

    @property
    def extra_channels(self) -> int:
        return int(self.arrays["features"].shape[1])

    def __len__(self) -> int:
        return len(self.renders)

    def feature_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-channel mean and standard deviation (float32, std ≥ 1e-3) of the stored classical channels, the
        fixed standardisation the refinement network applies to them."""
        feats = self.arrays["features"]
        mean = np.array([feats[:, c].mean(dtype=np.float64) for c in range(feats.shape[1])])
        sq = np.array([np.square(feats[:, c], dtype=np.float64).mean() for c in range(feats.shape[1])])
        std = np.sqrt(np.maximum(sq - mean ** 2, 1e-6))
        return mean.astype(np.float32), std.astype(np.float32)

    def pair(self, index: int, rng: np.random.Generator, augment: bool = True):
        """(input (6 + C)×S×S, AiF 3×S×S, range 1×S×S, valid 1×S×S) float32 of one decoded pair."""
        spec, r = self.spec, self.renders.arrays
        s, j = spec.crop_px, spec.jitter_px
        dr, dc = (2 * int(rng.integers(0, j + 1)) for _ in range(2)) if augment else (j - j % 2, j - j % 2)
        row0, col0 = int(r["origin"][index, 0]) + dr, int(r["origin"][index, 1]) + dc
        sl = (slice(dr, dr + s), slice(dc, dc + s))
        raw = self.arrays["raw"][index][sl]
        seen = raw_to_rgb(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, window_cfa(CFA_PATTERN, row0, col0))
        feats = self.arrays["features"][index][(slice(None), *sl)].astype(np.float32).transpose(1, 2, 0)
        rgb = r["rgb"][index][sl].astype(np.float32)
        range_m = r["range_m"][index][sl]
        field_ch = field_channels(self.geometry, row0, col0, s, s)
        valid = self.geometry.valid_mask(row0, col0, s, s) & np.isfinite(range_m)
        k = int(rng.integers(8)) if augment else 0
        seen, feats, rgb, range_m, valid = (dihedral(x, k) for x in (seen, feats, rgb, range_m, valid))
        field_ch = dihedral_field(field_ch, k)
        x = np.concatenate([seen.transpose(2, 0, 1), field_ch, feats.transpose(2, 0, 1)])
        return (x, rgb.transpose(2, 0, 1), np.nan_to_num(range_m, nan=1.0)[None], valid[None].astype(np.float32))

    def batch(self, seed: int, step: int, batch_size: int, sigma: float = 0.0, sigma_max: float | None = None):
        """The batch of ``step`` (a pure function of (seed, step)); the noise is the stored one (σ ignored)."""
        rng = np.random.default_rng([seed, step])
        items = [self.pair(int(rng.integers(len(self))), rng) for _ in range(batch_size)]
        return tuple(np.stack(parts) for parts in zip(*items))

