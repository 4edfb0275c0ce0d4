"""`bmi bench clipped`: windows holding clipped samples (``decode.clipped``), error against run time.

A sample at the white level is censored. The classical stage scores a window holding such samples from its other
samples, under its taper times weights that ramp to zero at the clipped ones (``ClassicalConfig.clipped_ramp_samples``),
for at most ``clipped_planes_per_frame`` (window, plane) pairs a frame; 0 gives such pairs no evidence. Two scene sets:

* ``HIGHLIGHT_SCENES``: a dark 1/f-textured disc (radius 70 px) at a near range holding a highlight far above white
  (radius 10 px), before a brighter 1/f-textured wall at 5 m, 256² at 15° of field, σ 0.005, the nominal tensor
  kernels (``highlight_scene``). The near kernel spreads the highlight over most of the disc: every window on the
  disc holds clipped samples. AbsRel inside the disc's rim (radius < 54 px) and on the wall (> 110 px from the disc's
  centre, past every window that sees the disc);
* the `bmi eval` tiles that hold clipped samples: seeds 777 and 4242 at scene scale 4, centre region, 6 tiles
  (``bmi eval --tiles 6 --seed S --scales 4``; 3 of their 12 tiles clip), read by the classical decoder.

Per configuration (the default and each knob moved alone): the AbsRels, the windows left without evidence and the
decode's CPU seconds per scene. ``--full`` reads the benchmarks' full 6000×4500 procedural frame over-exposed
``FULL_EXPOSURE``× (its optical image scaled before the noise and the ADC; about half its samples clip) with clipped
planes giving no evidence and at the default cap: what the cap bounds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import cpu_seconds, markdown_table, peak_rss_mb, register_target

HIGHLIGHT_SCENES = ((1, 1.0, 8.0, 0.3), (2, 2.0, 4.0, 0.3), (3, 1.5, 20.0, 0.2), (4, 3.0, 6.0, 0.4))
"""(seed, disc range m, highlight level × white, wall level) of each highlight scene."""
HIGHLIGHT_PX = 256
TILE_SEEDS = (777, 4242)
FULL_EXPOSURE = 3.0


def highlight_scene(seed: int, disc_m: float, highlight: float, wall: float, tensor, geometry, psf_map
                    ) -> dict:
    """{raw, row0, col0, range_m, radius_px}: a highlight scene (module doc) rendered with ``psf_map``'s kernels
    (``decoder.window_raw``: relative illumination, σ 0.005); ``radius_px`` each pixel's distance from the disc's
    centre. The textures, the highlight's place (within 30 px of the disc's centre) and the noise come from ``seed``."""
    from bmi_sdk.scenes.procedural import pink_noise

    from .decoder import PLANE_MARGIN_PX, window_raw

    m = PLANE_MARGIN_PX
    size = HIGHLIGHT_PX + 2 * m
    rng = np.random.default_rng(seed)

    def texture() -> np.ndarray:
        t = pink_noise((size, size), rng)
        return np.exp(0.8 * (t - t.mean()) / t.std())[..., None]

    yy, xx = np.mgrid[:size, :size] - size / 2
    radius = np.hypot(yy, xx)
    disc = radius < 70
    rgb = np.where(disc[..., None], 0.08 * texture() * np.array([1.0, 0.8, 0.6]),
                   wall * texture() * np.array([0.7, 0.8, 1.0]))
    dy, dx = rng.uniform(-30, 30, 2)
    rgb = np.where((np.hypot(yy - dy, xx - dx) < 10)[..., None], highlight, rgb).astype(np.float32)
    range_m = np.where(disc, disc_m, 5.0).astype(np.float32)
    raw, row0, col0 = window_raw(rgb, range_m, tensor, geometry, 15.0, 30.0, seed + 1, psf_map)
    return {"raw": raw, "row0": row0, "col0": col0, "range_m": range_m[m:-m, m:-m], "radius_px": radius[m:-m, m:-m]}


def variants() -> list[tuple[str, object]]:
    """(name, ``ClassicalConfig``) of the table's rows: the default, no evidence from clipped planes, and each
    knob moved alone."""
    from bmi_sdk.decode import ClassicalConfig

    base = ClassicalConfig()
    return [("clipped planes give no evidence (0 pairs)", replace(base, clipped_planes_per_frame=0)),
            ("default", base),
            ("hard holes (ramp 0)", replace(base, clipped_ramp_samples=0.0)),
            ("ramp 4 samples", replace(base, clipped_ramp_samples=4.0)),
            ("ramp 12 samples", replace(base, clipped_ramp_samples=12.0)),
            ("ramp 16 samples", replace(base, clipped_ramp_samples=16.0)),
            ("at most 64 pairs a frame", replace(base, clipped_planes_per_frame=64)),
            ("at most 256 pairs a frame", replace(base, clipped_planes_per_frame=256))]


def highlight_rows(psf_map, geometry) -> list[list]:
    """[configuration, disc AbsRel, wall AbsRel, windows without evidence, pairs scored, CPU s per scene] over
    ``HIGHLIGHT_SCENES`` (AbsRels the mean over the scenes), per ``variants`` row; each decoder decodes the first
    scene once untimed (its kernels' first load)."""
    from bmi_sdk.decode import ClassicalDecoder
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    scenes = [highlight_scene(*spec, psf_map.tensor, geometry, psf_map) for spec in HIGHLIGHT_SCENES]
    noise = NoiseProfile.additive(STANDARD_SIGMA)
    rows = []
    for name, config in variants():
        decoder = ClassicalDecoder.for_psf_map(psf_map, config)
        decode = lambda s: decoder.decode(s["raw"], BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry,  # noqa: E731
                                          s["row0"], s["col0"], noise_profile=noise, aif=False)
        decode(scenes[0])
        disc, wall, blind, scored, cpu = [], [], 0, 0, 0.0
        for s in scenes:
            c0 = cpu_seconds()
            out = decode(s)
            cpu += cpu_seconds() - c0
            error = np.abs(out.depth_m - s["range_m"]) / s["range_m"]
            disc.append(float(np.nanmean(error[s["radius_px"] < 54])))
            wall.append(float(np.nanmean(error[s["radius_px"] > 110])))
            blind += out.stats["windows_without_evidence"]
            scored += out.stats["windows_scored_without_clipped_samples"]
        rows.append([name, float(np.mean(disc)), float(np.mean(wall)), blind, scored, cpu / len(scenes)])
    return rows


def tile_rows(psf_map) -> list[list]:
    """[configuration, AbsRel per ``TILE_SEEDS`` seed, CPU s per tile] of the classical decoder on the `bmi eval`
    centre tiles at scene scale 4 (6 tiles, σ 0.005), per ``variants`` row."""
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.nn.evaluate import Benchmark, ClassicalTiles, score

    renders = {seed: [r for r in Benchmark(tiles=6, seed=seed, scene_scale=4.0).renders(psf_map.tensor)
                      if r["region"] == "centre"] for seed in TILE_SEEDS}
    rows = []
    for name, config in variants():
        tiles = ClassicalTiles(psf_map, config)
        row, cpu = [name], 0.0
        for seed, renders_s in renders.items():
            c0 = cpu_seconds()
            out = score(tiles, renders_s, Benchmark(tiles=6, seed=seed, scene_scale=4.0), STANDARD_SIGMA, "standard")
            cpu += cpu_seconds() - c0
            row.append(out[0]["absrel"])
        rows.append(row + [cpu / sum(len(r) for r in renders.values())])
    return rows


def full_frame_rows(psf_map, geometry) -> tuple[list[list], float]:
    """[configuration, AbsRel, windows with clipped samples, windows scored from their other samples, windows without
    evidence, decode wall s, peak RSS MB] of the full procedural frame over-exposed ``FULL_EXPOSURE``× (module doc),
    decoded whole without the AiF after an untimed decode of a 512² corner (the kernels' first load); and the share of
    its samples that clip."""
    import time

    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.metrics import depth_metrics
    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_raw
    from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    from .decoder import full_frame_optical

    range_m, optical, _ = full_frame_optical(psf_map.tensor, geometry, psf_map)
    optical *= np.float32(FULL_EXPOSURE)
    raw = simulate_raw(optical, STANDARD_SIGMA, np.random.default_rng(7))
    del optical
    noise = NoiseProfile.additive(STANDARD_SIGMA)
    rows = []
    for name, config in (("clipped planes give no evidence (0 pairs)", ClassicalConfig(clipped_planes_per_frame=0)),
                         ("default", ClassicalConfig())):
        decoder = ClassicalDecoder.for_psf_map(psf_map, config)
        decoder.decode(raw[:512, :512], BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, noise_profile=noise, aif=False)
        t0 = time.perf_counter()
        out = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, noise_profile=noise, aif=False)
        wall = time.perf_counter() - t0
        ok = out.valid & np.isfinite(range_m)
        st = out.stats
        rows.append([name, depth_metrics(out.depth_m, range_m, ok)["absrel"], st["windows_with_clipped_samples"],
                     st["windows_scored_without_clipped_samples"], st["windows_without_evidence"], wall,
                     peak_rss_mb()])
        del out
    return rows, float(np.mean(raw >= WHITE_LEVEL_DN))


