"""`bmi bench texture`: how the decoders read planes whose texture spectrum is not the one their likelihood assumes.

The likelihood's prior is a 1/f² power spectrum (docs/decoder.md, step 2): natural images' average. A surface whose
texture falls faster looks blurred and reads nearer (the sensor is focused near infinity, so blur grows toward the
camera), one whose texture falls slower looks sharp and reads farther. This measures by how much, on planes of
power spectrum 1/f^p for ``POWER_SLOPES`` (p 0: white noise, 2: the prior, 3: smooth; 1.6 and 2.4: the prior ± the
image-to-image spread of natural images' exponent), each 15 % contrast about a mean of 0.4
(``decoder.power_law_texture``), 256² px at φ 30°, σ 0.005, rendered and decoded with the design camera's exact
kernels: AbsRel and the median of read / true range over the plane, per field angle, range and decoder (the default
evidence decoder and the classical one), the mean over ``SEEDS`` texture and noise draws (``--full``: ``FULL_SEEDS``).
"""

from __future__ import annotations

import numpy as np

from . import markdown_table, register_target

POWER_SLOPES = (0.0, 1.0, 1.6, 2.0, 2.4, 3.0)
"""p of each texture's power spectrum 1/f^p: white noise, 1/f, the likelihood's 1/f², a smooth 1/f³, and 1.6 and 2.4:
natural images' power-spectrum exponents scatter about 2 by about ±0.4 from one image to the next (van der Schaaf &
van Hateren, Vision Research 36, 1996), so these two are the textures a user's scenes hold."""
SIZE_PX = 256
FIELDS_DEG = (5.0, 55.0)
RANGES_M = (1.5, 3.0, 6.0)
SEEDS = (3, 4)
FULL_SEEDS = (3, 4, 5, 6, 7, 8)


def run(full: bool = False) -> str:
    from .decoder import PLANE_MARGIN_PX, power_law_texture, window_raw
    from .plane_reads import DECODER_NAMES, decoder_reads, design_decoders

    psf_map, geometry, network, stages = design_decoders()
    seeds = FULL_SEEDS if full else SEEDS
    size = SIZE_PX + 2 * PLANE_MARGIN_PX
    rows = []
    for slope in POWER_SLOPES:
        for field_deg in FIELDS_DEG:
            for range_m in RANGES_M:
                stats: dict = {}
                for seed in seeds:
                    rgb = power_law_texture(size, slope, np.random.default_rng(seed))
                    raw, row0, col0 = window_raw(rgb, np.full((size, size), range_m, np.float32), psf_map.tensor,
                                                 geometry, field_deg, 30.0, seed, psf_map)
                    for name, depth in decoder_reads(raw, row0, col0, stages, network).items():
                        read = depth[np.isfinite(depth)]
                        stats.setdefault(name, []).append((float(np.mean(np.abs(read - range_m) / range_m)),
                                                           float(np.median(read / range_m))))
                for name in DECODER_NAMES:
                    absrel, ratio = np.mean(stats[name], axis=0)
                    rows.append([f"1/f^{slope:g}", f"{field_deg:g}°", f"{range_m:g} m", name, float(absrel),
                                 float(ratio)])
    return (f"### Planes of power spectrum 1/f^p ({SIZE_PX}² px, 15 % contrast about 0.4, φ 30°, σ 0.005, exact "
            f"kernels; mean over {len(seeds)} texture and noise draws)\n\n"
            + markdown_table(["texture power", "θ", "range", "decoder", "AbsRel", "median read / true"], rows))


def register(subparsers) -> None:
    register_target(subparsers, "texture", "planes whose texture spectrum is not the likelihood's 1/f²: the "
                    "decoders' bias", __doc__, "Texture statistics", run)
