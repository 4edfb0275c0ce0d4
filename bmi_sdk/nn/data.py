"""Training pairs from the forward simulator, cached on disk, with sensor noise drawn fresh each step.

The pipeline of one pair (model_io is the contract it ends in):

  scene window (procedural ``generate_scene`` by default, or a NYUv2 /
  FlyingThings3D image placed with the paper's 12° ``place_patch``) at a
  random sensor position → ``render_coded`` (spatially varying PSF,
  occlusion-aware layers) → × ``relative_illumination`` → **cache** →
  random crop (even offsets: the Bayer phase is kept) → dihedral augmentation
  → Gaussian noise σ → ``bayer_mosaic`` → 12-bit ADC with a black level →
  ``raw_to_rgb`` → ``network_input`` channels. Targets: the scene's linear RGB
  (AiF) and range (m); the valid mask is θ ≤ 60° and a finite range.

Sampled cameras (``CacheSpec.camera_errors`` > 0, the learned refinement's item of issue 13): each sample
draws its own hardware errors (``Perturbation.random``, within a fraction of the paper's ranges) and is
rendered with that camera's exact kernels; the errors are stored with the sample, so its classical decode
(``refine_data``) reads the matching kernels. The scene and window of sample i are those of the nominal
cache of the same seed.

Rendering a 192² window costs ~0.7 s, a training step on a CPU preset
~0.2 s, so the renders are cached (npz shards, written atomically, a build
resumes where it stopped) and everything after the cache — crop, flips,
noise, mosaic, ADC, demosaic — runs per step (a few ms), so noise is never
reused.

Placement: the window's centre is drawn with θ uniform in [0, θ_max] and φ
uniform (redrawn until the window lies on the sensor), so the field edge is
seen as often as the centre; a uniform draw over pixels would show 50–60° in
under 5 % of the pairs. Each window carries ``margin_px`` ≥ half a kernel of
extra scene on every side, rendered and then cut away, so light from just
outside a crop is in it; the stored part is the crop size plus 2 ×
``jitter_px`` for random crops.

Augmentation consistent with the radial geometry: a lens symmetric about its
axis images a mirrored (or 90°-rotated) scene into the mirrored (rotated)
optical image, PSFs included. So a flip or transpose T of the crop's pixels,
applied to the optical image, the targets and the θ map, with the direction
(cos φ, sin φ) transformed by the same T as a vector, is the pair of the
mirrored scene at the mirrored sensor position. The 8 elements of the
dihedral group are used.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from bmi_sdk.geometry import SensorGeometry
from bmi_sdk.io_atomic import write_json
from bmi_sdk.lenses import LENS_KERNEL_PX, lens_geometry, lens_tensor
from bmi_sdk.model_io import field_channels, raw_to_rgb, window_cfa
from bmi_sdk.sensor import (
    BLACK_LEVEL_DN,
    CFA_PATTERN,
    WHITE_LEVEL_DN,
    adc_dn,
    add_gaussian_noise,
    bayer_mosaic,
    relative_illumination,
)

STANDARD_SIGMA = 0.005
CAMERA_ERROR_STREAM = 53
"""Third seed word of a sample's camera-error draw (``CacheSpec.camera``), apart from its scene's stream."""
SHARD_SAMPLES = 32
CACHE_SCHEMA = "bmi-train-cache/1"
FAR_FILL_M = 10.0
"""Range given to pixels without ground truth (dataset holes) for rendering only; they are masked in losses."""


# -- lenses and their sensors ---------------------------------------------------------------------------

def render_margin_px(lens_name: str) -> int:
    """Scene margin rendered around a window and cut away: half a kernel, plus 4 px for jitter."""
    return LENS_KERNEL_PX[lens_name] // 2 + 4


SCENE_MARGIN_PX = render_margin_px("bmi_monocentric")
"""Procedural scene drawn around a window whatever the lens. Object sizes scale with the drawn size, so
a lens with a wider kernel margin (the fisheye: 84 px) sees the same draw extended by mirror reflection
(``mirror_extend``), not a larger draw: both systems train and are scored on one scene distribution."""


def mirror_extend(rgb: np.ndarray, range_m: np.ndarray, pad_px: int) -> tuple[np.ndarray, np.ndarray]:
    """A scene (H×W×3 RGB, H×W range) continued by ``pad_px`` of its mirror image on every side."""
    if pad_px < 0:
        raise ValueError(f"cannot extend a scene by {pad_px} px: its lens needs less margin than "
                         f"SCENE_MARGIN_PX = {SCENE_MARGIN_PX}")
    if not pad_px:
        return rgb, range_m
    return (np.pad(rgb, ((pad_px, pad_px), (pad_px, pad_px), (0, 0)), mode="reflect"),
            np.pad(range_m, pad_px, mode="reflect"))


# -- the sensor half of the chain (per step) -----------------------------------------------------------

def simulate_raw(optical: np.ndarray, sigma: float, rng: np.random.Generator, row0: int = 0, col0: int = 0,
                 black_level_dn: int = BLACK_LEVEL_DN, white_level_dn: int = WHITE_LEVEL_DN) -> np.ndarray:
    """Optical image at the sensor (H×W×3, relative illumination applied) → the raw H×W uint16 frame.

    Gaussian noise σ (the paper's model) → RGGB mosaic at the window's phase →
    ADC (``sensor.adc_dn``: black level, rounding to 12-bit DN, clipping at 0 and white).
    """
    noisy = add_gaussian_noise(optical, sigma, rng)
    mosaic = bayer_mosaic(noisy, row0, col0)
    return adc_dn(mosaic, white_level_dn - black_level_dn, black_level_dn, white_level_dn)


def simulate_sensor(optical: np.ndarray, sigma: float, rng: np.random.Generator, row0: int = 0, col0: int = 0,
                    black_level_dn: int = BLACK_LEVEL_DN, white_level_dn: int = WHITE_LEVEL_DN) -> np.ndarray:
    """Optical image at the sensor → demosaiced RGB the network sees: ``simulate_raw`` → ``raw_to_rgb``."""
    raw = simulate_raw(optical, sigma, rng, row0, col0, black_level_dn, white_level_dn)
    return raw_to_rgb(raw, black_level_dn, white_level_dn, window_cfa(CFA_PATTERN, row0, col0))


def dihedral(arr: np.ndarray, k: int) -> np.ndarray:
    """Element k ∈ 0..7 of the dihedral group on the first two axes: bit 0 flips columns, bit 1 flips rows,
    bit 2 transposes (applied in that order)."""
    if k & 1:
        arr = arr[:, ::-1]
    if k & 2:
        arr = arr[::-1]
    if k & 4:
        arr = arr.swapaxes(0, 1)
    return np.ascontiguousarray(arr)


def dihedral_field(field: np.ndarray, k: int) -> np.ndarray:
    """Field channels (3×H×W: θ/60°, cos φ, sin φ) of the transformed crop: the maps move with the pixels
    and the direction (x, y) = (cos φ, sin φ) is transformed as a vector (x → −x, y → −y, x ↔ y)."""
    theta, x, y = (dihedral(c, k) for c in field)
    if k & 1:
        x = -x
    if k & 2:
        y = -y
    if k & 4:
        x, y = y, x
    return np.stack([theta, x, y])


# -- window placement ----------------------------------------------------------------------------------

def sample_window(geometry: SensorGeometry, size_px: int, rng: np.random.Generator,
                  theta_range_deg: tuple[float, float] = (0.0, 60.0)) -> tuple[int, int]:
    """(row0, col0), both even, of a size_px² window on the sensor whose centre's θ is uniform in the range."""
    for _ in range(10000):
        theta = rng.uniform(*theta_range_deg)
        phi = rng.uniform(-180.0, 180.0)
        r, c = geometry.pixel_of_field(theta, phi)
        row0 = int(round((float(r) - size_px / 2) / 2)) * 2
        col0 = int(round((float(c) - size_px / 2) / 2)) * 2
        if 0 <= row0 <= geometry.height_px - size_px and 0 <= col0 <= geometry.width_px - size_px:
            return row0, col0
    raise ValueError(f"no {size_px}² window with θ in {theta_range_deg} fits on the sensor")


# -- the cache -----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CacheSpec:
    """What a cache holds: ``samples`` renders of ``crop_px + 2 jitter_px`` pixels through ``lens``."""

    lens: str = "bmi_monocentric"
    samples: int = 768
    crop_px: int = 128
    jitter_px: int = 8
    seed: int = 0
    source: str = "procedural"
    camera_errors: float = 0.0  # > 0: each sample's camera draws hardware errors within this fraction of the paper's
    #                             ranges (``Perturbation.random``) and is rendered with that camera's exact kernels
    scene_scale_max: float = 1.0  # > 1: each procedural sample's scene is drawn at a scale log-uniform in [1, this]
    #                               (objects that much larger: a crop of a frame-scale scene), ``draw_scene``

    def __post_init__(self):
        if not 0.0 <= self.camera_errors <= 1.0:
            raise ValueError(f"camera_errors is a fraction of the paper's error ranges in [0, 1], "
                             f"got {self.camera_errors}")
        if not self.scene_scale_max >= 1.0:
            raise ValueError(f"scene_scale_max must be >= 1 (1: scenes drawn at the crop's own scale), "
                             f"got {self.scene_scale_max}")

    def camera(self, index: int):
        """The ``BuiltCamera`` sample ``index`` is rendered through: the nominal lens, or (``camera_errors`` > 0) one
        with errors drawn from its own seeded stream, so the sample's scene and window are those of the nominal
        cache of the same seed."""
        from bmi_sdk.built_camera import BuiltCamera
        from bmi_sdk.optics.perturb import Perturbation

        if not self.camera_errors:
            return BuiltCamera(self.lens)
        rng = np.random.default_rng([self.seed, index, CAMERA_ERROR_STREAM])
        return BuiltCamera(self.lens, Perturbation.random(rng, self.camera_errors))

    @property
    def margin_px(self) -> int:
        return render_margin_px(self.lens)

    @property
    def stored_px(self) -> int:
        return self.crop_px + 2 * self.jitter_px

    def to_dict(self) -> dict:
        return asdict(self)


def _dataset_window(scenes: Sequence, geometry: SensorGeometry, size_px: int, rng: np.random.Generator):
    """A size_px² window of a dataset image placed as a 12° patch at a random sensor position."""
    from bmi_sdk.scenes import place_patch

    for _ in range(100):
        placed = place_patch(scenes[int(rng.integers(len(scenes)))], geometry, rng=rng)
        r0, c0, h, w = placed.roi
        if h < size_px + 2 or w < size_px + 2:
            raise ValueError(f"a placed patch of {h}×{w} px cannot hold a {size_px}² window")
        # offsets that put the window at an even sensor row/column (the Bayer phase of the cache)
        dr = r0 % 2 + 2 * int(rng.integers(0, (h - size_px - r0 % 2) // 2 + 1))
        dc = c0 % 2 + 2 * int(rng.integers(0, (w - size_px - c0 % 2) // 2 + 1))
        sl = (slice(dr, dr + size_px), slice(dc, dc + size_px))
        valid = placed.valid[sl] & np.isfinite(placed.range_m[sl])
        if valid.mean() > 0.5:
            return placed.rgb[sl], placed.range_m[sl], r0 + dr, c0 + dc
    raise ValueError("could not find a mostly valid window in 100 placed patches")


def scene_crop(draw_px: int, scene_px: int, rng: np.random.Generator, offset: tuple[int, int] | None = None,
               exponent_spread: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, range_m) of the ``draw_px``² crop at ``offset`` (row, col; default centred) of a ``scene_px``² procedural
    scene drawn from ``rng``, its surfaces' texture exponents scattered by ``exponent_spread`` (``generate_scene``).
    ``generate_scene`` sizes its objects to the scene, so a scene drawn k× larger than the crop holds objects k×
    larger against it, as a frame's are against a tile; ``scene_px`` = ``draw_px`` is the whole scene, drawn as before
    crops existed."""
    from bmi_sdk.scenes import generate_scene

    if scene_px < draw_px:
        raise ValueError(f"a {draw_px}² crop needs a scene of at least that size, got {scene_px}²")
    r0, c0 = offset if offset is not None else ((scene_px - draw_px) // 2,) * 2
    scene = generate_scene(scene_px, scene_px, rng, exponent_spread=exponent_spread)
    if scene_px == draw_px:
        return scene.rgb, scene.range_m
    box = slice(r0, r0 + draw_px), slice(c0, c0 + draw_px)
    return np.ascontiguousarray(scene.rgb[box]), np.ascontiguousarray(scene.range_m[box])


def draw_scene(draw_px: int, scale_max: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, range_m) of a training pair's ``draw_px``² procedural scene: with ``scale_max`` > 1 a random crop of a
    scene drawn at a size log-uniform in [1, scale_max] × ``draw_px`` (``scene_crop``). ``scale_max`` = 1 draws
    nothing more from ``rng``, so such caches are the ones rendered before the scale existed."""
    if scale_max <= 1.0:
        return scene_crop(draw_px, draw_px, rng)
    big = max(draw_px, int(round(draw_px * math.exp(rng.uniform(0.0, math.log(scale_max))))))
    r0, c0 = rng.integers(0, big - draw_px + 1, size=2)
    return scene_crop(draw_px, big, rng, (int(r0), int(c0)))


def procedural_window(spec: CacheSpec, rng: np.random.Generator, geometry: SensorGeometry) -> tuple[int, int]:
    """(row0, col0) of a procedural sample's window: the first draw of the sample's stream (seeded by
    (``spec.seed``, index)), so ``tensor_fields`` knows it before the sample renders."""
    return sample_window(geometry, spec.stored_px + 2 * spec.margin_px, rng)


def render_sample(spec: CacheSpec, index: int, tensor, geometry: SensorGeometry,
                  scenes: Sequence | None = None) -> dict:
    """One cached sample (seeded by (spec.seed, index)): optical image, targets and window position."""
    from bmi_sdk.render import render_coded

    rng = np.random.default_rng([spec.seed, index])
    size = spec.stored_px + 2 * spec.margin_px
    if scenes is None:
        row0, col0 = procedural_window(spec, rng, geometry)
        rgb, range_m = draw_scene(spec.stored_px + 2 * SCENE_MARGIN_PX, spec.scene_scale_max, rng)
        rgb, range_m = mirror_extend(rgb, range_m, spec.margin_px - SCENE_MARGIN_PX)
    else:
        rgb, range_m, row0, col0 = _dataset_window(scenes, geometry, size, rng)
    render_range = np.where(np.isfinite(range_m), range_m, FAR_FILL_M).astype(np.float32)
    extra = {}
    if spec.camera_errors:
        # the camera's own exact kernels, its whole-image shift taken out (a calibrated optical centre), on the
        # render zones its kernels need, as `bmi eval` renders its built-camera conditions
        camera = spec.camera(index)
        psf_map = camera.psf_map(mode="exact", centre_calibrated=True)
        optical = render_coded(rgb, render_range, psf_map.tensor, geometry, row0=row0, col0=col0, psf_map=psf_map,
                               zone_px=camera.render_zone_px("exact"))
        extra["perturbation"] = camera.perturbation.to_vector().astype(np.float32)
    else:
        optical = render_coded(rgb, render_range, tensor, geometry, row0=row0, col0=col0, psf_mode="tensor")
    optical *= relative_illumination(geometry, row0, col0, size, size)[..., None]
    m = slice(spec.margin_px, spec.margin_px + spec.stored_px)
    return {"optical": optical[m, m].astype(np.float16), "rgb": rgb[m, m].astype(np.float16),
            "range_m": range_m[m, m].astype(np.float32),
            "origin": np.array([row0 + spec.margin_px, col0 + spec.margin_px], dtype=np.int32), **extra}


def render_identity(lens_name: str) -> dict:
    """What the cached renders depend on besides the spec: the sensor mapping and the PSF tensor.

    Stored in ``cache.json``, so a cache rendered through another geometry
    (e.g. the ideal R·θ mapping) or another tensor is refused, not reused.
    """
    import hashlib

    tensor = lens_tensor(lens_name)
    geometry = json.dumps(lens_geometry(lens_name).to_dict(), sort_keys=True)
    return {"geometry_sha256": hashlib.sha256(geometry.encode()).hexdigest()[:16],
            "psf_tensor_key": tensor.spec.cache_key(tensor.lens)}


def shard_sample_range(spec: CacheSpec, shard: int, shard_samples: int = SHARD_SAMPLES) -> range:
    """The sample indices stored in shard ``shard``."""
    return range(shard * shard_samples, min(spec.samples, (shard + 1) * shard_samples))


def shard_path(cache_dir: Path, shard: int) -> Path:
    return Path(cache_dir) / f"shard_{shard:05d}.npz"


@dataclass(frozen=True)
class ShardRenderer:
    """What rendering a shard needs besides the spec: the lens's PSF tensor and sensor, and dataset scenes.

    Calling it opens the tensor, whose kernels load from the disk cache (``build_cache`` filled it first)
    as renders touch them and then stay in memory: a process (``parallel.map_jobs`` state) or a Dask worker
    (``scaleout.fan_out`` state) keeps one for all its shards.
    """

    lens: str
    scenes: Sequence | None = None

    def __call__(self) -> dict:
        tensor = lens_tensor(self.lens)
        return {"tensor": tensor, "geometry": lens_geometry(self.lens), "scenes": self.scenes}


def render_shard(renderer: dict, job: tuple) -> int:
    """Render shard ``job = (cache_dir, spec, shard, shard_samples)`` and publish it once; returns how many
    samples this call wrote (0 when the shard was already there: a resumed run, or a task re-run after its
    worker died after publishing). A lost race keeps the first copy; both are the same samples anyway."""
    from bmi_sdk.scaleout import publish_once

    cache_dir, spec, shard, shard_samples = job
    path = shard_path(cache_dir, shard)
    if path.exists():
        return 0
    items = [render_sample(spec, i, renderer["tensor"], renderer["geometry"], renderer["scenes"])
             for i in shard_sample_range(spec, shard, shard_samples)]
    arrays = {k: np.stack([it[k] for it in items]) for k in items[0]}
    return len(items) if publish_once(path, lambda tmp: np.savez(tmp, **arrays), suffix=".npz") else 0


def _remove_stale_temporaries(cache_dir: Path) -> None:
    """Delete the hidden temporaries (``.shard_NNNNN.npz.*``) of shards that are published: left by a
    process killed while writing, they are never read."""
    for tmp in cache_dir.glob(".shard_*.npz.*"):
        if (cache_dir / (tmp.name[1:].split(".npz.")[0] + ".npz")).exists():
            tmp.unlink(missing_ok=True)


def tensor_fields(spec: CacheSpec, indices: Sequence[int]) -> list[int]:
    """The PSF tensor's field indices that the procedural samples ``indices`` of ``spec`` render through: each
    sample's window (``render_sample``'s first draw, replayed) split into the renderer's zones, each zone's θ
    bracketed by two field angles. A few samples touch a few of the tensor's field angles, not all of them."""
    from bmi_sdk.render import PsfMap
    from bmi_sdk.render.compose import render_zones

    tensor, geometry = lens_tensor(spec.lens), lens_geometry(spec.lens)
    psf_map = PsfMap(tensor, geometry, mode="tensor")
    size = spec.stored_px + 2 * spec.margin_px
    fields: set[int] = set()
    for index in indices:
        row0, col0 = procedural_window(spec, np.random.default_rng([spec.seed, index]), geometry)
        fields.update(psf_map.field_indices(render_zones(geometry, tensor, row0, col0, size, size)[1]))
    return sorted(fields)


def build_cache(cache_dir: str | Path, spec: CacheSpec, scenes: Sequence | None = None,
                progress: bool = True, workers: int = 1, scheduler: str | None = None,
                shard_samples: int = SHARD_SAMPLES) -> Path:
    """Render every missing shard of ``spec`` into ``cache_dir`` (resumable; a spec mismatch is refused).

    Shards of ``shard_samples`` renders are rendered by ``workers`` local processes (one numpy thread
    each), or with ``scheduler`` (``local:N`` / ``tcp://HOST:PORT``) by Dask workers; each shard is
    published under its final name once, whole. Samples are seeded by index, so the cache is the same
    whoever renders which shard, and a run that dies resumes with the shards still missing.
    """
    cache_dir = Path(cache_dir)
    meta_path = cache_dir / "cache.json"
    meta = {"schema": CACHE_SCHEMA, "spec": spec.to_dict(), "renderer": render_identity(spec.lens),
            "shard_samples": shard_samples}
    if meta_path.exists():
        old = {"shard_samples": SHARD_SAMPLES, **json.loads(meta_path.read_text())}  # caches before the field
        try:  # a cache from before a spec field reads it at its default, which is how it was rendered
            old["spec"] = CacheSpec(**old["spec"]).to_dict()
        except (KeyError, TypeError, ValueError):
            pass  # not a spec this version knows: refused below
        if old != meta:
            raise ValueError(f"{cache_dir} holds another cache (spec {old.get('spec')}, renderer {old.get('renderer')}, "
                             f"{old['shard_samples']} samples a shard; this run needs {meta['spec']}, "
                             f"{meta['renderer']}, {shard_samples}); choose another --cache")
    else:
        write_json(meta_path, meta)
    n_shards = math.ceil(spec.samples / shard_samples)
    todo = [s for s in range(n_shards) if not shard_path(cache_dir, s).exists()]
    if todo:
        if not spec.camera_errors:  # exact-kernel renders (sampled cameras) trace their kernels, not the tensor's
            # the field angles the renders touch, built once here rather than by each worker
            tensor = lens_tensor(spec.lens)
            fields = range(len(tensor.field_deg)) if scenes is not None else tensor_fields(
                spec, [i for s in todo for i in shard_sample_range(spec, s, shard_samples)])
            tensor.ensure_fields(fields, progress=progress, workers=workers)
        sizes = [len(shard_sample_range(spec, s, shard_samples)) for s in todo]
        jobs = [(cache_dir, spec, s, shard_samples) for s in todo]
        how = dict(state=ShardRenderer(spec.lens, scenes), desc=f"rendering {spec.lens} pairs", unit="pair",
                   sizes=sizes, progress=progress)
        if scheduler is not None:
            from bmi_sdk.scaleout import fan_out, open_client

            with open_client(scheduler, announce=progress) as client:
                fan_out(render_shard, jobs, client=client, **how)
        else:
            from bmi_sdk.parallel import map_jobs

            for _ in map_jobs(render_shard, jobs, workers, **how):
                pass  # each shard is published by its job
    _remove_stale_temporaries(cache_dir)
    return cache_dir


def check_noise_range(sigma: float, sigma_max: float | None) -> None:
    """Refuse a noise range that is empty or reaches σ ≤ 0 (log-uniform needs both ends positive)."""
    if sigma_max is not None and not 0 < sigma <= sigma_max:
        raise ValueError(f"a noise range needs 0 < sigma <= sigma_max, got {sigma} and {sigma_max}")


def noise_sigma(rng: np.random.Generator, sigma: float, sigma_max: float | None) -> float:
    """One pair's noise σ: ``sigma``, or log-uniform over [``sigma``, ``sigma_max``] (no draw without a range).

    Log-uniform because the network's difficulty scales with the ratio of noise to signal,
    not with its difference: every octave of σ gets the same share of training pairs.
    """
    if sigma_max is None:
        return sigma
    check_noise_range(sigma, sigma_max)
    return float(np.exp(rng.uniform(np.log(sigma), np.log(sigma_max))))


class PairCache:
    """The rendered pairs of a cache in memory, and the per-step batch assembly."""

    def __init__(self, cache_dir: str | Path):
        cache_dir = Path(cache_dir)
        meta = json.loads((cache_dir / "cache.json").read_text())
        if meta.get("schema") != CACHE_SCHEMA:
            raise ValueError(f"{cache_dir}: not a training cache (schema {meta.get('schema')!r})")
        self.spec = CacheSpec(**meta["spec"])
        self.geometry = lens_geometry(self.spec.lens)
        shards = sorted(cache_dir.glob("shard_*.npz"))
        expected = math.ceil(self.spec.samples / meta.get("shard_samples", SHARD_SAMPLES))
        if len(shards) != expected:
            raise ValueError(f"{cache_dir}: {len(shards)} of {expected} shards; run build_cache to finish it")
        parts = {}
        for path in shards:
            with np.load(path, allow_pickle=False) as z:
                for k in z.files:
                    parts.setdefault(k, []).append(z[k])
        self.arrays = {k: np.concatenate(v) for k, v in parts.items()}

    def __len__(self) -> int:
        return len(self.arrays["origin"])

    def pair(self, index: int, rng: np.random.Generator, sigma: float = STANDARD_SIGMA,
             augment: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(input 6×S×S, AiF 3×S×S, range 1×S×S, valid 1×S×S) float32 for one cached render."""
        spec, a = self.spec, self.arrays
        s, j = spec.crop_px, spec.jitter_px
        dr, dc = (2 * int(rng.integers(0, j + 1)) for _ in range(2)) if augment else (j - j % 2, j - j % 2)
        row0, col0 = int(a["origin"][index, 0]) + dr, int(a["origin"][index, 1]) + dc
        sl = (slice(dr, dr + s), slice(dc, dc + s))
        optical = a["optical"][index][sl].astype(np.float32)
        rgb = a["rgb"][index][sl].astype(np.float32)
        range_m = a["range_m"][index][sl]
        field = field_channels(self.geometry, row0, col0, s, s)
        valid = self.geometry.valid_mask(row0, col0, s, s) & np.isfinite(range_m)
        k = int(rng.integers(8)) if augment else 0
        optical, rgb, range_m, valid = (dihedral(x, k) for x in (optical, rgb, range_m, valid))
        field = dihedral_field(field, k)
        # the augmented crop is a virtual window; its mosaic keeps the even-offset (RGGB) phase
        seen = simulate_sensor(optical, sigma, rng, row0 - row0 % 2, col0 - col0 % 2)
        x = np.concatenate([seen.transpose(2, 0, 1), field])
        return (x, rgb.transpose(2, 0, 1), np.nan_to_num(range_m, nan=1.0)[None],
                valid[None].astype(np.float32))

    def batch(self, seed: int, step: int, batch_size: int, sigma: float = STANDARD_SIGMA,
              sigma_max: float | None = None):
        """The batch of ``step``: a pure function of (seed, step), so a resumed run sees the same data.

        With ``sigma_max`` each pair draws its own noise σ log-uniform over
        [``sigma``, ``sigma_max``] (``noise_sigma``); without it every pair has ``sigma``
        and the random stream is the one fixed-σ runs have always used.
        """
        rng = np.random.default_rng([seed, step])
        items = [self.pair(int(rng.integers(len(self))), rng, noise_sigma(rng, sigma, sigma_max))
                 for _ in range(batch_size)]
        return tuple(np.stack(parts) for parts in zip(*items))
