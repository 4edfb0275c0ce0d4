"""`bmi bench pooling`: the classical decoder's evidence pooling (``decode.pooling``), error against run time.

Two scene sets, because pooling helps where surfaces are larger than a window and must not hurt where
they are not:

* the `bmi eval` benchmark (condition `standard`, σ 0.005, its 12 tiles per region): procedural scenes
  drawn at the 192² tile's own scale, so objects are 8–150 px and only ~3 % of the 64-px windows hold
  one depth;
* frame-scale scenes: procedural scenes drawn at 1024² (objects 40–600 px, as a full-frame scene's
  are ~4× larger still) at ``SCENE_FIELDS`` field positions, rendered with the nominal tensor kernels
  and the standard noise.

Each pooling knob is varied alone around the default ``ClassicalConfig()``; per configuration, depth
AbsRel, δ1, the RMS of (error / reported σ) and the decode's CPU seconds per megapixel (AiF included).
``--full`` adds the full 6000×4500 frame of ``bmi bench decoder --full``, read each window alone and pooled.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import cpu_seconds, markdown_table, peak_rss_mb, register_target
from .decoder import PLANE_MARGIN_PX, full_frame_raw, window_raw

SCENE_PX = 1024
SCENE_FIELDS = ((0.0, 0.0), (20.0, 120.0), (30.0, 240.0), (38.0, 0.0))  # (θ°, φ°) of each scene's centre
SCENE_SEEDS = (101, 102)
NO_LIMIT = 1e9


def variants() -> list[tuple[str, object]]:
    """(name, ``ClassicalConfig``) of the table's rows: each pooling knob alone around the default."""
    from bmi_sdk.decode import ClassicalConfig

    base = ClassicalConfig()
    return [("each window alone (no pooling)", replace(base, pool_sigma_px=0.0)),
            ("default", base),
            ("radius 32 px", replace(base, pool_sigma_px=32.0)),
            ("radius 96 px", replace(base, pool_sigma_px=96.0)),
            ("truncation 5 nats", replace(base, pool_truncate_nats=5.0)),
            ("truncation 20 nats", replace(base, pool_truncate_nats=20.0)),
            ("no truncation", replace(base, pool_truncate_nats=NO_LIMIT)),
            ("colour scale 0.15", replace(base, pool_colour_sigma=0.15)),
            ("no colour weight", replace(base, pool_colour_sigma=NO_LIMIT))]


def frame_scale_scenes(tensor, geometry) -> list[dict]:
    """Raw frames (σ 0.005) and true ranges of procedural scenes drawn at ``SCENE_PX``², one per seed and field
    (``decoder.window_raw``)."""
    from bmi_sdk.render import PsfMap
    from bmi_sdk.scenes import generate_scene

    psf_map = PsfMap(tensor, geometry, mode="tensor")
    m, size = PLANE_MARGIN_PX, SCENE_PX + 2 * PLANE_MARGIN_PX
    scenes = []
    for seed in SCENE_SEEDS:
        for field_deg, azimuth_deg in SCENE_FIELDS:
            scene = generate_scene(size, size, np.random.default_rng([seed, int(field_deg), int(azimuth_deg)]))
            raw, row0, col0 = window_raw(scene.rgb, scene.range_m, tensor, geometry, field_deg, azimuth_deg, seed,
                                         psf_map)
            scenes.append({"raw": raw, "row0": row0, "col0": col0, "range_m": scene.range_m[m:-m, m:-m]})
    return scenes


def scene_rows(scenes: list[dict], psf_map, geometry) -> list[list]:
    """[configuration, AbsRel, δ1, σ z RMS, CPU s / MP, pooling wall s / MP] over ``scenes`` (all pixels pooled) per
    ``variants`` row; each decoder decodes the first scene once untimed (its kernels' first load)."""
    from bmi_sdk.decode import ClassicalDecoder
    from bmi_sdk.metrics import depth_metrics
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    noise = NoiseProfile.additive(STANDARD_SIGMA)
    rows = []
    for name, config in variants():
        decoder = ClassicalDecoder.for_psf_map(psf_map, config)
        first = scenes[0]  # untimed: loads the kernels every configuration shares from the PSF cache
        decoder.decode(first["raw"], BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, first["row0"], first["col0"],
                       noise_profile=noise)
        reads, trues, z2, cpu, pool_s, pixels = [], [], [], 0.0, 0.0, 0
        for s in scenes:
            c0 = cpu_seconds()
            out = decoder.decode(s["raw"], BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, s["row0"], s["col0"],
                                 noise_profile=noise)
            cpu += cpu_seconds() - c0
            pool_s += out.stats["timings_s"]["pool_s"]
            pixels += s["raw"].size
            ok = out.valid & np.isfinite(s["range_m"]) & np.isfinite(out.depth_m)
            reads.append(out.depth_m[ok].astype(np.float64))
            trues.append(s["range_m"][ok])
            z2.append(((reads[-1] - trues[-1]) / out.depth_sigma_m[ok]) ** 2)
        m = depth_metrics(np.concatenate(reads), np.concatenate(trues))
        rows.append([name, m["absrel"], m["delta1"], float(np.sqrt(np.mean(np.concatenate(z2)))),
                     cpu / (pixels / 1e6), pool_s / (pixels / 1e6)])
    return rows


