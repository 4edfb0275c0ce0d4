"""The synthetic benchmark behind ``bmi eval``: the paper's table analogues on fixed, seeded tiles.

Benchmark: ``tiles`` procedural scenes per field region, each a ``tile_px``²
window (+ a margin of half a kernel, rendered and cut away; a wider kernel's
margin is the scene's mirror continuation, ``data.SCENE_MARGIN_PX``, so every
optical system scores the very same content on each tile) whose centre is
drawn with the seed: **centre** = θ ∈ [0°, 20°], **edge** = θ ∈ [52°, 58°]
(its pixels span the 50–60° band; those beyond 60° are invalid). Metrics
(``metrics``) are per tile on valid pixels, averaged over the tiles of a region;
every row also breaks its depth error down by range band, by distance to a
depth edge and by the pixel's noiseless signal at the sensor, with the confident
coverage and the σ's honesty (``eval_strata``).

Scene scale: each tile is the centre of a scene drawn ``scene_scale`` × larger
than the window, so its objects are that much larger against the tile. ``bmi eval``
runs at ``PAPER_SCENE_SCALE`` (4: the seed paper places a 640-px NYU image in
~12° of field, ~750 sensor px, a scale of 3–4); ×1 (a whole room in one tile:
95 % of pixels within 32 px of a depth step) is its stress test and ×16 its
large-surface case (``SCENE_SCALES``). ``Benchmark()`` itself defaults to ×1, the
tile set the ``bmi bench`` targets read.

Decoders are the registry's (``runtime.decoders``): each is opened once per camera
with ``open_decoder`` and fed, tile by tile, the ``devices.RawFrame`` a camera reading
that tile's ROI would deliver (``tile_frame``): raw DN, black and white level, the
sensor geometry with the ROI offsets, RGGB and the noise profile of the σ it was
given. So a tile is decoded exactly as ``bmi infer`` decodes a frame of that size.
The camera a decoder is opened on is a ``BenchmarkCamera``: a ``BuiltCamera`` whose
kernels are the ones the tiles were rendered with (the design's rotated tensor, or
a built camera's exact kernels with its optical centre calibrated).

A condition is what changes between capture and the fixed decoders:

* noise σ (the sensor stage; ``ideal`` = σ 0, still 12-bit quantised,
  ``standard`` = 0.005, ``noise_<σ>`` the sweep);
* the scene's texture statistics (``natural_textures``: the same tiles, layout,
  colours and ranges, with each surface's texture power spectrum 1/f^p, p drawn
  about 2 with std 0.4 as natural images' exponents scatter, where ``standard``'s
  are all 1/f², the likelihood's prior; σ 0.005);
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
* ``built_camera_sampled``: ``cameras`` built cameras drawn from the calibration's
  error prior, each calibrated by the real fit on simulated point-source captures
  (``nn.sampled_cameras``), rendered like ``EXACT`` with its true errors and read
  with its *fitted* ones; its rows average over the cameras. Cost: each camera's
  capture and fit (~35 s median, up to ~150 s, on 2 cores; once per process), its
  exact renders and its decoders' exact kernels (traced once, then disk-cached);
* another optical system (``fisheye_standard``: the fisheye lens and its plane
  sensor, read by every requested decoder with a model for that lens).

Every decoder reads each condition with the design camera's kernels (its row named
by its kind); one whose decode reads its camera's kernels (its report names the
camera: ``classical``, ``learned``, ``evidence``) also reads a hardware condition
with the built camera's own kernels (``<kind>_calibrated``: a perfect calibration,
or for ``built_camera_sampled`` the fitted one).

Every other condition renders with ``psf_mode="tensor"`` (the paper's
rotated radial tensor), which by itself differs from the exact kernels
(``render.psf_map``). So decenter and tilt are to be read against
``nominal_exact``, the design rendered by the same exact renderer at the
same σ (0.005), not against ``standard``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bmi_sdk.built_camera import BuiltCamera
from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.metrics import depth_metrics, image_metrics, mean_metrics
from bmi_sdk.nn.data import (
    SCENE_MARGIN_PX,
    STANDARD_SIGMA,
    mirror_extend,
    render_margin_px,
    sample_window,
    scene_crop,
    simulate_raw,
)
from bmi_sdk.nn.eval_strata import StrataSums, edge_distance_px
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
SCENE_DRAW_BYTES_PER_PX = 28
"""Peak memory of drawing a procedural scene (``scenes.generate_scene``) per scene pixel: 112 MB at 1024² and 513 MB at
4096² (``ru_maxrss``, 71 MB of it the imports), 26 B for each added pixel."""

PAPER_SCENE_SCALE = 4.0
"""``bmi eval``'s scene scale: the seed paper's (a 640-px NYU image in ~12° of field, ~750 sensor px)."""
SCENE_SCALES = {1.0: "stress test", 4.0: "paper", 16.0: "large surfaces"}
"""The named scene scales (``bmi eval --scales 1,4,16``): ×1 draws a whole room into one tile."""
SAMPLED = "built_camera_sampled"
"""The condition of built cameras drawn from the error prior and read with their fitted calibration."""
NATURAL = "natural_textures"
"""The condition of the same tiles with each surface's texture power exponent drawn about 2 (``Benchmark.
texture_spread`` = ``NATURAL_TEXTURE_SPREAD``), design camera, σ 0.005."""
NATURAL_TEXTURE_SPREAD = 0.4
"""The std of natural images' power-spectrum exponents about 2 (van der Schaaf & van Hateren, Vision Research 36,
1996)."""

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
    """Every condition name, in the default order."""
    return [*noise_conditions(), NATURAL, *HARDWARE, *EXACT, SAMPLED, "fisheye_standard"]


@dataclass(frozen=True)
class Benchmark:
    lens: str = "bmi_monocentric"
    tiles: int = 12
    tile_px: int = 192
    seed: int = 20260
    threads: int = 2
    scheduler: str | None = None  # renders on Dask (``scaleout``: local:N or tcp://HOST:PORT); None: here
    scene_scale: float = 1.0  # > 1: each tile's scene is drawn this much larger and its centre kept (``scene``);
    #                           bmi eval runs at PAPER_SCENE_SCALE
    texture_exponent: str = "prior"  # the decoders that take one read with this texture model
    #                                  (``decode.classical.TEXTURE_EXPONENTS``; ``DecoderOptions.texture_exponent``)
    texture_spread: float = 0.0  # the std about 2 of each surface's texture power exponent (``generate_scene``'s
    #                              ``exponent_spread``; 0: every surface 1/f²; the ``natural_textures`` condition's)

    def __post_init__(self):
        if not 0.0 <= self.texture_spread <= 1.0:
            raise ValueError(f"texture_spread must be in [0, 1], got {self.texture_spread}")
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
        from bmi_sdk.decode.classical import TEXTURE_EXPONENTS

        if self.texture_exponent not in TEXTURE_EXPONENTS:
            raise ValueError(f"benchmark texture_exponent must be one of {', '.join(TEXTURE_EXPONENTS)}, got "
                             f"{self.texture_exponent!r}")

    @property
    def margin_px(self) -> int:
        return render_margin_px(self.lens)

    def scene_bytes(self) -> float:
        """Peak memory of drawing one tile's scene (``scene``): ``SCENE_DRAW_BYTES_PER_PX`` per pixel of a scene
        ``scene_scale`` × the drawn window."""
        side = (self.tile_px + 2 * SCENE_MARGIN_PX) * self.scene_scale
        return SCENE_DRAW_BYTES_PER_PX * side * side

    def renders_bytes(self) -> float:
        """Memory of every tile's render, held while the decoders read them (``renders``): the float32 optical window
        (tile + margin, 3 colours) and the tile's scene colour, range, edge distance and signal."""
        window = self.tile_px + 2 * self.margin_px
        per_tile = 4 * (3 * window * window + 6 * self.tile_px * self.tile_px)
        return float(len(REGIONS) * self.tiles * per_tile)

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
                                  np.random.default_rng([self.seed, 7, list(REGIONS).index(region), i]),
                                  exponent_spread=self.texture_spread)
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
    """Scene, optical image, position, distance to the nearest depth edge (``eval_strata.edge_distance_px``, over
    the whole rendered window, so a step just outside the tile counts) and the tile's noiseless signal at the sensor
    (the optical image's mean over colours, for ``eval_strata``'s signal bands) of one benchmark window (region, tile
    index, row0, col0)."""
    from bmi_sdk.render import render_coded

    bench, geometry = state["bench"], state["geometry"]
    size, m = bench.tile_px + 2 * bench.margin_px, bench.margin_px
    region, i, row0, col0 = window
    rgb, range_m = bench.scene(region, i)
    optical = render_coded(rgb, range_m, state["tensor"], geometry, row0=row0, col0=col0, psf_map=state["psf_map"],
                           zone_px=state["zone_px"])
    optical *= relative_illumination(geometry, row0, col0, size, size)[..., None]
    return {"region": region, "tile": i, "row0": row0 + m, "col0": col0 + m, "optical_full": optical,
            "rgb": rgb[m:-m, m:-m], "range_m": range_m[m:-m, m:-m],
            "edge_distance_px": edge_distance_px(range_m)[m:-m, m:-m].astype(np.float32),
            "signal": optical[m:-m, m:-m].mean(axis=2)}