def run(full: bool = False) -> str:
    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from bmi_sdk.render import PsfMap

    tensor = lens_tensor("bmi_monocentric")
    geometry = lens_geometry("bmi_monocentric")
    psf_map = PsfMap(tensor, geometry, mode="tensor")
    scenes = ", ".join(f"{d:g} m disc, highlight {h:g}× white, wall {w:g}" for _, d, h, w in HIGHLIGHT_SCENES)
    out = [
        f"### Near discs with a blown-out highlight ({len(HIGHLIGHT_SCENES)} scenes of {HIGHLIGHT_PX}² px: {scenes}; "
        "σ 0.005; classical decoder)", "",
        "AbsRel inside the disc's rim and on the wall, the mean over the scenes; windows without evidence and "
        "(window, plane) pairs scored from their unclipped samples, summed over the scenes; CPU s per scene of the "
        "decode without the AiF, after one untimed decode per configuration.", "",
        markdown_table(["configuration", "disc AbsRel", "wall AbsRel", "windows without evidence", "pairs scored",
                        "CPU s / scene"], highlight_rows(psf_map, geometry)), "",
        f"### `bmi eval` centre tiles at scene scale 4 (seeds {', '.join(map(str, TILE_SEEDS))}, 6 tiles each, σ 0.005; "
        "classical decoder)", "",
        markdown_table(["configuration"] + [f"AbsRel, seed {s}" for s in TILE_SEEDS] + ["CPU s / tile"],
                       tile_rows(psf_map))]
    if full:
        rows, share = full_frame_rows(psf_map, geometry)
        out += ["", f"### The full 6000×4500 procedural frame over-exposed {FULL_EXPOSURE:g}× (seed 7, tensor kernels, "
                    f"σ 0.005; {share:.0%} of its samples clip; classical decoder without the AiF)", "",
                markdown_table(["configuration", "AbsRel", "windows with clipped samples", "windows scored from their "
                                "other samples", "windows without evidence", "decode wall s", "peak RSS MB (process)"],
                               rows)]
    return "\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "clipped", "windows holding clipped samples: error against run time (highlight "
                    "scenes, clipped benchmark tiles; --full: an over-exposed full frame)", __doc__, "Clipped samples", run)
