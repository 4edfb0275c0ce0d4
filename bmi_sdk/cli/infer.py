"""`bmi infer RAW.dng --out DIR`: decode one raw frame into AiF RGB, range map, point cloud and a report."""

from __future__ import annotations

import argparse
import time

from ..option_values import OptionError, number, whole
from ._logging import bars_shown


def window_px(text: str) -> int:
    """``--window-px``: a whole multiple of 4, at least 16 (``decode.ClassicalConfig``'s rule)."""
    value = whole(16)(text)
    if value % 4:
        raise argparse.ArgumentTypeError(f"{text} is not a multiple of 4; valid: [16, inf), a multiple of 4")
    return value


def noise_sigma(text: str) -> float:
    """``--noise-sigma``: a raw noise σ in (0, ``decode.classical.NOISE_SIGMA_MAX``] (units of full scale)."""
    from bmi_sdk.decode.classical import NOISE_SIGMA_MAX

    return number(0, NOISE_SIGMA_MAX, lo_open=True)(text)


def depth_range(text: str) -> tuple[float, float]:
    """``--depth-range NEAR,FAR`` (metres) → (near, far), refused unless 0 < NEAR < FAR."""
    from bmi_sdk.runtime.outputs import check_depth_range

    parts = text.split(",")
    if len(parts) != 2:
        raise OptionError(f"--depth-range wants NEAR,FAR in metres (e.g. 0.7,10), got {text!r}", "--depth-range")
    try:
        return check_depth_range(parts)
    except ValueError as exc:
        raise OptionError(f"--depth-range {text}: {exc}", "--depth-range") from None


CLASSICAL_FLAGS = {
    "window_px": (window_px, "evidence window (px), a multiple of 4 >= 16"),
    "stride_px": (whole(2, even=True), "window stride (px), even >= 2"),
    "candidates": (whole(3, 1000), "depth candidates spaced in 1/d, snapped to the kernel grid (3 to 1000)"),
    "noise_sigma": (noise_sigma, "a constant raw noise σ in units of full scale, > 0 and at most half the range "
                                 "(default: the frame's NoiseProfile tag, the camera's photon transfer; estimated from "
                                 "the picture when the file has none)"),
    "pool_sigma_px": (number(0), "radius over which each window's evidence pools its like-coloured neighbours' (0: each "
                             "window alone; docs/decoder.md, method step 4b)"),
    "exact_model_below": (number(0, 1), "windows whose mean signal, a fraction of white, is below this are scored with "
                                        "the exact expected periodogram (0: none; docs/decoder.md, method step 2)"),
    "weak_texture_below": (number(0, 1), "sharp windows whose texture contrast (RMS over mean, 3–6 cycles per window) "
                                         "is below this skip the bins within 2 cycles of DC (0: none; docs/decoder.md, "
                                         "method step 2)"),
    "clipped_planes_per_frame": (whole(0, 65536), "(window, colour plane) pairs holding samples at the white level "
                                                  "scored from their other samples, at most, 2-7 ms of one core "
                                                  "each (0: such planes give no evidence; docs/decoder.md, step 2)"),
}
"""The ``decode.ClassicalConfig`` fields ``bmi infer --decoder classical`` takes as flags (``--window-px`` …): their
checked type (``_options``: a bad value is refused by argparse, naming the option and the valid range) and help; each default is the dataclass's own. Any other decoder refuses a changed value."""

WINDOW_KNOBS = ("window_px", "stride_px", "candidates")
"""The classical decoder's window grid options, which ``bmi eval`` takes too (``add_classical_arguments``)."""


def check_texture_exponent(kind: str, texture_exponent: str) -> None:
    """``--texture-exponent``: refused (``OptionError``, before any work) for a decoder that cannot read with it."""
    from bmi_sdk.runtime.decoders import texture_exponent_refusal

    reason = texture_exponent_refusal(kind, texture_exponent)
    if reason is not None:
        raise OptionError(f"--texture-exponent {texture_exponent}: {reason}", "--texture-exponent")