@dataclass(frozen=True)
class BenchmarkCamera(BuiltCamera):
    """A ``BuiltCamera`` whose kernels (``psf_map``) are those the benchmark renders its tiles with.

    ``kernel_mode="tensor"``: the design's rotated radial tensor (or a built lens's tensor, ``HARDWARE``), as every
    condition but ``EXACT``'s renders; ``"exact"`` with ``centre_calibrated``: a built lens traced at each zone with
    its on-axis landing shift taken out, as ``EXACT`` and ``built_camera_sampled`` render. A registered decoder opened
    on it (``open_tiles``) reads the tiles through the render's own kernel model, so a row measures the decoder and
    the camera's errors, not a render-model mismatch. Its identity (``to_dict``, ``sha256``) includes both fields."""

    kernel_mode: str = "tensor"
    centre_calibrated: bool = False

    def psf_map(self, mode: str | None = None, centre_calibrated: bool = False, disk_cache: bool = False):
        return super().psf_map(mode or self.kernel_mode, centre_calibrated or self.centre_calibrated, disk_cache)

    def to_dict(self) -> dict:
        return super().to_dict() | {"kernel_mode": self.kernel_mode, "centre_calibrated": self.centre_calibrated}


def tile_frame(raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile, lens_name: str,
               frame_id: int = 0):
    """The ``devices.RawFrame`` a camera reading a ROI of the sensor at (``row0``, ``col0``) delivers for the raw tile
    ``raw`` (H × W DN): the benchmark's black and white level, the full sensor ``geometry`` with the ROI's offsets,
    RGGB, the lens name and the ``noise`` profile the tile was taken at (as a DNG's NoiseProfile tag carries it)."""
    from devices.frame import FrameStatus, RawFrame, Roi

    height, width = raw.shape
    return RawFrame(data=raw, frame_id=frame_id, status=FrameStatus.COMPLETE, black_level_dn=BLACK_LEVEL_DN,
                    white_level_dn=WHITE_LEVEL_DN, exposure_us=0, analog_gain=1.0, temperature_c=25.0,
                    device_timestamp_ns=0, readout_timestamp_ns=0, host_timestamp_ns=0,
                    roi=Roi(x_px=col0, y_px=row0, width_px=width, height_px=height), geometry=geometry,
                    lens={"name": lens_name}, device={"model": "bmi eval benchmark"}, cfa=CFA_PATTERN,
                    noise_profile=noise)


