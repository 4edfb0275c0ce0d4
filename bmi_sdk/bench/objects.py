"""`bmi bench objects`: textured objects before a wall, every surface with natural images' texture statistics.

Scenes like a user's, for the decoders' depth edges and σ: a wall 4–8 m away and ``OBJECTS`` discs and boxes 0.9–3.5 m
away, 40–200 px across (the objects of `bmi eval`'s tiles at the paper's scale, ×3–4), drawn far to near so that
nearer ones occlude. Every surface carries its own texture of power spectrum 1/f^p about its own mean colour
(``surface_texture``), at its own contrast: objects ``OBJECT_CONTRAST``, the wall ``WALLS`` (textured; weak, where the
honest read is a wide σ; weak and lit by a lamp near it, ``lamp_irradiance``). p is 2 on every surface (natural
images' average, the likelihood's prior) or scattered about 2 as natural images' exponents are
(``EXPONENT_SPREADS``). 384² px at φ 30°, σ 0.005, rendered and decoded with the design camera's exact kernels (the
simulated device's and ``bmi infer``'s path). Per textures, wall, field angle and decoder (the default evidence
decoder, the classical one, the evidence decoder with a wider support read, ``WIDE_SUPPORT``, the evidence decoder
with the texture's exponent profiled where the evidence asks for it, ``PROFILED_EXPONENT``, and the evidence decoder
with its weak-texture gate off, every window scored on every bin: ``decode.classical.window_groups``), over ``SEEDS``
scenes (``--full``: ``FULL_SEEDS``) pooled: AbsRel, within ``EDGE_NEAR_PX`` of a depth edge and beyond it, on the wall
beyond it, δ1, σ's honesty (std of error/σ, 1 for an honest σ, and the share within one σ, 0.683) and the confident
coverage (σ ≤ 10 % of the depth).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from . import markdown_table, register_target

SIZE_PX = 384
OBJECTS = (3, 7)
"""Objects per scene: drawn uniformly from [3, 7)."""
OBJECT_HALF_PX = (20.0, 100.0)
OBJECT_RANGE_M = (0.9, 3.5)
WALL_RANGE_M = (4.0, 8.0)
OBJECT_CONTRAST = (0.2, 0.5)
"""Range of each object texture's std relative to its mean colour."""
LAMP_DISTANCE_PX = 300.0
"""A lamp-lit wall's lamp: its distance from the wall in the wall's pixels (about 0.5 m from a wall 5 m away)."""


@dataclasses.dataclass(frozen=True)
class Wall:
    """A scene's wall: its texture's std relative to its mean colour, and whether a lamp near it lights it
    (``lamp_irradiance``) rather than an even light."""

    contrast: float
    lamp: bool = False


WALLS = {"textured wall": Wall(0.3), "weak wall": Wall(0.03), "weak wall, lamp-lit": Wall(0.03, lamp=True)}
"""The walls each scene is drawn with. A weakly textured wall is where the honest read is a wide σ; lit by a lamp, its
smooth shading puts far more power into each window's lowest frequencies than its texture does."""
MEAN_COLOUR = (0.08, 0.6)
"""Range of a surface's mean linear colour, per channel."""
EXPONENT_SPREADS = {"1/f²": 0.0, "1/f^(2 ± 0.4)": 0.4}
"""Std of each surface's power-spectrum exponent about 2: every surface the prior's 1/f², or scattered as natural
images' exponents are (about ±0.4 from one image to the next; van der Schaaf & van Hateren, Vision Research 36,
1996)."""
CHANNEL_CORRELATION = 0.9
"""Correlation of a texture's colour channels: natural images' texture is mostly luminance, their colour channels
strongly correlated (Ruderman, Cronin & Chiao, J. Opt. Soc. Am. A 15, 1998, for the cone responses)."""
WIDE_SUPPORT = {"radius_windows": 3, "spatial_sigma_windows": 2.0, "spread_scale": 0.2}
"""A support read that reaches the like-coloured windows inside an object from its rim (docs/decoder.md, the evidence
decoder's step 3), measured beside the shipped one."""
PROFILED_EXPONENT = "profiled"
"""The evidence decoder with ``bmi infer --texture-exponent profiled`` (``decode.classical.TEXTURE_EXPONENTS``: each
pool's texture exponent profiled where its pooled evidence rejects the prior's 1/f²), measured beside the shipped
stage, whose prior is 1/f² only."""
FIELDS_DEG = (5.0, 45.0)
SEEDS = (0, 1)
FULL_SEEDS = tuple(range(6))


