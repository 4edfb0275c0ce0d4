"""The synthetic benchmark behind ``bmi eval``: the paper's table analogues on fixed, seeded tiles.

Benchmark: ``tiles`` procedural scenes per field region, each a ``tile_px``²
window (+ a margin of half a kernel, rendered and cut away; a wider kernel's
margin is the scene's mirror continuation, ``data.SCENE_MARGIN_PX``, so every
optical system scores the very same content on each tile) whose centre is
drawn with the seed: **centre** = θ ∈ [0°, 20°], **edge** = θ ∈ [52°, 58°]
(its pixels span the 50–60° band; those beyond 60° are invalid). Metrics
(``metrics``) are per tile on valid pixels, averaged over the tiles of a region.

A condition is what changes between capture and the fixed trained network:

* noise σ (the sensor stage; ``ideal`` = σ 0, still 12-bit quantised,
  ``standard`` = 0.005, ``noise_<σ>`` the sweep);
* hardware errors, no retraining, each an ``optics.perturb.Perturbation``: the
  one hardware-error model, the one ``bmi calibrate`` fits. Errors a rotationally
  symmetric tensor can hold (``HARDWARE``: PSF shift, scale, stray light, sensor
  radius) render from the built lens's PSF tensor (``PsfTensor(perturbation=…)``,
  its φ = 0 kernels rotated per pixel, so the shift is radial);
* a built lens that breaks the rotational symmetry (``EXACT``: lens decenter
  10 µm, tilt 1 arcmin, the paper's joint condition, traced exactly at every zone's (θ, φ) by an
  ``exact``-mode ``PsfMap`` with the ``Perturbation``). The
  camera's optical centre is taken as calibrated: a 10 µm decenter moves the
  whole image by ~5 px, which any principal-point calibration removes and
  which would otherwise dominate the image metrics as misregistration, so
  the on-axis spot shift is taken out of every kernel
  (``PsfMap(centre_calibrated=True)``) and the field-dependent rest and the
  PSF shapes remain;
* another optical system (``fisheye_standard``: the fisheye lens, its plane
  sensor and its own trained model).

Every other condition renders with ``psf_mode="tensor"`` (the paper's
rotated radial tensor), which by itself differs from the exact kernels
(``render.psf_map``). So decenter and tilt are to be read against
``nominal_exact``, the design rendered by the same exact renderer at the
same σ (0.005), not against ``standard``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.metrics import depth_metrics, image_metrics, mean_metrics
from bmi_sdk.model_io import INPUT_CHANNELS, network_input, raw_to_rgb, window_cfa
from bmi_sdk.nn.data import (
    SCENE_MARGIN_PX,
    STANDARD_SIGMA,
    mirror_extend,
    render_margin_px,
    sample_window,
    scene_crop,
    simulate_raw,
)
from bmi_sdk.optics.perturb import Perturbation
from bmi_sdk.runtime.decoders import DEFAULT_DECODER
from bmi_sdk.sensor import (
    BLACK_LEVEL_DN,
    CFA_PATTERN,
    PAPER_NOISE_SIGMAS,
    WHITE_LEVEL_DN,
    NoiseProfile,
    relative_illumination,
)

REGIONS = {"centre": (0.0, 20.0), "edge": (52.0, 58.0)}

HARDWARE = {
    "psf_shift_0.5px": Perturbation(psf_shift_px=(0.5, 0.0)),
    "psf_scale_3pct": Perturbation(psf_scale_pct=3.0),
    "psf_scale_5pct": Perturbation(psf_scale_pct=5.0),
    "stray_light_3pct": Perturbation(stray_light_fraction=0.03),
    "sensor_radius_0.5pct": Perturbation(sensor_radius_error_pct=0.5),
    "sensor_radius_1pct": Perturbation(sensor_radius_error_pct=1.0),
    "sensor_radius_2pct": Perturbation(sensor_radius_error_pct=2.0),
}
"""Hardware-error conditions (paper Tables 5, 6) that a rotationally symmetric PSF tensor can hold, rendered
from the built lens's tensor: the shift along +col of the φ = 0 kernels (radial once rotated), the scale one
factor for every kernel, the glare ``perturb.glare_kernel`` of the calibrated spread, the radius re-traced."""

EXACT = {
    "nominal_exact": Perturbation(),
    "decenter_10um": Perturbation(decenter_um=(10.0, 0.0)),
    "tilt_1arcmin": Perturbation(tilt_arcmin=(1.0, 0.0)),
    "joint": Perturbation(psf_shift_px=(0.5, 0.0), psf_scale_pct=3.0, decenter_um=(10.0, 0.0),
                          tilt_arcmin=(1.0, 0.0), stray_light_fraction=0.03),
    "built_camera": Perturbation(decenter_um=(10.0, 0.0), psf_shift_px=(0.5, 0.0), stray_light_fraction=0.03,
                                 sensor_radius_error_pct=0.5),
}
"""Conditions rendered with exact-mode kernels of the (perturbed) lens at σ = ``STANDARD_SIGMA``; decenter
along the sensor's +col, tilt about it; ``joint`` is the paper's (shift 0.5 px, scale 3 %, decenter 10 µm,
tilt 1′, stray light 3 %); ``built_camera`` is the decoding issue's perturbed camera (decenter 10 µm, PSF
shift 0.5 px, stray light 3 %, sensor radius +0.5 %); ``nominal_exact`` is their reference (module doc)."""


def noise_conditions() -> dict:
    out = {"ideal": 0.0, "standard": STANDARD_SIGMA}
    out.update({f"noise_{s:g}": s for s in PAPER_NOISE_SIGMAS})
    return out


def known_conditions() -> list[str]:
    """Every condition name, in the default order (``fisheye_standard`` needs its own model)."""
    return [*noise_conditions(), *HARDWARE, *EXACT, "fisheye_standard"]


@dataclass(frozen=True)
class Benchmark:
    lens: str = "bmi_monocentric"
    tiles: int = 12
    tile_px: int = 192
    seed: int = 20260
    threads: int = 2
    scheduler: str | None = None  # renders on Dask (``scaleout``: local:N or tcp://HOST:PORT); None: here
    scene_scale: float = 1.0  # > 1: each tile's scene is drawn this much larger and its centre kept (``scene``)

    def __post_init__(self):
        if not self.scene_scale >= 1.0:
            raise ValueError(f"scene_scale must be >= 1 (1: scenes drawn at the tile's own scale), "
                             f"got {self.scene_scale}")
        for name, least in (("tiles", 1), ("tile_px", 4), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"benchmark {name} must be a whole number >= {least}, got {value!r}")
        if self.tile_px % 4:
            raise ValueError(f"benchmark tile_px must be a multiple of 4 (whole Bayer cells, the networks' size "
                             f"multiple), got {self.tile_px}")

    @property
    def margin_px(self) -> int:
        return render_margin_px(self.lens)

    def windows(self) -> list[tuple[str, int, int, int]]:
        """(region, tile index, row0, col0) of the rendered windows (tile + margin), seeded."""
        geometry = lens_geometry(self.lens)
        size = self.tile_px + 2 * self.margin_px
        out = []
        for r, (name, band) in enumerate(REGIONS.items()):
            rng = np.random.default_rng([self.seed, r])
            out += [(name, i, *sample_window(geometry, size, rng, band)) for i in range(self.tiles)]
        return out

    def scene(self, region: str, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(linear RGB, range_m) of tile ``i`` of ``region`` over this lens's window (tile + 2 × margin): a
        procedural scene drawn at the window's size, or (``scene_scale`` > 1) the centre of one drawn that much
        larger, whose objects are that much larger against the tile (``nn.data.scene_crop``)."""
        draw_px = self.tile_px + 2 * SCENE_MARGIN_PX
        rgb, range_m = scene_crop(draw_px, int(round(draw_px * self.scene_scale)),
                                  np.random.default_rng([self.seed, 7, list(REGIONS).index(region), i]))
        return mirror_extend(rgb, range_m, self.margin_px - SCENE_MARGIN_PX)

    def renders(self, tensor, progress: bool = False, psf_mode: str = "tensor",
                centre_calibrated: bool = True, zone_px: int | None = None) -> list[dict]:
        """Scene, optical image (relative illumination applied) and position of every tile, for one tensor.

        ``psf_mode`` makes the zone kernels (``render.PsfMap``) from ``tensor``, with the hardware errors
        it was built with (``BuiltCamera.psf_tensor``); ``centre_calibrated`` (default) takes the
        whole-image shift of those errors out in ``exact`` mode, as a camera whose optical centre is
        calibrated sees it. ``zone_px``: the render zones (default the renderer's 512 px; a built camera's
        ``BuiltCamera.render_zone_px``, finer where its kernels change fast with θ).
        """
        from bmi_sdk.scaleout import fan_out, open_client

        state = _WindowRenderer(self, tensor, psf_mode, centre_calibrated, zone_px)
        with open_client(self.scheduler, announce=False) as client:
            return fan_out(_render_window, self.windows(), client=client, state=state,
                           desc="rendering benchmark tiles", unit="tile", progress=progress)