class FrameTiles:
    """A registered decoder (``runtime.decoders.Decoder``) as a benchmark decoder: raw tile in (``tile_frame``),
    ``Decoder.decode`` on it, (AiF H × W × 3, depth, 1σ or None) out. ``name`` labels its rows."""

    def __init__(self, decoder, name: str):
        self.decoder = decoder
        self.name = name

    def __call__(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        out = self.decoder.decode(tile_frame(raw, geometry, row0, col0, noise, self.decoder.camera.lens_name))
        return out.aif, out.depth_m, out.depth_sigma_m


NETWORK_MARGIN_PX = 128
"""A benchmark tile is read as a frame of its size, whose border the runtime pads by half the network's receptive
field (48 px for the shipped models, ``runtime.tiling.TilePlan``): a network tile this much larger than the benchmark
tile holds the padded frame, so the network runs once per tile and reads each pixel as ``bmi infer``'s 512-px tiles
do, on a third of their pixels."""


def reads_camera(decoder) -> bool:
    """Whether a decoder's read depends on its camera's kernels: its report names the camera (``Decoder.head``), as
    the classical, learned and evidence decoders' do; the end-to-end network's reads every camera alike."""
    return "camera" in decoder.head()


def evidence_window_px(decoder) -> int | None:
    """The evidence window (px) of a decoder with a classical stage (``stage``, a ``decode.ClassicalDecoder``), else
    None."""
    config = getattr(getattr(decoder, "stage", None), "config", None)
    return getattr(config, "window_px", None)


def open_tiles(kinds, camera: BuiltCamera, models: dict, config, bench: "Benchmark", suffix: str = "",
               skip_missing: bool = False) -> list[FrameTiles]:
    """The registry's decoders of ``kinds`` opened once on ``camera`` (``open_decoder``), each as a ``FrameTiles``
    named ``kind + suffix``: ``models`` maps a kind to its model (a path or a loaded one; a kind without one reads its
    packaged model for the camera's lens), ``config`` goes to the decoders that take a ``ClassicalConfig``, and the
    networks run with ``bench.threads`` threads on network tiles of ``bench.tile_px + NETWORK_MARGIN_PX``; the
    decoders that take a texture model read with ``bench.texture_exponent``, the others with their own.
    ``skip_missing`` leaves out a kind that has no model for the lens (``ModelError``), as the fisheye has no learned
    refinement."""
    from bmi_sdk.model_manifest import ModelError
    from bmi_sdk.runtime.decoders import DECODERS, DecoderOptions, open_decoder

    out = []
    for kind in kinds:
        texture = bench.texture_exponent if DECODERS[kind].takes_texture_exponent else "prior"
        options = DecoderOptions(tile_px=bench.tile_px + NETWORK_MARGIN_PX, threads=bench.threads,
                                 texture_exponent=texture)
        try:
            decoder = open_decoder(camera, kind, models.get(kind), config if DECODERS[kind].takes_config else None,
                                   options)
        except ModelError:
            if skip_missing:
                continue
            raise
        out.append(FrameTiles(decoder, kind + suffix))
    return out


def calibrated_tiles(tiles: list[FrameTiles], camera: BuiltCamera, config, bench: "Benchmark") -> list[FrameTiles]:
    """``tiles``' decoders that read their camera's kernels (``reads_camera``), opened again on ``camera`` with the
    same models, named ``<kind>_calibrated``."""
    kept = [t.decoder for t in tiles if reads_camera(t.decoder)]
    models = {d.kind: d.model for d in kept if d.model is not None}
    return open_tiles([d.kind for d in kept], camera, models, config, bench, "_calibrated")


class ClassicalTiles:
    """The classical decoder (``bmi_sdk.decode``) over any ``psf_map`` as a benchmark decoder: raw tile in, AiF + depth
    + 1σ out. The ``bmi bench`` targets use it to score decoder knobs and kernel models the registry does not name.
    """

    name = "classical"

    def __init__(self, psf_map, config=None, name: str = "classical"):
        from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder

        self.decoder = ClassicalDecoder.for_psf_map(psf_map, config or ClassicalConfig())
        self.name = name

    def __call__(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        out = self.decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, noise_profile=noise)
        return out.aif, out.depth_m, out.depth_sigma_m


class NetworkTiles:
    """A learned refinement's stages taken apart, for what measures them one by one (``bmi bench learned``,
    ``bmi bench aif-step``, ``bmi fit-fusion``): its classical read of a raw tile, its network's own read, their
    fusion and the AiF's consistency step. Each is the runtime's own function (``runtime.pipeline.infer_raw`` with
    the stage's channels, ``runtime.learned.fuse_into`` and ``consistent_aif``), so a stage reads a tile exactly as
    ``bmi infer --decoder learned`` reads a frame; ``bmi eval`` runs the decoder whole (``FrameTiles``).

    ``tile_px``: the side of the tiles it reads (its network runs on tiles ``NETWORK_MARGIN_PX`` larger, as
    ``open_tiles``'); ``psf_map``: the kernels the classical stage believes in (the nominal camera's, or a built
    camera's own); ``fuse=False`` leaves the manifest's fusion weights unread (``network_read`` then returns the
    network's own read).
    """

    def __init__(self, path: str | Path, tile_px: int, threads: int = 2, psf_map=None, fuse: bool = True):
        from bmi_sdk.decode import ClassicalDecoder
        from bmi_sdk.model_io import INPUT_CHANNELS
        from bmi_sdk.runtime.learned import model_classical_config
        from bmi_sdk.runtime.model import Model

        self.model = Model(path, tile_px=tile_px + NETWORK_MARGIN_PX, threads=threads, read_fusion_weights=fuse)
        if self.model.input_channels <= INPUT_CHANNELS:
            raise ValueError(f"model {self.model.path.name} is not a learned refinement: it has no classical read to "
                             "fuse with (bmi train --decoder learned)")
        self.fuse = fuse
        self.stage = ClassicalDecoder.for_psf_map(psf_map, model_classical_config(self.model, threads))

    def classical_read(self, raw: np.ndarray, geometry, row0: int, col0: int, noise: NoiseProfile):
        """The first stage: the classical decode (``DecodeResult``) of a raw tile with the model's knobs."""
        return self.stage.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, noise_profile=noise)

    def network_read(self, raw: np.ndarray, geometry, row0: int, col0: int, decoded, fuse: bool | None = None):
        """(AiF H × W × 3, depth, 1σ) of the network on a raw tile with ``decoded``'s channels (``infer_raw``); when
        ``fuse`` (default: this object's), its depth fused with ``decoded``'s and its AiF made consistent with the
        tile at that depth, as ``bmi infer`` returns them."""
        from bmi_sdk.decode.features import FeatureTiles
        from bmi_sdk.runtime.pipeline import infer_raw

        net = infer_raw(self.model, raw, black_level_dn=BLACK_LEVEL_DN, white_level_dn=WHITE_LEVEL_DN,
                        cfa=CFA_PATTERN, geometry=geometry, row0=row0, col0=col0,
                        extra=FeatureTiles(decoded, self.stage.config.stride_px))
        aif, depth, sigma = net.aif, net.depth_m, net.depth_sigma_m
        if (self.fuse if fuse is None else fuse) and sigma is not None:
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