def surface_texture(size: int, rng: np.random.Generator, contrast: float, power_exponent: float = 2.0) -> np.ndarray:
    """(size, size, 3) linear RGB: a mean colour (``MEAN_COLOUR``) times (1 + ``contrast`` × a unit-std field of power
    spectrum 1/f^``power_exponent`` per channel, the channels correlated by ``CHANNEL_CORRELATION``), clipped to
    [0.005, 1]."""
    from bmi_sdk.scenes.procedural import pink_noise

    colour = rng.uniform(*MEAN_COLOUR, 3)
    amplitude_exponent = power_exponent / 2.0
    shared = pink_noise((size, size), rng, exponent=amplitude_exponent)
    field = np.stack([np.sqrt(CHANNEL_CORRELATION) * shared
                      + np.sqrt(1.0 - CHANNEL_CORRELATION) * pink_noise((size, size), rng, exponent=amplitude_exponent)
                      for _ in range(3)], axis=-1)
    return np.clip(colour * (1.0 + contrast * field), 0.005, 1.0).astype(np.float32)


def lamp_irradiance(size: int, rng: np.random.Generator) -> np.ndarray:
    """(size, size) the irradiance of a wall lit by a point lamp ``LAMP_DISTANCE_PX`` from it, its foot drawn
    uniformly over the wall, relative to its mean: h / (h² + r²)^(3/2) (inverse square times the incidence cosine),
    r the distance from the lamp's foot."""
    rows, cols = np.mgrid[0:size, 0:size] + 0.5
    foot_row, foot_col = rng.uniform(0, size, 2)
    h = LAMP_DISTANCE_PX
    irradiance = h / (h * h + (rows - foot_row) ** 2 + (cols - foot_col) ** 2) ** 1.5
    return irradiance / irradiance.mean()