@dataclass(frozen=True)
class _WindowRenderer:
    """Builds, once per process, what ``_render_window`` needs: the lens's sensor and the zone kernels."""

    bench: Benchmark
    tensor: object
    psf_mode: str
    centre_calibrated: bool
    zone_px: int | None = None

    def __call__(self) -> dict:
        from bmi_sdk.render import PsfMap

        geometry = lens_geometry(self.bench.lens)
        psf_map = PsfMap(self.tensor, geometry, mode=self.psf_mode, centre_calibrated=self.centre_calibrated)
        return {"bench": self.bench, "tensor": self.tensor, "geometry": geometry, "psf_map": psf_map,
                "zone_px": self.zone_px}


def _render_window(state: dict, window: tuple) -> dict:
    """Scene, optical image and position of one benchmark window (region, tile index, row0, col0)."""
    from bmi_sdk.render import render_coded

    bench, geometry = state["bench"], state["geometry"]
    size, m = bench.tile_px + 2 * bench.margin_px, bench.margin_px
    region, i, row0, col0 = window
    rgb, range_m = bench.scene(region, i)
    optical = render_coded(rgb, range_m, state["tensor"], geometry, row0=row0, col0=col0, psf_map=state["psf_map"],
                           zone_px=state["zone_px"])
    optical *= relative_illumination(geometry, row0, col0, size, size)[..., None]
    return {"region": region, "tile": i, "row0": row0 + m, "col0": col0 + m, "optical_full": optical,
            "rgb": rgb[m:-m, m:-m], "range_m": range_m[m:-m, m:-m]}


