"""Training pairs of the evidence decoder: a rendered window, its raw frame, the classical cost volume.

Each pair is drawn from its own seed (``VolumeSpec.seed``, index):

* a procedural scene at a scale log-uniform in [1, ``scene_scale_max``] (objects that much larger than the
  window: ``nn.data.draw_scene``) at a random field position (θ uniform in 0–60°);
* a camera: the design's, or (``camera_errors`` > 0, for a share ``built_share`` of the pairs) one with
  hardware errors drawn from the calibration's error prior (``Perturbation.random``: the errors
  ``bmi calibrate`` fits), rendered and decoded with its own exact kernels (centre calibrated), as
  ``bmi infer --calibration`` decodes a calibrated camera;
* noise σ log-uniform in [``sigma_min``, ``sigma_max``];
* the classical decoder's volume (``decode.volume.volume_inputs``) and the scene's 1/d per window cell
  (``decode.volume.grid_targets``).

Pairs are written in shards (npz, published once under their final name), so a build can stop and resume
and shards can be made on several machines; ``VolumePairs`` reads them back for training.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bmi_sdk.io_atomic import write_json
from bmi_sdk.lenses import DEFAULT_LENS
from bmi_sdk.nn.data import CacheSpec, render_sample, simulate_raw
from bmi_sdk.parallel import map_jobs
from bmi_sdk.sensor import BLACK_LEVEL_DN, CFA_PATTERN, WHITE_LEVEL_DN, NoiseProfile

VOLUME_SCHEMA = "bmi-volume-pairs/1"
SHARD_PAIRS = 4


@dataclass(frozen=True)
class VolumeSpec:
    """What a set of training pairs holds (module doc)."""

    lens: str = DEFAULT_LENS
    pairs: int = 256
    crop_px: int = 256
    seed: int = 0
    scene_scale_max: float = 16.0
    sigma_min: float = 0.002
    sigma_max: float = 0.05
    camera_errors: float = 0.0
    built_share: float = 0.5

    def __post_init__(self):
        if not 0 < self.sigma_min <= self.sigma_max:
            raise ValueError(f"pairs need 0 < sigma_min <= sigma_max, got {self.sigma_min}, {self.sigma_max}")
        if self.pairs < 1:
            raise ValueError(f"pairs must be >= 1, got {self.pairs}")
        if not 1.0 <= self.scene_scale_max < float("inf"):
            raise ValueError(f"scene_scale_max must be a finite number >= 1, got {self.scene_scale_max}")
        if self.crop_px % 16 or self.crop_px < 128:
            raise ValueError(f"crop_px must be a multiple of 16 of at least 128, got {self.crop_px}")
        if not 0.0 <= self.built_share <= 1.0:
            raise ValueError(f"built_share is a fraction in [0, 1], got {self.built_share}")

    def cache_spec(self, built: bool) -> CacheSpec:
        """The render spec of one pair: ``nn.data.render_sample`` draws its window, scene and camera."""
        return CacheSpec(lens=self.lens, samples=self.pairs, crop_px=self.crop_px, jitter_px=0, seed=self.seed,
                         camera_errors=self.camera_errors if built else 0.0, scene_scale_max=self.scene_scale_max)

    def built(self, index: int) -> bool:
        """Whether pair ``index`` goes through a camera with hardware errors."""
        if not self.camera_errors:
            return False
        return bool(np.random.default_rng([self.seed, index, 53]).uniform() < self.built_share)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class PairMaker:
    """Builds, once per process, the design camera's tensor, geometry and classical decoder."""

    spec: VolumeSpec
    threads: int | None = 1

    def __call__(self) -> dict:
        from bmi_sdk.lenses import lens_geometry, lens_tensor
        from bmi_sdk.nn.refine_data import RefineSpec, ShardDecoder

        decoding = ShardDecoder(self.spec.lens, RefineSpec(), threads=self.threads)()
        return {"spec": self.spec, "tensor": lens_tensor(self.spec.lens), "geometry": lens_geometry(self.spec.lens),
                "decoding": decoding}


def make_pair(state: dict, index: int) -> dict:
    """Pair ``index`` (module doc) as arrays: volume (2, D, R, C) f16, guide (4, R, C) f16, target (R, C) f32,
    sigma, theta_deg, built."""
    from bmi_sdk.decode.volume import grid_targets, volume_inputs
    from bmi_sdk.nn.refine_data import pair_decoder

    spec: VolumeSpec = state["spec"]
    built = spec.built(index)
    sample = render_sample(spec.cache_spec(built), index, state["tensor"], state["geometry"])
    decoder = pair_decoder(state["decoding"], sample.get("perturbation"))
    rng = np.random.default_rng([spec.seed, 31, index])
    sigma = float(math.exp(rng.uniform(math.log(spec.sigma_min), math.log(spec.sigma_max))))
    row0, col0 = (int(v) for v in sample["origin"])
    raw = simulate_raw(sample["optical"].astype(np.float32), sigma, rng, row0, col0)
    result = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, state["geometry"], row0, col0, CFA_PATTERN,
                            noise_profile=NoiseProfile.additive(sigma), aif=False)
    volume, guide, valid = volume_inputs(result.grid_pooled, result.grid_curves, result.grid_colour)
    target = grid_targets(sample["range_m"], decoder.config.stride_px, valid.shape)
    target[~valid] = np.nan
    centre = (row0 + spec.crop_px / 2, col0 + spec.crop_px / 2)
    theta = float(np.asarray(state["geometry"].field_angles(np.array([centre[0]]), np.array([centre[1]]))[0])[0])
    return {"volume": volume.astype(np.float16), "guide": guide.astype(np.float16), "target": target,
            "classical_inv": result.grid_inv_depth.astype(np.float32), "sigma": np.float32(sigma),
            "theta_deg": np.float32(theta), "built": np.bool_(built),
            "inv_depth_per_m": decoder.candidates.inv_depth_per_m.astype(np.float32)}


