"""The runtime side of the classical decoder: a camera's frames in, depth + 1σ + AiF out.

``classical_decoder(camera)`` builds a ``decode.ClassicalDecoder`` over the built camera's own
kernels (``BuiltCamera.psf_map``: the nominal tensor, or the calibrated camera's exact kernels),
and ``decode_frame`` checks a ``devices.RawFrame`` against that camera and decodes it. Nothing
is trained, so a calibration reaches the decoder as soon as its file is read.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, replace

from ..built_camera import BuiltCamera
from ..decode import ClassicalConfig, ClassicalDecoder
from ..memory_budget import check_allocation, limit_bytes
from .decoders import DecodedFrame
from .pipeline import check_decodable

MEMORY_KNOBS = ("window_px", "stride_px", "candidates", "pool_sigma_px")
"""The ``ClassicalConfig`` fields that size the decoder's arrays (``classical_peak_bytes``)."""


def classical_peak_bytes(config: ClassicalConfig, height_px: int = 0, width_px: int = 0) -> float:
    """Estimated peak bytes of a classical decode of an H × W frame (0 × 0: what opening the decoder allocates).

    The terms follow ``decode.ClassicalDecoder``'s arrays: the taper (n² float64, n = window_px / 2), the blocks
    read at once (``block_windows``² windows of n² float32 each, copied, tapered and transformed, on every
    thread), the kernel models (4 planes × slopes × candidates × n × (n/2 + 1) float32), the reflected planes
    (4 × (H/2 + n + stride/2) × (W/2 + n + stride/2) float32, stacked), the window grid's curves and pooled curves
    (grid × candidates float32, five copies while pooling; with the exponent profiled per pool, each slope's curves
    as well, float32, and their pooled stack, float64, three copies while profiling), the pooling's padded grid
    (reach 2 pool_sigma / stride windows each side), the per-pixel maps (~40 bytes a pixel) and, where clipped
    samples are scored (``clipped_planes_per_frame`` > 0), the planes' clipped flags and weights (4 × 5 bytes a
    padded plane sample) and each thread's block of clipped pairs (up to 4 × ``block_windows``² of them, ~96 n²
    bytes each: ``decode.clipped.ClippedPairs``)."""
    n = config.window_px // 2
    m = n // 2 + 1
    depths = config.candidates
    threads = config.threads or os.cpu_count() or 1
    taper = 3.0 * 8 * n * n
    blocks = threads * 4 * config.block_windows ** 2 * (3 * 4 * n * n + 8 * n * m)
    models = 3 * 4 * len(config.slopes) * depths * n * m * 4
    sp = config.stride_px // 2
    padded_samples = 4 * (height_px // 2 + n + sp) * (width_px // 2 + n + sp)  # the four reflected planes
    planes = 2 * padded_samples * 4
    rows, cols = -(-height_px // config.stride_px) + 1, -(-width_px // config.stride_px) + 1
    grid = rows * cols * (64 + 5 * 4 * depths)
    if config.exponent_per_pool:
        grid += rows * cols * depths * len(config.slopes) * (4 + 3 * 8)
    reach = 2.0 * config.pool_sigma_px / config.stride_px
    pool = (rows + 2 * reach + 1) * (cols + 2 * reach + 1) * (depths + 4) * 4 if config.pool_sigma_px > 0 else 0
    pixels = 40 * height_px * width_px
    clipped = (5 * padded_samples + threads * min(config.clipped_planes_per_frame, 4 * config.block_windows ** 2) * 96 * n * n
               if config.clipped_planes_per_frame else 0)
    return float(taper + blocks + models + planes + grid + pool + pixels + clipped)


def check_classical_memory(config: ClassicalConfig, height_px: int = 0, width_px: int = 0) -> None:
    """Refuse, before any allocation, a ``config`` whose decode of an H × W frame (0 × 0: the decoder's opening)
    would not fit the memory limit (``memory_budget``): ``MemoryBudgetError`` naming the option (``--window-px``
    …), its value, the estimate and the limit. Each of ``MEMORY_KNOBS`` that differs from the default is judged
    with the others at theirs, then all together (naming the one that asks the most); a default decode is
    never refused here."""
    defaults = replace(ClassicalConfig(), threads=config.threads)
    base = classical_peak_bytes(defaults, height_px, width_px)
    alone = {}
    for name in MEMORY_KNOBS:
        value = getattr(config, name)
        if value != getattr(defaults, name):
            alone[name] = classical_peak_bytes(replace(defaults, **{name: value}), height_px, width_px)
    frame = f" on a {height_px}×{width_px} px frame" if height_px else ""
    for name, estimate in alone.items():
        if estimate > base:
            check_allocation(_flag(name), getattr(config, name), estimate,
                             f"lower it{frame} (default {getattr(defaults, name):g})")
    total = classical_peak_bytes(config, height_px, width_px)
    grows = {name: estimate for name, estimate in alone.items() if estimate > base}
    if grows and total > limit_bytes()[0]:
        name = max(grows, key=lambda k: grows[k])
        check_allocation(_flag(name), getattr(config, name), total,
                         f"with {', '.join(f'{_flag(k)} {getattr(config, k)}' for k in grows)}{frame}; lower one")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


class WindowFitWarning(UserWarning):
    """The evidence window asked for is smaller than the lens's kernel, so the decoder reads with the smallest
    window that holds it (``window_holding``)."""


def window_holding(kernel_px: int, window_px: int) -> int:
    """``window_px``, or the smallest multiple of 4 that holds a ``kernel_px`` kernel when that is larger: a window
    narrower than the kernel cannot be fitted at all (``decode.ClassicalDecoder``)."""
    return max(window_px, -(-kernel_px // 4) * 4)


def classical_decoder(camera: BuiltCamera, config: ClassicalConfig = ClassicalConfig()) -> ClassicalDecoder:
    """A decoder over ``camera``'s kernels at ``config.candidates`` depths spaced in 1/d (a calibrated camera's exact
    kernels kept in the disk cache: its next frame or run reads them); refused first when its arrays would not fit
    in memory (``check_classical_memory``). A window narrower than the lens's kernel (the default 64 px against the
    fisheye's 161-px kernels) is widened to hold it, with a ``WindowFitWarning``."""
    check_classical_memory(config)
    psf_map = camera.psf_map(disk_cache=True)
    fitted = window_holding(psf_map.kernel_px, config.window_px)
    if fitted != config.window_px:
        warnings.warn(f"--window-px {config.window_px} holds no {psf_map.kernel_px}-px kernel of the "
                      f"{camera.lens_name} lens; reading with {fitted}-px windows", WindowFitWarning, stacklevel=3)
        config = replace(config, window_px=fitted)
        check_classical_memory(config)
    return ClassicalDecoder.for_psf_map(psf_map, config)


@dataclass(frozen=True)
class _ZoneTracer:
    """Builds, once per process, the decoder whose disk-cached ``PsfMap`` a warm-up fills (``warm_kernels``)."""

    camera: BuiltCamera
    config: ClassicalConfig

    def __call__(self) -> ClassicalDecoder:
        return classical_decoder(self.camera, self.config)


def _trace_ring(decoder: ClassicalDecoder, ring: list) -> tuple[int, int]:
    """Trace (or read) the kernels of one θ ring's zones, [(zone, candidate indices)], and make (or read) their
    evidence models (the window model every window not gated to the exact one reads: the exact model where the
    config gates every window to it, ``exact_model_below`` ≥ 1), into the disk cache; returns the kernel sets traced
    and the models made. A ring is one job, so its zones share the process's pupil fits (the design's depend on θ
    alone) and aims (every lens's)."""
    traced, made = decoder.zones.psf_map.kernels_traced, decoder.zones.models_computed
    exact = decoder.config.exact_model_below >= 1.0
    for zone, which in ring:
        decoder.zones.kernels(zone, which)
        decoder.zones.models(zone, which, exact)
    return decoder.zones.psf_map.kernels_traced - traced, decoder.zones.models_computed - made


def warm_kernels(camera: BuiltCamera, config: ClassicalConfig = ClassicalConfig(), roi: tuple | None = None,
                 workers: int = 1, progress: bool = False) -> dict:
    """Trace ahead of a capture every kernel a frame's decode can read, and make their evidence models, into the disk
    cache (``bmi psf warm``).

    A camera's first full frame otherwise spends most of its time tracing (docs/benchmarks.md, ``bmi bench
    frame``); its later frames, and any process after a warm-up, read the kernels. ``roi`` = (row0, col0, height, width)
    of the sensor (default the whole sensor). The zones are those ``ClassicalDecoder.frame_zones`` lists, every
    candidate of the evidence and the AiF's, so any scene's decode finds them. ``workers`` > 1 traces zones in
    that many single-threaded processes, a θ ring per job (each writes its own zones' shards). Returns what was done: zones,
    kernel sets traced and evidence models made (0 when the cache was already warm), the cache folder and the wall time.
    """
    import time

    from ..parallel import map_jobs

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    geometry = camera.sensor()
    row0, col0, height, width = roi or (0, 0, geometry.height_px, geometry.width_px)
    if height <= 0 or width <= 0 or row0 < 0 or col0 < 0 or row0 + height > geometry.height_px \
            or col0 + width > geometry.width_px:
        raise ValueError(f"region (row0 {row0}, col0 {col0}, {height} × {width} px) is not inside the "
                         f"{geometry.height_px} × {geometry.width_px} sensor")
    decoder = classical_decoder(camera, config)
    zones = decoder.frame_zones(geometry, height, width, row0, col0)
    rings: dict[float, list] = {}
    for zone, which in zones.items():
        rings.setdefault(zone[0], []).append((zone, which))
    start = time.perf_counter()
    done = list(map_jobs(_trace_ring, list(rings.values()), workers, state=_ZoneTracer(camera, config),
                         desc="tracing zone kernels", unit="θ ring", progress=progress))
    traced, made = int(sum(t for t, _ in done)), int(sum(m for _, m in done))
    return {"camera_sha256": camera.sha256(), "calibration_id": camera.calibration_id, "zones": len(zones),
            "kernel_sets": int(sum(len(w) for w in zones.values())), "kernel_sets_traced": traced,
            "evidence_models_made": made,
            "cache_dir": str(decoder.zones.psf_map.exact_cache_dir), "wall_s": time.perf_counter() - start}


def decode_frame(decoder: ClassicalDecoder, frame, camera: BuiltCamera, progress: bool = False) -> DecodedFrame:
    """Decode a ``devices.RawFrame`` taken by ``camera`` (refused, naming why, when it cannot be). The result's
    ``parts["classical"]`` is the decoder's whole ``decode.DecodeResult`` (window grids, evidence)."""
    check_decodable(frame, camera.lens_name, "the decoder's camera has", "the classical decoder")
    check_classical_memory(decoder.config, *frame.data.shape)
    out = decoder.decode(frame.data, frame.black_level_dn, frame.white_level_dn, frame.geometry,
                         row0=frame.roi.y_px, col0=frame.roi.x_px, cfa=frame.cfa, progress=progress,
                         noise_profile=frame.noise_profile)
    stats = dict(out.stats, camera_sha256=camera.sha256(), calibration_id=camera.calibration_id)
    skipped = stats["candidate_evaluations_exhaustive"] - stats["candidate_evaluations"]
    report = {"valid_fraction": float(out.valid.mean()), "blocks_run": stats["blocks_run"],
              "blocks_skipped": stats["blocks_skipped"], "candidate_evaluations_skipped": int(skipped),
              "decoder_stats": stats, "timings_s": stats["timings_s"]}
    return DecodedFrame(out.aif, out.depth_m, out.valid, out.depth_sigma_m, report, {"classical": out, "stats": stats})