class NetworkTiles:
    """A verified ONNX model (``runtime.Model``: manifest and SHA-256 checked) as a benchmark decoder:
    raw tile in, AiF + depth (+ 1σ) out, one tile per session run.

    An end-to-end model (decoder ``cnn``) reads the demosaiced tile and its field channels; a learned
    refinement (decoder ``learned``) also the classical decoder's channels (``decode.features``), made with
    its manifest's knobs over ``psf_map``'s kernels (the nominal camera's, or the built camera's own), and
    its depth is the network's fused with the classical stage's (``decode.fusion``, with the weights of the
    model's manifest, as ``bmi infer`` does), and its AiF the network's made consistent with the tile through
    those kernels at the fused depth (``runtime.learned.consistent_aif``, as ``bmi infer`` does);
    ``fuse=False`` keeps the network's own depth and AiF (and leaves the manifest's fusion weights unread).
    """

    def __init__(self, path: str | Path, tile_px: int, threads: int = 2, psf_map=None, name: str | None = None,
                 fuse: bool = True):
        from bmi_sdk.runtime.model import Model

        self.model = Model(path, tile_px=tile_px, threads=threads, read_fusion_weights=fuse)
        self.name = name or self.model.decoder
        self.fuse = fuse
        self.stage = None
        if self.model.input_channels > INPUT_CHANNELS:  # a refinement: it reads its classical stage's channels
            from bmi_sdk.decode import ClassicalDecoder
            from bmi_sdk.runtime.learned import model_classical_config

            self.stage = ClassicalDecoder.for_psf_map(psf_map, model_classical_config(self.model, threads))

    def __call__(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        decoded = None if self.stage is None else self.classical_read(raw, geometry, row0, col0, noise)
        return self.network_read(raw, geometry, row0, col0, decoded)

    def classical_read(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        """A learned refinement's first stage: the classical decode (``DecodeResult``) of a raw tile."""
        return self.stage.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, noise_profile=noise)

    def network_read(self, raw: np.ndarray, geometry, row0: int, col0: int, decoded=None, fuse: bool | None = None):
        """(AiF H × W × 3, depth, 1σ or None) of the network on a raw tile; a refinement also reads ``decoded``'s
        channels and, when ``fuse`` (default: this decoder's), returns its depth fused with ``decoded``'s and its AiF
        made consistent with the tile at that depth."""
        seen = raw_to_rgb(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, window_cfa(CFA_PATTERN, row0, col0))
        x = network_input(seen, geometry, row0, col0)
        if decoded is not None:
            from bmi_sdk.decode.features import refinement_features

            x = np.concatenate([x, refinement_features(decoded, self.stage.config.stride_px)[None]], axis=1)
        aif, depth, *sigma = self.model.run(np.ascontiguousarray(x, np.float32))
        depth, sigma = depth[0, 0], (sigma[0][0, 0] if sigma else None)
        aif = aif[0].transpose(1, 2, 0)
        if decoded is not None and (self.fuse if fuse is None else fuse) and sigma is not None:
            self.fuse_read(decoded, depth, sigma)
            aif = self.consistent_read(raw, geometry, row0, col0, decoded, aif, depth)
        return aif, depth, sigma

    def fuse_read(self, decoded, depth: np.ndarray, sigma: np.ndarray) -> None:
        """The network's ``depth`` and 1σ ``sigma`` of a tile fused with its classical read ``decoded``'s, in place
        (``runtime.learned.fuse_into`` with the manifest's weights, as ``bmi infer`` fuses)."""
        if self.model.fusion_weights is None:
            raise ValueError("this decoder was built with fuse=False: its model's fusion weights were not read")
        from bmi_sdk.runtime.learned import fuse_into

        fuse_into(decoded, self.stage.config.stride_px, depth, sigma, self.model.fusion_weights,
                  decoded.stats.get("noise_sigma"))

    def consistent_read(self, raw: np.ndarray, geometry, row0: int, col0: int, decoded, aif: np.ndarray,
                        depth: np.ndarray, aif_step: int | None = None) -> np.ndarray:
        """The network's ``aif`` of a tile made consistent with it through the stage's kernels at the fused ``depth``
        (``runtime.learned.consistent_aif``, as ``bmi infer`` does; on every ``aif_step``-th candidate)."""
        from bmi_sdk.runtime.learned import consistent_aif

        return consistent_aif(self.stage, decoded, raw, aif, depth, black_level_dn=BLACK_LEVEL_DN,
                              white_level_dn=WHITE_LEVEL_DN, cfa=CFA_PATTERN, geometry=geometry, row0=row0, col0=col0,
                              aif_step=aif_step)


class ClassicalTiles:
    """The classical decoder (``bmi_sdk.decode``) as a benchmark decoder: raw tile in, AiF + depth + 1σ out.

    ``psf_map`` is the kernel source the decoder believes in: the nominal camera's, or (for a
    "calibrated" row) the perturbed camera's own kernels.
    """

    name = "classical"

    def __init__(self, psf_map, config=None, name: str = "classical"):
        from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder

        self.decoder = ClassicalDecoder.for_psf_map(psf_map, config or ClassicalConfig())
        self.name = name

    def __call__(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        out = self.decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, noise_profile=noise)
        return out.aif, out.depth_m, out.depth_sigma_m


def tile_raw(bench: Benchmark, item: dict, k: int, sigma: float) -> np.ndarray:
    """The raw frame of rendered tile ``k`` (``Benchmark.renders``) at noise σ: the same draw for every decoder."""
    m, t = bench.margin_px, bench.tile_px
    rng = np.random.default_rng([bench.seed, 99, k, int(round(sigma * 1e6))])
    return simulate_raw(item["optical_full"][m:m + t, m:m + t], sigma, rng, item["row0"], item["col0"])


def score(model, renders: list[dict], bench: Benchmark, sigma: float, condition: str) -> list[dict]:
    """Rows {condition, decoder, region, metrics…} for one condition over pre-rendered tiles.

    ``model``: a ``NetworkTiles`` or a ``ClassicalTiles``, called as ``model(raw, geometry, row0, col0, noise)`` with
    the tile's raw frame and the ``NoiseProfile`` of the noise it was given (decoders that read noise use it, as
    they would a frame's DNG tag). Decoders that report a depth 1σ
    (classical, learned) add ``sigma_z_rms`` and ``sigma_z_std`` to their rows: the RMS and the standard
    deviation of z = (depth error / reported 1σ) over all valid pixels of the region (1 for an honest σ).
    """
    geometry = lens_geometry(bench.lens)
    t = bench.tile_px
    noise = NoiseProfile.additive(sigma)  # the camera's noise is known (its photon transfer); decoders may use it
    per_region: dict[str, list] = {}
    z_sums: dict[str, list] = {}
    for k, item in enumerate(renders):
        raw = tile_raw(bench, item, k, sigma)
        valid = geometry.valid_mask(item["row0"], item["col0"], t, t) & np.isfinite(item["range_m"])
        aif_hwc, depth_m, depth_sigma_m = model(raw, geometry, item["row0"], item["col0"], noise)
        valid &= np.isfinite(depth_m)
        if depth_sigma_m is not None:
            z = (depth_m[valid] - item["range_m"][valid]) / depth_sigma_m[valid]
            z_sums.setdefault(item["region"], []).append((float(np.sum(z)), float(np.sum(z ** 2)), int(z.size)))
        row = depth_metrics(depth_m, item["range_m"], valid)
        row.update(image_metrics(aif_hwc, item["rgb"], valid))
        per_region.setdefault(item["region"], []).append(row)
    rows = []
    for region, region_rows in per_region.items():
        row = {"condition": condition, "decoder": getattr(model, "name", "cnn"), "region": region,
               **mean_metrics(region_rows)}
        if getattr(model, "stage", None) is not None:  # a learned refinement: fused with its classical stage?
            row["fusion"] = model.fuse
        if region in z_sums:
            z_sum, z2_sum, count = map(sum, zip(*z_sums[region]))
            count = max(count, 1)
            row["sigma_z_rms"] = float(np.sqrt(z2_sum / count))
            row["sigma_z_std"] = float(np.sqrt(max(z2_sum / count - (z_sum / count) ** 2, 0.0)))
        rows.append(row)
    return rows


def classical_window_px(lens_name: str, base_px: int) -> int:
    """The evidence window for a lens: ``base_px``, or the smallest multiple of 4 that holds its kernel."""
    from bmi_sdk.lenses import LENS_KERNEL_PX

    return max(base_px, -(-LENS_KERNEL_PX[lens_name] // 4) * 4)


def _decoders(decoders, model_path, psf_map, config, threads: int, tile_px: int, learned_path=None,
              fuse: bool = True) -> list:
    """The benchmark decoders of one optical system: its ONNX model (``cnn``), the classical decoder over its
    nominal kernels, and the learned refinement over them (``learned_path``; none for a lens without one;
    ``fuse``: its depth fused with its classical stage's, ``NetworkTiles``)."""
    out = []
    if "cnn" in decoders:
        if model_path is None:
            raise ValueError("the cnn decoder needs a model (for fisheye_standard: --fisheye-model)")
        out.append(NetworkTiles(model_path, tile_px, threads))
    if "classical" in decoders:
        out.append(ClassicalTiles(psf_map, config))
    if "learned" in decoders and learned_path is not None:
        out.append(NetworkTiles(learned_path, tile_px, threads, psf_map, fuse=fuse))
    return out


def run_benchmark(model_path: str | Path | None, bench: Benchmark = Benchmark(), conditions: list[str] | None = None,
                  fisheye_model: str | Path | None = None, progress: bool = True,
                  decoders: tuple[str, ...] = (DEFAULT_DECODER,), classical_config=None,
                  learned_model: str | Path | None = None, learned_fusion: bool = True) -> list[dict]:
    """Every requested condition (default: noise sweep, hardware errors (``HARDWARE``, ``EXACT``), + fisheye
    when its model is given, or always for the classical decoder) for every requested decoder.

    The classical decoder reads the nominal camera's kernels (decoder ``classical``); on a hardware
    condition whose kernels a camera model can represent it also reads the built camera's own kernels
    (decoder ``classical_calibrated``: decoding with a perfect calibration). The learned refinement
    (``learned_model``, default the shipped ``learned.onnx``) does the same through its classical stage
    (``learned`` and ``learned_calibrated``); there is no fisheye refinement, so no fisheye learned row.
    ``learned_fusion=False`` scores the refinement's network alone, without its fusion with the classical
    stage (``decode.fusion``); its rows say which (``fusion``).
    """
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.render import PsfMap
    from bmi_sdk.runtime.decoders import DECODERS

    unknown_dec = [d for d in decoders if d not in DECODERS]
    if unknown_dec or not decoders:
        raise ValueError(f"unknown decoders {unknown_dec}; known: {tuple(DECODERS)}")
    noise = noise_conditions()
    known = known_conditions()
    with_fisheye = fisheye_model is not None or "classical" in decoders
    conditions = conditions or [c for c in known if c != "fisheye_standard" or with_fisheye]
    unknown = [c for c in conditions if c not in known]
    if unknown:
        raise ValueError(f"unknown conditions {unknown}; known: {known}")
    geometry = lens_geometry(bench.lens)
    nominal = lens_tensor(bench.lens)
    config = classical_config or ClassicalConfig()
    if "learned" in decoders and learned_model is None:
        from bmi_sdk.runtime.model import LEARNED_MODEL

        learned_model = LEARNED_MODEL
    models = _decoders(decoders, model_path, PsfMap(nominal, geometry, mode="tensor"), config, bench.threads,
                       bench.tile_px, learned_model, learned_fusion)

    def calibrated(psf_map):
        out = [ClassicalTiles(psf_map, config, "classical_calibrated")] if "classical" in decoders else []
        if "learned" in decoders:
            out.append(NetworkTiles(learned_model, bench.tile_px, bench.threads, psf_map, "learned_calibrated",
                                    fuse=learned_fusion))
        return out

    rows: list[dict] = []
    renders = None
    for name in [c for c in conditions if c in noise]:
        renders = renders or bench.renders(nominal, progress)
        for model in models:
            rows += score(model, renders, bench, noise[name], name)
    for name in [c for c in conditions if c in HARDWARE]:
        camera = BuiltCamera(bench.lens, HARDWARE[name])
        renders_p = bench.renders(camera.psf_tensor(), progress, zone_px=camera.render_zone_px("tensor"))
        for model in models + calibrated(camera.psf_map(mode="tensor")):
            rows += score(model, renders_p, bench, STANDARD_SIGMA, name)
    for name in [c for c in conditions if c in EXACT]:
        camera = BuiltCamera(bench.lens, EXACT[name])
        renders_p = bench.renders(camera.psf_tensor(), progress, psf_mode="exact",
                                  zone_px=camera.render_zone_px("exact"))
        for model in models + calibrated(camera.psf_map(mode="exact", centre_calibrated=True)):
            rows += score(model, renders_p, bench, STANDARD_SIGMA, name)
    if "fisheye_standard" in conditions:
        fb = Benchmark(lens="fisheye", tiles=bench.tiles, tile_px=bench.tile_px, seed=bench.seed, threads=bench.threads,
                       scheduler=bench.scheduler, scene_scale=bench.scene_scale)
        from dataclasses import replace

        fisheye_tensor = lens_tensor("fisheye")
        fisheye_models = _decoders(decoders, fisheye_model,
                                   PsfMap(fisheye_tensor, lens_geometry("fisheye"), mode="tensor"),
                                   replace(config, window_px=classical_window_px("fisheye", config.window_px)),
                                   bench.threads, bench.tile_px)
        fisheye_renders = fb.renders(fisheye_tensor, progress)
        for model in fisheye_models:
            rows += score(model, fisheye_renders, fb, STANDARD_SIGMA, "fisheye_standard")
    return rows
