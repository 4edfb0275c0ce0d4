"""``bmi bench evidence``: the evidence decoder's read against the classical decoder's, and its upsampling knob.

On ``bmi eval``'s benchmark tiles at the paper's scene scale (4; ``--full``: 12 tiles per region instead of 4),
σ 0.005, design camera, tensor kernels (rendered and decoded with the same): the classical stage runs once per
tile; the network then reads its volume, and the window grid goes to the pixels by colour-guided upsampling
at each colour scale of ``COLOUR_SIGMAS`` (∞: plain bilinear weights). Rows: AbsRel, δ1, the std of
error / σ (1: honest σ), the confident coverage (share of valid pixels with σ ≤ 10 % of depth) and the
upsampling's time per megapixel; the classical decoder's own read beside them.
"""

from __future__ import annotations

import math
import time

import numpy as np

from . import markdown_table, register_target

COLOUR_SIGMAS = (0.1, 0.2, 0.3, 0.5, 1.0, math.inf)


def _row(depth: np.ndarray, sigma: np.ndarray, truth: np.ndarray, ok: np.ndarray) -> list[float]:
    from ..metrics import depth_metrics

    ok = ok & np.isfinite(depth) & np.isfinite(truth) & np.isfinite(sigma) & (sigma > 0)
    m = depth_metrics(depth, truth, ok)
    z = (depth[ok] - truth[ok]) / sigma[ok]
    confident = float(np.mean(sigma[ok] <= 0.1 * depth[ok])) if ok.any() else math.nan
    return [m["absrel"], m["delta1"], float(np.std(z)) if z.size else math.nan, confident]


def run(full: bool = False) -> str:
    from ..decode import ClassicalDecoder
    from ..decode.volume import guided_upsample, pixel_log_colour
    from ..lenses import lens_geometry, lens_tensor
    from ..model_io import raw_to_rgb
    from ..nn.evaluate import Benchmark, tile_raw
    from ..render import PsfMap
    from ..runtime.evidence import EvidenceNetwork
    from ..runtime.model import select_model
    from ..sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    sigma_noise = 0.005
    bench = Benchmark(tiles=12 if full else 4, scene_scale=4.0)
    tensor, geometry = lens_tensor(bench.lens), lens_geometry(bench.lens)
    network = EvidenceNetwork(select_model(bench.lens, "evidence"), threads=2)
    config = network.stage_config()
    stage = ClassicalDecoder.for_psf_map(PsfMap(tensor, geometry, mode="tensor"), config)
    rows: dict[str, list] = {}
    seconds: dict[str, float] = {}
    pixels = 0
    for k, item in enumerate(bench.renders(tensor)):
        raw = tile_raw(bench, item, k, sigma_noise)
        result = stage.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, item["row0"], item["col0"],
                              noise_profile=NoiseProfile.additive(sigma_noise), aif=False)
        truth = item["range_m"]
        rows.setdefault("classical", []).append(_row(result.depth_m, result.depth_sigma_m, truth, result.valid))
        inv_grid, sig_grid = network.read_decode(result)
        log_rgb = pixel_log_colour(raw_to_rgb(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN))
        pixels += raw.size
        for c in COLOUR_SIGMAS:
            name = f"evidence, colour σ {c:g}"
            t0 = time.perf_counter()
            inv_px, var_px = guided_upsample(inv_grid, sig_grid.astype(np.float64) ** 2, log_rgb,
                                             config.stride_px, c if math.isfinite(c) else 1e6)
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
            depth = np.where(inv_px > 0, 1.0 / np.where(inv_px > 0, inv_px, 1.0), np.nan)
            rows.setdefault(name, []).append(_row(depth, np.sqrt(var_px) * depth ** 2, truth, result.valid))
    table = []
    for name, values in rows.items():
        mean = np.nanmean(np.array(values, np.float64), axis=0)
        per_mpx = seconds[name] / (pixels / 1e6) if name in seconds else math.nan
        table.append([name, *[float(v) for v in mean], per_mpx])
    header = ["decoder", "AbsRel", "δ1", "std(error/σ)", "confident coverage", "upsampling s/Mpx"]
    return (f"### Evidence decoder against the classical read (scene scale 4, σ {sigma_noise}, "
            f"{2 * bench.tiles} tiles of {bench.tile_px} px)\n\n" + markdown_table(header, table))


def register(subparsers) -> None:
    register_target(subparsers, "evidence", "evidence decoder: error against the classical read and its "
                    "upsampling's colour scale", __doc__, "evidence", run)