def classical_defaults() -> dict:
    """{field: default} of ``CLASSICAL_FLAGS`` from ``decode.ClassicalConfig`` itself."""
    from dataclasses import fields

    from bmi_sdk.decode import ClassicalConfig

    return {f.name: f.default for f in fields(ClassicalConfig) if f.name in CLASSICAL_FLAGS}


def add_classical_arguments(p, knobs=tuple(CLASSICAL_FLAGS)) -> None:
    """One ``--knob-name`` flag per field of ``knobs`` on parser ``p``, defaulting to ``ClassicalConfig``'s."""
    defaults = classical_defaults()
    for knob in knobs:
        kind, text = CLASSICAL_FLAGS[knob]
        shown = "" if defaults[knob] is None else f" (default {defaults[knob]:g})"
        p.add_argument(f"--{knob.replace('_', '-')}", type=kind, default=defaults[knob], metavar=knob.upper(),
                       help=f"classical: {text}{shown}")


def changed_classical_flags(args, knobs=tuple(CLASSICAL_FLAGS)) -> list[str]:
    """The classical flags of ``knobs`` given another value than ``ClassicalConfig``'s default."""
    defaults = classical_defaults()
    return [f"--{k.replace('_', '-')}" for k in knobs if getattr(args, k) != defaults[k]]


def classical_config(args, knobs=tuple(CLASSICAL_FLAGS)):
    """The ``ClassicalConfig`` of the classical flags ``knobs`` (the dataclass's defaults for every other field)."""
    from bmi_sdk.decode import ClassicalConfig

    return ClassicalConfig(**{knob: getattr(args, knob) for knob in knobs})


def _run(args) -> int:
    from bmi_sdk.cli._infer_many import infer_many, wants_batch
    from bmi_sdk.cli._logging import command_logger
    from bmi_sdk.runtime import DECODERS, run_job
    from bmi_sdk.runtime.decoders import decoder_kind

    if args.depth_range is not None:
        args.depth_range = depth_range(args.depth_range)
    if args.overlap_px is not None and args.overlap_px >= args.tile_px:
        raise OptionError(f"--overlap-px {args.overlap_px} must be less than --tile-px {args.tile_px} (the tiles "
                          "must advance)", "--overlap-px")
    args.decoder = decoder_kind(args.decoder, args.model)
    takes_config = DECODERS[args.decoder].takes_config
    knobs = changed_classical_flags(args)
    if knobs and not takes_config:
        raise ValueError(f"{', '.join(knobs)}: classical decoder options, not taken by the {args.decoder} decoder "
                         "(the learned one decodes with its model's own; use --decoder classical)")
    check_texture_exponent(args.decoder, args.texture_exponent)
    if args.provider is not None:  # an unavailable provider fails here, naming the available ones, before any work
        from bmi_sdk.runtime.model import choose_providers

        if DECODERS[args.decoder].model_kind is None:
            raise ValueError(f"--provider picks the network's onnxruntime provider; the {args.decoder} decoder runs "
                             "none (drop --provider or choose another --decoder)")
        choose_providers(args.provider)
    args.classical_config = classical_config(args) if takes_config else None
    if args.classical_config is not None and args.texture_exponent != "prior":
        from bmi_sdk.decode.classical import with_texture_exponent

        try:  # the texture model's knobs with the classical flags given: refused here, naming both
            with_texture_exponent(args.classical_config, args.texture_exponent)
        except ValueError as exc:
            raise OptionError(f"--texture-exponent {args.texture_exponent} with the classical flags given: {exc}",
                              "--texture-exponent") from None
    if wants_batch(args):
        return infer_many(args)
    args.raw = args.raw[0]

    # frame-quality findings (FrameQualityWarning) reach stderr through logging: "bmi infer: warning: …"
    t0 = time.perf_counter()
    _, report = run_job(args.raw, args.out, decoder=args.decoder, model_path=args.model,
                        calibration_path=args.calibration, classical_config=args.classical_config,
                        tile_px=args.tile_px, threads=args.threads, overlap_px=args.overlap_px,
                        providers=args.provider, ply_step_px=args.ply_step, progress=bars_shown(args.quiet),
                        overwrite=args.overwrite, allow_test_pattern=args.allow_test_pattern,
                        depth_range_m=args.depth_range, texture_exponent=args.texture_exponent)
    wall_s = time.perf_counter() - t0
    log = command_logger("infer")
    log.info("input %s; bmi-sdk %s, onnxruntime %s; execution provider %s", report["input_path"],
             report["software"]["bmi_sdk"], report["software"]["onnxruntime"], report["execution_provider"])
    for line in detail_lines(report):
        log.info("%s", line)
    for line in summary_lines(report, args.out, wall_s):
        print(line)
    return 0