def _shard_job(state: dict, job: tuple) -> int:
    """Write shard ``job = (out_dir, shard)`` once; returns the pairs written."""
    from bmi_sdk.scaleout import publish_once

    out_dir, shard = job
    path = Path(out_dir) / f"shard_{shard:05d}.npz"
    if path.exists():
        return 0
    spec: VolumeSpec = state["spec"]
    items = [make_pair(state, i) for i in range(shard * SHARD_PAIRS, min(spec.pairs, (shard + 1) * SHARD_PAIRS))]
    arrays = {k: np.stack([it[k] for it in items]) for k in items[0]}
    return len(items) if publish_once(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz") else 0


def build_pairs(out_dir: str | Path, spec: VolumeSpec, workers: int = 1, progress: bool = True,
                deadline_s: float | None = None) -> Path:
    """Make every shard of ``spec`` not yet in ``out_dir`` (resumable; ``workers`` processes); returns the folder.
    ``deadline_s``: stop starting shards after this many seconds (the running ones finish and are kept)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta_path = out / "volume.json"
    identity = {"schema": VOLUME_SCHEMA, "spec": spec.to_dict()}
    if meta_path.exists() and json.loads(meta_path.read_text()) != identity:
        raise ValueError(f"{out} holds pairs of another spec; choose another folder")
    write_json(meta_path, identity)
    shards = -(-spec.pairs // SHARD_PAIRS)
    jobs = [(str(out), s) for s in range(shards) if not (out / f"shard_{s:05d}.npz").exists()]
    workers = max(1, min(workers, len(jobs)))
    state = PairMaker(spec, threads=1 if workers > 1 else None)
    start = time.monotonic()
    for _ in map_jobs(_shard_job, jobs, workers, state=state, desc="evidence-volume pairs", unit="shard",
                      progress=progress):
        if deadline_s is not None and time.monotonic() - start > deadline_s:
            break
    return out


class VolumePairs:
    """The pairs of one or more folders made by ``build_pairs``, in memory (a few kB per window)."""

    def __init__(self, folders):
        arrays: dict[str, list] = {}
        for folder in folders:
            for path in sorted(Path(folder).glob("shard_*.npz")):
                with np.load(path, allow_pickle=False) as z:
                    for k in z.files:
                        arrays.setdefault(k, []).append(z[k])
        if not arrays:
            raise ValueError(f"no pair shards in {list(folders)}")
        self.arrays = {k: np.concatenate(v) for k, v in arrays.items()}
        cands = self.arrays["inv_depth_per_m"]
        if not np.allclose(cands, cands[:1]):
            raise ValueError("the pairs were decoded over different candidate sets")
        self.inv_depth_per_m = cands[0]

    def __len__(self) -> int:
        return len(self.arrays["volume"])

    def batch(self, rng: np.random.Generator, size: int, crop: int | None = None) -> dict:
        """``size`` random pairs, each a random ``crop``² of its grid (multiple of 4), dihedrally augmented."""
        idx = rng.integers(0, len(self), size)
        rows, cols = self.arrays["target"].shape[1:]
        crop = crop or (min(rows, cols) // 4) * 4
        out: dict[str, list] = {"volume": [], "guide": [], "target": []}
        for i in idx:
            r0, c0 = rng.integers(0, rows - crop + 1), rng.integers(0, cols - crop + 1)
            box = (slice(r0, r0 + crop), slice(c0, c0 + crop))
            k = int(rng.integers(8))
            for name in out:
                a = self.arrays[name][i][(..., *box)]
                a = np.rot90(a, k % 4, axes=(-2, -1))
                if k >= 4:
                    a = a[..., ::-1]
                out[name].append(np.ascontiguousarray(a))
        return {k: np.stack(v).astype(np.float32) for k, v in out.items()}


def main(argv=None) -> None:
    """``python -m bmi_sdk.nn.volume_data --out DIR [--pairs N --seed S --camera-errors F --workers W --deadline-s T]``"""
    import argparse

    ap = argparse.ArgumentParser(description="make evidence-decoder training pairs (resumable)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--pairs", type=int, default=VolumeSpec.pairs)
    ap.add_argument("--crop-px", type=int, default=VolumeSpec.crop_px)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene-scale-max", type=float, default=VolumeSpec.scene_scale_max)
    ap.add_argument("--camera-errors", type=float, default=0.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--deadline-s", type=float, default=None)
    a = ap.parse_args(argv)
    if a.workers < 1:
        ap.error(f"--workers must be >= 1, got {a.workers}")
    try:
        spec = VolumeSpec(pairs=a.pairs, crop_px=a.crop_px, seed=a.seed, scene_scale_max=a.scene_scale_max,
                          camera_errors=a.camera_errors)
    except ValueError as exc:
        ap.error(str(exc))
    build_pairs(a.out, spec, workers=a.workers, deadline_s=a.deadline_s)


if __name__ == "__main__":
    main()