def benchmark_rows(psf_map) -> list[list]:
    """[configuration, AbsRel centre, AbsRel edge, δ1 centre, δ1 edge, σ z RMS centre, edge] on the `bmi eval`
    benchmark's `standard` condition, per ``variants`` row."""
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.nn.evaluate import Benchmark, ClassicalTiles, score

    bench = Benchmark()
    renders = bench.renders(psf_map.tensor)
    rows = []
    for name, config in variants():
        out = {r["region"]: r for r in score(ClassicalTiles(psf_map, config), renders, bench, STANDARD_SIGMA,
                                             "standard")}
        rows.append([name] + [out[region][key] for key in ("absrel", "delta1", "sigma_z_rms")
                              for region in ("centre", "edge")])
    return rows


def full_frame_rows(tensor, geometry) -> tuple[list[list], int]:
    """[configuration, AbsRel, δ1, decode wall s, pooling s, peak RSS MB] of the benchmarks' full 6000×4500 frame
    (``decoder.full_frame_raw``) decoded each window alone and pooled, each decoder's kernels loaded by an untimed
    decode of a 512² window first; and the count of valid pixels."""
    import time

    from bmi_sdk.decode import ClassicalDecoder
    from bmi_sdk.metrics import depth_metrics
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.render import PsfMap
    from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    range_m, raw, _ = full_frame_raw(tensor, geometry)
    psf_map = PsfMap(tensor, geometry, mode="tensor")
    noise = NoiseProfile.additive(STANDARD_SIGMA)
    rows, pixels = [], 0
    for name, config in variants()[:2]:
        decoder = ClassicalDecoder.for_psf_map(psf_map, config)
        decoder.decode(raw[:512, :512], BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, noise_profile=noise)
        t0 = time.perf_counter()
        out = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, noise_profile=noise)
        wall = time.perf_counter() - t0
        ok = out.valid & np.isfinite(range_m)
        pixels = int(ok.sum())
        m = depth_metrics(out.depth_m, range_m, ok)
        rows.append([name, m["absrel"], m["delta1"], wall, out.stats["timings_s"]["pool_s"], peak_rss_mb()])
        del out
    return rows, pixels


def run(full: bool = False) -> str:
    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from bmi_sdk.render import PsfMap

    tensor = lens_tensor("bmi_monocentric")
    geometry = lens_geometry("bmi_monocentric")
    psf_map = PsfMap(tensor, geometry, mode="tensor")
    scenes = frame_scale_scenes(tensor, geometry)
    out = [f"Frame-scale scenes: {len(scenes)} procedural scenes drawn at {SCENE_PX}² (seeds {SCENE_SEEDS}, centred "
           f"at (θ, φ) = {', '.join(f'({t:g}°, {p:g}°)' for t, p in SCENE_FIELDS)}), nominal tensor kernels render "
           "and decode, σ 0.005; all pixels pooled; CPU s per megapixel of the whole decode (AiF included), "
           "after one untimed decode per configuration", "",
           markdown_table(["configuration", "AbsRel", "δ1", "σ z RMS", "CPU s / MP", "of which pooling, wall s / MP"],
                          scene_rows(scenes, psf_map, geometry)), "",
           "The `bmi eval` benchmark, condition `standard` (σ 0.005, 12 tiles per region):", "",
           markdown_table(["configuration", "AbsRel centre", "AbsRel edge", "δ1 centre", "δ1 edge", "σ z RMS centre",
                           "σ z RMS edge"], benchmark_rows(psf_map))]
    if full:
        rows, pixels = full_frame_rows(tensor, geometry)
        out += ["", f"`--full`: the full 6000×4500 procedural frame (seed 7, tensor-mode render, σ 0.005) of `bmi bench "
                    f"decoder --full`, decoded whole ({pixels} valid pixels; the kernels loaded first, untimed):", "",
                markdown_table(["configuration", "AbsRel", "δ1", "decode wall s", "of which pooling s",
                                "peak RSS MB (process)"], rows)]
    return "\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "pooling", "classical decoder's evidence pooling: error against run time, "
                    "frame-scale scenes and the benchmark", __doc__, "Evidence pooling", run)