def tile_raw(bench: Benchmark, item: dict, k: int, sigma: float) -> np.ndarray:
    """The raw frame of rendered tile ``k`` (``Benchmark.renders``) at noise σ: the same draw for every decoder."""
    m, t = bench.margin_px, bench.tile_px
    rng = np.random.default_rng([bench.seed, 99, k, int(round(sigma * 1e6))])
    return simulate_raw(item["optical_full"][m:m + t, m:m + t], sigma, rng, item["row0"], item["col0"])


def score_tiles(model, renders: list[dict], bench: Benchmark, sigma: float, into: dict | None = None) -> dict:
    """Decode every rendered tile at noise σ and add its scores to ``into`` (region → (per-tile metric dicts,
    ``eval_strata.StrataSums``)); returns ``into``. Scoring several cameras' tiles into one ``into`` averages their
    rows over the cameras.

    ``model`` is called as ``model(raw, geometry, row0, col0, noise)`` (``FrameTiles``, ``ClassicalTiles``) with the
    tile's raw frame and the ``NoiseProfile`` of the noise it was given (decoders that read noise use it, as they
    would a frame's DNG tag), and returns (AiF, depth, 1σ or None)."""
    into = {} if into is None else into
    geometry = lens_geometry(bench.lens)
    t = bench.tile_px
    noise = NoiseProfile.additive(sigma)  # the camera's noise is known (its photon transfer); decoders may use it
    for k, item in enumerate(renders):
        raw = tile_raw(bench, item, k, sigma)
        valid = geometry.valid_mask(item["row0"], item["col0"], t, t) & np.isfinite(item["range_m"])
        aif_hwc, depth_m, depth_sigma_m = model(raw, geometry, item["row0"], item["col0"], noise)
        valid &= np.isfinite(depth_m)
        tiles, strata = into.setdefault(item["region"], ([], StrataSums()))
        tiles.append(depth_metrics(depth_m, item["range_m"], valid) | image_metrics(aif_hwc, item["rgb"], valid))
        strata.add(depth_m, item["range_m"], valid, depth_sigma_m, item["edge_distance_px"], item["signal"])
    return into