def summary_lines(report: dict, out, wall_s: float) -> list[str]:
    """What ``bmi infer`` prints of a frame's report, in a user's terms: the decoder and the time it took, the
    depth range and how much of it is confident, and where the files are (hashes and internals: ``detail_lines``,
    ``-v``, and report.json)."""
    from bmi_sdk.runtime import DECODERS
    from bmi_sdk.runtime.job import CONFIDENT_RELATIVE_SIGMA

    calibration = f"calibration {report['calibration_id']}" if report["calibration_id"] else "nominal PSFs"
    lines = [f"decoded with the {DECODERS[report['decoder']].title} ({report['decoder']}, {calibration}) "
             f"in {wall_s:.1f} s"]
    span, coverage = report["depth_range_m"], report["confident_coverage"]
    if span is None:
        lines.append("no pixel has a depth")
    else:
        depth = (f"depth {span[0]:.2f}-{span[1]:.2f} m (1st-99th percentile) on {report['valid_fraction']:.0%} "
                 "of the frame")
        if coverage is None:
            depth += "; this decoder reports no 1σ"
        else:
            depth += (f"; confident (1σ ≤ {CONFIDENT_RELATIVE_SIGMA:.0%} of the depth) on {coverage:.0%} of those "
                      "pixels")
        lines.append(depth)
    names = [n for n in report["files"] if n != "points.ply"]
    lines.append(f"wrote {out}/: {', '.join(names)}, points.ply ({report['ply_points']} points), report.json")
    return lines