def object_scene(seed: int, wall: Wall, exponent_spread: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, range_m) of ``SIZE_PX`` + 2 ``PLANE_MARGIN_PX`` square: ``wall`` (its texture contrast; lit by a lamp,
    ``lamp_irradiance``, or evenly) and the objects of ``seed`` before it (module doc), each surface's power exponent
    drawn from a normal law about 2 of std ``exponent_spread`` (from a generator of its own, so the same seed gives
    the same objects, colours and ranges for every wall and spread)."""
    from .decoder import PLANE_MARGIN_PX

    size = SIZE_PX + 2 * PLANE_MARGIN_PX
    rng = np.random.default_rng(seed)
    wall_rng = np.random.default_rng([seed, 1])
    exponent_rng = np.random.default_rng([seed, 2])
    exponent = lambda: 2.0 + exponent_spread * exponent_rng.standard_normal()  # noqa: E731
    rgb = surface_texture(size, wall_rng, wall.contrast, exponent())
    if wall.lamp:
        rgb = np.clip(rgb * lamp_irradiance(size, np.random.default_rng([seed, 3]))[..., None], 0.005,
                      1.0).astype(np.float32)
    range_m = np.full((size, size), np.exp(wall_rng.uniform(*np.log(WALL_RANGE_M))), np.float32)
    count = int(rng.integers(*OBJECTS))
    ranges = np.sort(np.exp(rng.uniform(*np.log(OBJECT_RANGE_M), count)))[::-1]  # far to near: nearer ones occlude
    rows, cols = np.mgrid[0:size, 0:size] + 0.5
    for object_m in ranges:
        half = rng.uniform(*OBJECT_HALF_PX)
        centre_row, centre_col = rng.uniform(0, size, 2)
        if rng.uniform() < 0.5:
            mask = (rows - centre_row) ** 2 + (cols - centre_col) ** 2 < half ** 2
        else:
            mask = (np.abs(rows - centre_row) < half) & (np.abs(cols - centre_col) < half * rng.uniform(0.4, 1.5))
        rgb[mask] = surface_texture(size, rng, rng.uniform(*OBJECT_CONTRAST), exponent())[mask]
        range_m[mask] = object_m
    return rgb, range_m


def _metrics(depth, sigma, truth, near_edge, wall) -> list[float]:
    """The row's numbers from pooled pixels: AbsRel (all, ``near_edge``, beyond, the ``wall`` beyond), δ1, std(error/σ),
    the share within one σ and the confident coverage (σ ≤ 10 % of the depth)."""
    from ..metrics import depth_metrics

    absrel = [depth_metrics(depth, truth, mask)["absrel"] for mask in (None, near_edge, ~near_edge, ~near_edge & wall)]
    scored = np.isfinite(depth) & np.isfinite(sigma) & (sigma > 0)
    z = (depth - truth)[scored] / sigma[scored]
    return [*absrel, depth_metrics(depth, truth)["delta1"], float(np.std(z)), float(np.mean(np.abs(z) <= 1.0)),
            float(np.mean(sigma[scored] <= 0.1 * depth[scored]))]


def run(full: bool = False) -> str:
    from ..decode import ClassicalDecoder
    from ..decode.classical import with_texture_exponent
    from ..nn.eval_strata import EDGE_NEAR_PX, edge_distance_px
    from .decoder import PLANE_MARGIN_PX, window_raw
    from .plane_reads import DECODER_NAMES, decoder_reads_sigma, design_decoders

    psf_map, geometry, network, stages = design_decoders()
    wide = ("evidence, support radius {radius_windows}, spatial σ {spatial_sigma_windows:g}, τ {spread_scale:g}"
            .format(**WIDE_SUPPORT))
    supports = {wide: dataclasses.replace(network.support, **WIDE_SUPPORT)}
    profiled = f"evidence, --texture-exponent {PROFILED_EXPONENT}"
    volumes = {profiled: ClassicalDecoder.for_psf_map(psf_map, with_texture_exponent(network.stage_config(),
                                                                                     PROFILED_EXPONENT))}
    ungated = "evidence, every window on every bin (weak_texture_below 0)"
    volumes[ungated] = ClassicalDecoder.for_psf_map(psf_map, dataclasses.replace(network.stage_config(),
                                                                                 weak_texture_below=0.0))
    names = (*DECODER_NAMES, wide, profiled, ungated)
    seeds = FULL_SEEDS if full else SEEDS
    m = PLANE_MARGIN_PX
    rows = []
    for (textures, spread), (wall_name, wall), field_deg in itertools.product(
            EXPONENT_SPREADS.items(), WALLS.items(), FIELDS_DEG):
        pooled: dict = {name: [] for name in names}
        truths, near, walls = [], [], []
        for seed in seeds:
            rgb, range_m = object_scene(seed, wall, spread)
            raw, row0, col0 = window_raw(rgb, range_m, psf_map.tensor, geometry, field_deg, 30.0, seed, psf_map)
            truth = range_m[m:-m, m:-m]
            truths.append(truth)
            near.append(edge_distance_px(truth) <= EDGE_NEAR_PX)
            walls.append(truth >= WALL_RANGE_M[0])  # every object lies nearer than the wall's nearest range
            for name, reads in decoder_reads_sigma(raw, row0, col0, stages, network, supports, volumes).items():
                pooled[name].append(reads)
        for name in names:
            depth = np.concatenate([d.ravel() for d, _ in pooled[name]])
            sigma = np.concatenate([s.ravel() for _, s in pooled[name]])
            rows.append([textures, wall_name, f"{field_deg:g}°", name,
                         *_metrics(depth, sigma, np.concatenate([t.ravel() for t in truths]),
                                   np.concatenate([n.ravel() for n in near]),
                                   np.concatenate([w.ravel() for w in walls]))])
    return (f"### Textured objects before a wall ({SIZE_PX}² px, every surface 1/f^p about its own colour, φ 30°, "
            f"σ 0.005, exact kernels; {len(seeds)} scenes pooled per row)\n\n"
            + markdown_table(["textures", "wall", "θ", "decoder", "AbsRel", f"≤ {EDGE_NEAR_PX:g} px of an edge",
                              "beyond", "wall beyond", "δ1", "std(error/σ)", "within 1σ", "confident coverage"], rows))


def register(subparsers) -> None:
    register_target(subparsers, "objects", "textured objects before a wall, natural texture statistics: the "
                    "decoders' depth edges and σ", __doc__, "Textured objects", run)