def region_rows(scores: dict, condition: str, decoder: str, bench: Benchmark, extra: dict | None = None) -> list[dict]:
    """One row per region of ``score_tiles``' ``scores``: {condition, decoder, region, scene_scale, the per-tile
    metrics averaged over the region's tiles, ``absrel_se`` (``tile_standard_error`` of the AbsRel),
    ``tile_absrel`` (each tile's AbsRel in scoring order, for ``eval_paired``), the ``eval_strata`` breakdown,
    ``extra``}."""
    return [{"condition": condition, "decoder": decoder, "region": region, "scene_scale": bench.scene_scale,
             **mean_metrics(tiles), "absrel_se": tile_standard_error([t["absrel"] for t in tiles]),
             "tile_absrel": [t["absrel"] for t in tiles],
             **strata.summary(), **(extra or {})}
            for region, (tiles, strata) in scores.items()]


def tile_standard_error(values: list[float]) -> float:
    """The standard error of a mean over tiles, s / √n (s the tiles' sample standard deviation, NaN tiles left
    out): how far another draw of as many tiles would move the row, the benchmark's own sampling uncertainty. NaN
    with fewer than two tiles."""
    finite = np.asarray(values, np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size < 2:
        return math.nan
    return float(finite.std(ddof=1) / math.sqrt(finite.size))


def score(model, renders: list[dict], bench: Benchmark, sigma: float, condition: str) -> list[dict]:
    """Rows {condition, decoder, region, metrics…} for one condition over pre-rendered tiles (``score_tiles``,
    ``region_rows``). Decoders that report a depth 1σ add the confident coverage and ``sigma_z_rms`` /
    ``sigma_z_std``: the RMS and the standard deviation of z = (depth error / reported 1σ) over the region's
    scored pixels (1 for an honest σ)."""
    return region_rows(score_tiles(model, renders, bench, sigma), condition, getattr(model, "name", "cnn"), bench)


def models_by_kind(paths, decoders: tuple[str, ...], option: str) -> dict:
    """{kind: path} of ONNX models (None, one path or several), each the model of the decoder kind its manifest
    names (``runtime.decoders.decoder_kind``); refused, naming ``option``, when that decoder is not run or named
    twice."""
    from bmi_sdk.runtime.decoders import decoder_kind

    out: dict = {}
    for path in [] if paths is None else [paths] if isinstance(paths, (str, Path)) else list(paths):
        kind = decoder_kind(model=path)
        if kind not in decoders:
            raise ValueError(f"{option} {path} is a model of the {kind} decoder, and the decoders run are "
                             f"{', '.join(decoders)}")
        if kind in out:
            raise ValueError(f"{option} names two models of the {kind} decoder: {out[kind]} and {path}")
        out[kind] = Path(path)
    return out


def check_windows(tiles: list[FrameTiles], bench: Benchmark) -> None:
    """Refuse a benchmark whose tiles hold no evidence window of a decoder: its depth there would be a guess."""
    for t in tiles:
        window_px = evidence_window_px(t.decoder)
        if window_px is not None and bench.tile_px < window_px:
            raise ValueError(f"benchmark tile_px {bench.tile_px} holds no {window_px}-px evidence window of the "
                             f"{t.decoder.kind} decoder on lens {bench.lens}: its depth would be a guess")


def run_benchmark(model=None, bench: Benchmark = Benchmark(), conditions: list[str] | None = None,
                  fisheye_model=None, progress: bool = True, decoders: tuple[str, ...] = (DEFAULT_DECODER,),
                  classical_config=None, cameras: int | None = None) -> list[dict]:
    """Every requested condition (default: all of ``known_conditions``) for every requested decoder kind (the
    registry's, ``runtime.decoders.DECODERS``).

    ``model`` / ``fisheye_model``: None, an ONNX path or several, each the model of the decoder its manifest names
    on the BMI / fisheye lens (``models_by_kind``); a decoder without one reads its packaged model for the lens
    (on the fisheye, a decoder with none is left out). ``classical_config``: the ``ClassicalConfig`` of the decoders
    that take one (default theirs). ``cameras``: how many cameras ``built_camera_sampled`` averages over (default
    ``sampled_cameras.SAMPLED_CAMERAS``). Rows: module doc; every row carries ``scene_scale``.
    """
    from bmi_sdk.runtime.decoders import DECODERS

    decoders = tuple(decoders)
    unknown_dec = [d for d in decoders if d not in DECODERS]
    if unknown_dec or not decoders:
        raise ValueError(f"unknown decoders {unknown_dec}; known: {tuple(DECODERS)}")
    known = known_conditions()
    explicit = conditions is not None
    conditions = list(conditions) if explicit else known
    unknown = [c for c in conditions if c not in known]
    if unknown:
        raise ValueError(f"unknown conditions {unknown}; known: {known}")
    models = models_by_kind(model, decoders, "model")
    fisheye_models = models_by_kind(fisheye_model, decoders, "fisheye model")
    design = BenchmarkCamera(bench.lens)
    base = open_tiles(decoders, design, models, classical_config, bench)
    check_windows(base, bench)
    noise = noise_conditions()
    rows: list[dict] = []
    renders = None
    for name in [c for c in conditions if c in noise]:
        renders = renders or bench.renders(design.psf_tensor(), progress)
        for tiles in base:
            rows += score(tiles, renders, bench, noise[name], name)
    if NATURAL in conditions:
        natural = replace(bench, texture_spread=NATURAL_TEXTURE_SPREAD)
        renders_n = natural.renders(design.psf_tensor(), progress)
        for tiles in base:
            rows += score(tiles, renders_n, natural, STANDARD_SIGMA, NATURAL)
    for name in [c for c in conditions if c in HARDWARE]:
        camera = BenchmarkCamera(bench.lens, HARDWARE[name])
        renders_p = bench.renders(camera.psf_tensor(), progress, zone_px=camera.render_zone_px("tensor"))
        for tiles in base + calibrated_tiles(base, camera, classical_config, bench):
            rows += score(tiles, renders_p, bench, STANDARD_SIGMA, name)
    for name in [c for c in conditions if c in EXACT]:
        camera = BenchmarkCamera(bench.lens, EXACT[name], kernel_mode="exact", centre_calibrated=True)
        renders_p = bench.renders(camera.psf_tensor(), progress, psf_mode="exact", zone_px=camera.render_zone_px("exact"))
        for tiles in base + calibrated_tiles(base, camera, classical_config, bench):
            rows += score(tiles, renders_p, bench, STANDARD_SIGMA, name)
    if SAMPLED in conditions:
        rows += sampled_rows(base, bench, classical_config, cameras, progress)
    if "fisheye_standard" in conditions:
        rows += fisheye_rows(decoders, fisheye_models, bench, classical_config, progress, explicit)
    return rows


def sampled_rows(base: list[FrameTiles], bench: Benchmark, classical_config, cameras: int | None,
                 progress: bool) -> list[dict]:
    """``built_camera_sampled``: each sampled camera (``nn.sampled_cameras``) rendered with its true errors (exact
    kernels, optical centre calibrated) and read by ``base`` (the design's kernels) and by the decoders that read
    their camera opened on its *fitted* errors (``<kind>_calibrated``); rows average over the cameras and carry
    ``cameras``."""
    from bmi_sdk.nn.sampled_cameras import SAMPLED_CAMERAS, sampled_cameras

    count = SAMPLED_CAMERAS if cameras is None else cameras
    scores: dict[str, dict] = {}
    for sampled in sampled_cameras(count, bench.seed, bench.lens):
        truth = BenchmarkCamera(bench.lens, sampled.truth, kernel_mode="exact", centre_calibrated=True)
        fitted = BenchmarkCamera(bench.lens, sampled.fitted, kernel_mode="exact", centre_calibrated=True)
        renders = bench.renders(truth.psf_tensor(), progress, psf_mode="exact", zone_px=truth.render_zone_px("exact"))
        for tiles in base + calibrated_tiles(base, fitted, classical_config, bench):
            score_tiles(tiles, renders, bench, STANDARD_SIGMA, scores.setdefault(tiles.name, {}))
    return [row for name, by_region in scores.items()
            for row in region_rows(by_region, SAMPLED, name, bench, {"cameras": count})]


def fisheye_rows(decoders: tuple[str, ...], models: dict, bench: Benchmark, classical_config, progress: bool,
                 required: bool) -> list[dict]:
    """``fisheye_standard``: the fisheye lens and its plane sensor at σ 0.005, read by every decoder of ``decoders``
    with a model for that lens (``models`` or its packaged one), the classical ones with a window that holds its
    kernel (``runtime.classical.classical_decoder`` widens a narrower one). ``required``: refuse, when no decoder
    can read it, instead of leaving it out."""
    fisheye = replace(bench, lens="fisheye")
    tiles = open_tiles(decoders, BenchmarkCamera("fisheye"), models, classical_config, fisheye, skip_missing=True)
    if not tiles:
        if required:
            raise ValueError(f"fisheye_standard: none of the decoders {', '.join(decoders)} has a model for the "
                             "fisheye lens (give one with --fisheye-model)")
        return []
    check_windows(tiles, fisheye)
    renders = fisheye.renders(lens_tensor("fisheye"), progress)
    return [row for t in tiles for row in score(t, renders, fisheye, STANDARD_SIGMA, "fisheye_standard")]