def detail_lines(report: dict) -> list[str]:
    """The internals of a frame's decode (``bmi infer -v``): model or camera hashes, noise, what ran, memory, the
    fusion's weights, clipped windows and per-stage timings."""
    lines = []
    stats = report.get("decoder_stats")
    who = []
    if "model" in report:
        who.append(f"model {report['model']['preset']} {report['model']['sha256'][:12]}… on "
                   f"{report['execution_provider']}")
    if "camera" in report:
        who.append(f"camera {report['camera']['sha256'][:12]}…")
    if stats is not None:
        who.append(f"noise σ {stats['noise_sigma']:.4f} ({stats['noise_source']})")
    if who:
        lines.append(", ".join(who))
    ran = []
    if "blocks_run" in report:
        ran.append(f"classical blocks run {report['blocks_run']}, skipped {report['blocks_skipped']} (outside the "
                   f"image circle); candidate evaluations {stats['candidate_evaluations']} (coarse + fine) against "
                   f"{stats['candidate_evaluations_exhaustive']} exhaustive")
    if "tiles_run" in report:
        ran.append(f"network tiles run {report['tiles_run']}, skipped {report['tiles_skipped']}")
    lines.append("; ".join(ran + [f"peak memory {report['peak_rss_mb']:.0f} MB"]))
    if "fusion" in report:
        how = {"fitted": "by their 1σ, their disagreement and the classical depth's local variation, with the "
                         "model's fitted weights",
               "inverse-variance": "by their 1σ"}[report["fusion"]["weights"]]
        lines.append(f"depth: the network's fused with the classical stage's {how} (the classical read's mean "
                     f"weight {report['fusion']['classical_weight_mean']:.2f})")
    if stats is not None and stats.get("windows_with_clipped_samples"):
        lines.append(f"evidence windows holding clipped samples {stats['windows_with_clipped_samples']} (read without "
                     f"those planes; {stats['windows_without_evidence']} clipped in every plane take their "
                     "neighbours' depth)")
    lines.append("stages: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in report["stage_timings_s"].items()))
    return lines


def register(subparsers) -> None:
    from bmi_sdk.decode.classical import TEXTURE_EXPONENTS
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER
    from bmi_sdk.scaleout import add_scheduler_argument

    p = subparsers.add_parser("infer", help="raw frame (DNG + sidecar) → AiF image, depth map, point cloud, report",
                              description=__doc__)
    p.add_argument("raw", nargs="+", help="raw frame: a DNG written by a BMI camera (bmi acquire), with its JSON "
                                          "sidecar; several frames, a folder or replay://FOLDER write OUT/<stem>/ each")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--model", default=None,
                   help="ONNX model with its .manifest.json (default: the packaged model of the decoder's kind for "
                        "the frame's lens)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="calibration file from bmi calibrate (validated once; the camera's fitted errors: its "
                        "kernels and rays)")
    p.add_argument("--tile-px", type=whole(4, multiple_of=4), default=512,
                   help="tile size, a multiple of 4 (default 512)")
    p.add_argument("--overlap-px", type=whole(0), default=None,
                   help="tile overlap (default: the model's receptive field, from its manifest: tiled equals untiled)")
    p.add_argument("--provider", default=None, metavar="NAME",
                   help="onnxruntime execution provider for the network, e.g. cpu, cuda, tensorrt or "
                        "CUDAExecutionProvider (default: the best available: TensorRT, CUDA, then CPU)")
    p.add_argument("--threads", type=whole(1, 1024), default=None,
                   help="onnxruntime intra-op threads, 1 to 1024 (default: all cores)")
    p.add_argument("--depth-range", default=None, metavar="NEAR,FAR",
                   help="fixed range (metres) of depth_preview.png's colours, e.g. 0.7,10, so that frames compare "
                        "(default: each frame's 1st-99th percentile)")
    p.add_argument("--ply-step", type=whole(1), default=1, help="one point per N×N pixels in points.ply (default 1)")
    p.add_argument("--decoder", choices=tuple(DECODERS), default=None,
                   help=f"evidence: the classical stage's cost volume read by a small network (evidence.onnx), "
                        f"each window's read taken from its like-coloured neighbours, with a depth 1σ; "
                        f"learned: the classical evidence refined by a network (learned.onnx), with a depth 1σ; "
                        f"classical: depth evidence from the camera's own (calibrated) kernels, no network, with a "
                        f"depth 1σ; cnn: the shipped end-to-end network (default: the kind of --model, else "
                        f"{DEFAULT_DECODER}; docs/decoder.md)")
    add_classical_arguments(p)
    p.add_argument("--texture-exponent", choices=tuple(TEXTURE_EXPONENTS), default="prior",
                   help="evidence and classical decoders: prior, every surface's texture read with natural images' "
                        "mean power spectrum 1/f^2; profiled, each surface's exponent profiled where its pooled "
                        "evidence rejects 2 (for large natural surfaces beyond about 3 m; about 2x the evidence "
                        "stage's time; docs/decoder.md) (default prior)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier run's results in --out (they are replaced only once all new files "
                        "are written)")
    p.add_argument("--allow-test-pattern", action="store_true",
                   help="decode a frame flagged as the camera's test pattern (refused by default)")
    add_scheduler_argument(p)
    p.set_defaults(handler=_run)
