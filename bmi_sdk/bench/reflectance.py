"""`bmi bench reflectance`: reflectance edges on a plane (two paints on one wall), read by the decoders.

The likelihood (docs/decoder.md, step 2) models a window as one stationary texture under one prior level. A window
across a reflectance edge holds two textures of different means and a step between them, whose power lies on one
line of the spectrum; no single level fits both sides and the step, and the read moves. This measures by how much,
where a user meets it: a 1/f²-textured plane (``decoder.plane_texture`` "pink", the texture whose statistics the
likelihood assumes), 256² px at φ 30°, σ 0.005, rendered and decoded with the design camera's exact kernels (the
simulated device's and ``bmi infer``'s path), painted ``STEP_FACTOR`` × darker on its left half (one edge) or on a
``STRIPE_PX`` stripe down its middle (two edges closer than a window: no window on the stripe sees one paint), beside
the same plane unpainted (the control). Per painting, field angle, range and decoder (the default evidence decoder and
the classical one): AbsRel and the median of read / true range within ``EDGE_BAND_PX`` of an edge, and AbsRel beyond
``AWAY_PX``, the mean over ``SEEDS`` texture and noise draws (``--full``: ``FULL_SEEDS``).
"""

from __future__ import annotations

import numpy as np

from . import markdown_table, register_target

STEP_FACTOR = 0.2
"""The darker half's reflectance against the lighter's: a dark paint beside a light one."""
SIZE_PX = 256
STRIPE_PX = 48
EDGE_BAND_PX = 32  # half the evidence window: every window whose centre lies in this band straddles the edge
AWAY_PX = 64  # a window's width: windows centred beyond it see one side only
FIELDS_DEG = (5.0, 55.0)
RANGES_M = (2.0, 4.0, 6.5)
SEEDS = (3, 4)
FULL_SEEDS = (3, 4, 5, 6, 7, 8)


PAINTINGS = {"one edge": (-SIZE_PX, 0), f"a {STRIPE_PX}-px stripe": (-STRIPE_PX // 2, STRIPE_PX // 2)}
"""Painted columns of each painting, [start, stop) relative to the plane's centre column."""


def painted_scene(seed: int, painted: tuple[int, int], step_factor: float) -> np.ndarray:
    """(SIZE_PX + 2 margins)² × 3 linear RGB: the 1/f² plane texture of ``seed``, the columns ``painted`` (relative to
    the centre) × ``step_factor``."""
    from .decoder import PLANE_MARGIN_PX, plane_texture

    size = SIZE_PX + 2 * PLANE_MARGIN_PX
    rgb = plane_texture(size, "pink", np.random.default_rng(seed))
    start, stop = (max(0, size // 2 + c) for c in painted)
    rgb[:, start:stop] *= np.float32(step_factor)
    return rgb


def band_masks(painted: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(near an edge, away from every edge): SIZE_PX² masks of the pixels within ``EDGE_BAND_PX`` columns of an edge
    of the ``painted`` columns inside the plane, and beyond ``AWAY_PX`` of all of them."""
    columns = np.arange(SIZE_PX) + 0.5 - SIZE_PX / 2
    edges = [c for c in painted if -SIZE_PX / 2 < c < SIZE_PX / 2]
    distance = np.min([np.abs(columns - c) for c in edges], axis=0)
    near = np.broadcast_to(distance <= EDGE_BAND_PX, (SIZE_PX, SIZE_PX))
    away = np.broadcast_to(distance >= AWAY_PX, (SIZE_PX, SIZE_PX))
    return near, away


def _band_stats(depth: np.ndarray, range_m: float, mask: np.ndarray) -> tuple[float, float]:
    """(AbsRel, median read / true) over ``mask``'s finite reads."""
    read = depth[mask & np.isfinite(depth)]
    return float(np.mean(np.abs(read - range_m) / range_m)), float(np.median(read / range_m))


def run(full: bool = False) -> str:
    from .decoder import PLANE_MARGIN_PX, window_raw
    from .plane_reads import DECODER_NAMES, decoder_reads, design_decoders

    psf_map, geometry, network, stages = design_decoders()
    seeds = FULL_SEEDS if full else SEEDS
    size = SIZE_PX + 2 * PLANE_MARGIN_PX
    masks = {painting: band_masks(painted) for painting, painted in PAINTINGS.items()}
    rows: dict = {painting: [] for painting in PAINTINGS}

    def reads(painted: tuple[int, int], factor: float, field_deg: float, range_m: float, seed: int) -> dict:
        raw, row0, col0 = window_raw(painted_scene(seed, painted, factor), np.full((size, size), range_m, np.float32),
                                     psf_map.tensor, geometry, field_deg, 30.0, seed, psf_map)
        return decoder_reads(raw, row0, col0, stages, network)

    for field_deg in FIELDS_DEG:
        for range_m in RANGES_M:
            # the unpainted plane is one scene for every painting: read once per draw
            control = {seed: reads((0, 0), 1.0, field_deg, range_m, seed) for seed in seeds}
            for painting, painted in PAINTINGS.items():
                near, away = masks[painting]
                stats: dict = {}
                for seed in seeds:
                    for name, depth in reads(painted, STEP_FACTOR, field_deg, range_m, seed).items():
                        stats.setdefault((name, "near"), []).append(_band_stats(depth, range_m, near))
                        stats.setdefault((name, "away"), []).append(_band_stats(depth, range_m, away))
                        stats.setdefault((name, "control"), []).append(_band_stats(control[seed][name], range_m, near))
                for name in DECODER_NAMES:
                    near_stats, away_stats, control_stats = (np.mean(stats[(name, key)], axis=0)
                                                             for key in ("near", "away", "control"))
                    rows[painting].append([painting, f"{field_deg:g}°", f"{range_m:g} m", name,
                                           float(near_stats[0]), float(near_stats[1]), float(away_stats[0]),
                                           float(control_stats[0])])
    header = ["painting", "θ", "range", "decoder", f"AbsRel ≤ {EDGE_BAND_PX} px from an edge",
              "median read / true there", f"AbsRel ≥ {AWAY_PX} px from every edge", "unpainted: AbsRel, same pixels"]
    return (f"### Reflectance edges ({STEP_FACTOR:g}× darker paint) on a 1/f² plane ({SIZE_PX}² px, φ 30°, σ 0.005, "
            f"exact kernels; mean over {len(seeds)} texture and noise draws)\n\n"
            + markdown_table(header, [row for painting in PAINTINGS for row in rows[painting]]))


def register(subparsers) -> None:
    register_target(subparsers, "reflectance", "a reflectance edge on a plane: the decoders' read across it "
                    "against the same plane without it", __doc__, "Reflectance edges", run)
