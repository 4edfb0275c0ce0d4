"""`bmi infer RAW.dng --out DIR`: decode one raw frame into AiF RGB, range map, point cloud and a report."""

from __future__ import annotations


def depth_range(text: str) -> tuple[float, float]:
    """``--depth-range NEAR,FAR`` (metres) → (near, far), refused unless 0 < NEAR < FAR."""
    from bmi_sdk.runtime.outputs import check_depth_range

    parts = text.split(",")
    if len(parts) != 2:
        raise ValueError(f"--depth-range wants NEAR,FAR in metres (e.g. 0.7,10), got {text!r}")
    try:
        return check_depth_range(parts)
    except ValueError as exc:
        raise ValueError(f"--depth-range {text}: {exc}") from None


CLASSICAL_KNOBS = {"window_px": 64, "stride_px": 16, "candidates": 48, "noise_sigma": None, "pool_sigma_px": 48.0}
"""``--decoder classical``'s options and their defaults (``ClassicalConfig``'s: a test holds them equal); any other
value with another decoder is refused."""


WINDOW_KNOBS = ("window_px", "stride_px", "candidates")
"""The classical decoder's window grid options, which ``bmi eval`` takes too (``add_window_arguments``)."""


def add_window_arguments(p) -> None:
    """``--window-px``, ``--stride-px`` and ``--candidates`` (defaults ``CLASSICAL_KNOBS``) on parser ``p``."""
    p.add_argument("--window-px", type=int, default=CLASSICAL_KNOBS["window_px"],
                   help="classical: evidence window (default 64)")
    p.add_argument("--stride-px", type=int, default=CLASSICAL_KNOBS["stride_px"],
                   help="classical: window stride (default 16)")
    p.add_argument("--candidates", type=int, default=CLASSICAL_KNOBS["candidates"],
                   help="classical: depth candidates spaced in 1/d, snapped to the kernel grid (default 48)")


def classical_config(args):
    """The ``ClassicalConfig`` of ``--decoder classical``'s options."""
    from bmi_sdk.decode import ClassicalConfig

    return ClassicalConfig(**{knob: getattr(args, knob) for knob in CLASSICAL_KNOBS})


def _run(args) -> int:
    from bmi_sdk.cli._infer_many import infer_many, wants_batch
    from bmi_sdk.cli._logging import command_logger
    from bmi_sdk.runtime import run_job
    from bmi_sdk.runtime.job import decoder_for

    if args.depth_range is not None:
        args.depth_range = depth_range(args.depth_range)
    args.decoder = decoder_for(args.decoder, model_path=args.model)
    knobs = [f"--{k.replace('_', '-')}" for k, default in CLASSICAL_KNOBS.items() if getattr(args, k) != default]
    if knobs and args.decoder != "classical":
        raise ValueError(f"{', '.join(knobs)}: classical decoder options, not taken by the {args.decoder} decoder "
                         "(the learned one decodes with its model's own; use --decoder classical)")
    if args.provider is not None:  # an unavailable provider fails here, naming the available ones, before any work
        from bmi_sdk.runtime.model import choose_providers

        if args.decoder == "classical":
            raise ValueError("--provider picks the network's onnxruntime provider; the classical decoder runs none "
                             "(drop --provider or use --decoder cnn)")
        choose_providers(args.provider)
    if wants_batch(args):
        return infer_many(args)
    args.raw = args.raw[0]

    options = {"classical_config": classical_config(args)} if args.decoder == "classical" else {}

    # frame-quality findings (FrameQualityWarning) reach stderr through logging: "bmi infer: warning: …"
    result, report = run_job(args.raw, args.out, model_path=args.model, calibration_id=args.calibration_id,
                             calibration_path=args.calibration,
                             tile_px=args.tile_px, threads=args.threads, overlap_px=args.overlap_px,
                             ply_step_px=args.ply_step, progress=not args.quiet, overwrite=args.overwrite,
                             allow_test_pattern=args.allow_test_pattern, decoder=args.decoder,
                             depth_range_m=args.depth_range,
                             **({"providers": args.provider} if args.provider else {}), **options)
    command_logger("infer").info("input %s; bmi-sdk %s, onnxruntime %s; execution provider %s",
                                 report["input_path"], report["software"]["bmi_sdk"],
                                 report["software"]["onnxruntime"], report["execution_provider"])
    if report["decoder"] == "learned":
        stats = report["decoder_stats"]
        print(f"learned refinement {report['model']['sha256'][:12]}… on {report['execution_provider']}, camera "
              f"{report['camera']['sha256'][:12]}…, calibration {report['calibration_id'] or 'nominal PSFs'}, "
              f"noise σ {stats['noise_sigma']:.4f} ({stats['noise_source']})")
        print(f"classical blocks run {stats['blocks_run']}, skipped {stats['blocks_skipped']}; network tiles run "
              f"{report['tiles_run']}, skipped {report['tiles_skipped']}; peak memory {report['peak_rss_mb']:.0f} MB")
        how = {"fitted": "by their 1σ, their disagreement and the classical depth's local variation, with the "
                         "model's fitted weights",
               "inverse-variance": "by their 1σ"}[report["fusion"]["weights"]]
        print(f"depth: the network's fused with the classical stage's {how} (the classical read's mean weight "
              f"{report['fusion']['classical_weight_mean']:.2f})")
        _print_clipped(stats)
        print(f"wrote {args.out}/aif.png, aif.npy, depth.npy, depth_z.npy, depth_sigma.npy, confidence.png, depth_mm.png, "
              f"points.ply ({report['ply_points']} points, with σ), report.json")
        return 0
    if report["decoder"] == "classical":
        stats = report["decoder_stats"]
        print(f"classical decoder, camera {report['camera']['sha256'][:12]}…, "
              f"calibration {report['calibration_id'] or 'nominal PSFs'}, noise σ {stats['noise_sigma']:.4f} "
              f"({stats['noise_source']})")
        print(f"blocks run {stats['blocks_run']}, skipped {stats['blocks_skipped']} (outside the image circle); "
              f"candidate evaluations {stats['candidate_evaluations']} (coarse + fine) against "
              f"{stats['candidate_evaluations_exhaustive']} exhaustive; peak memory {report['peak_rss_mb']:.0f} MB")
        _print_clipped(stats)
        print("stages: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in stats["timings_s"].items()))
        print(f"wrote {args.out}/aif.png, aif.npy, depth.npy, depth_z.npy, depth_sigma.npy, confidence.png, depth_mm.png, "
              f"points.ply ({report['ply_points']} points, with σ), report.json")
        return 0
    if report["calibration_note"]:
        command_logger("infer").warning("%s", report["calibration_note"])
    t = report["stage_timings_s"]
    print(f"model {report['model']['preset']} sha256 {report['model']['sha256'][:12]}… on "
          f"{report['execution_provider']}, "
          f"calibration {report['calibration_id'] or 'nominal PSFs'}")
    print(f"tiles run {result.tiles_run}, skipped {result.tiles_skipped} (outside the image circle); "
          f"peak memory {report['peak_rss_mb']:.0f} MB")
    print("stages: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in t.items()))
    print(f"wrote {args.out}/aif.png, aif.npy, depth.npy, depth_z.npy, depth_mm.png, points.ply ({report['ply_points']} points), "
          "report.json")
    return 0


def register(subparsers) -> None:
    from bmi_sdk.runtime.job import DEFAULT_DECODER
    from bmi_sdk.scaleout import add_scheduler_argument

    p = subparsers.add_parser("infer", help="raw frame (DNG + sidecar) → AiF image, depth map, point cloud, report",
                              description=__doc__)
    p.add_argument("raw", nargs="+", help="raw frame: a DNG written by a BMI camera (bmi acquire), with its JSON "
                                          "sidecar; several frames, a folder or replay://FOLDER write OUT/<stem>/ each")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--model", default=None,
                   help="ONNX model with its .manifest.json (default: the packaged model for the calibration)")
    p.add_argument("--calibration-id", default=None,
                   help="calibration in use (default: the frame's); picks the model trained on its PSF tensor")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="calibration file from bmi calibrate (validated; its id picks the model)")
    p.add_argument("--tile-px", type=int, default=512, help="tile size, a multiple of 4 (default 512)")
    p.add_argument("--overlap-px", type=int, default=None,
                   help="tile overlap (default: the model's receptive field, from its manifest: tiled equals untiled)")
    p.add_argument("--provider", default=None, metavar="NAME",
                   help="onnxruntime execution provider for the network, e.g. cpu, cuda, tensorrt or "
                        "CUDAExecutionProvider (default: the best available: TensorRT, CUDA, then CPU)")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: all cores)")
    p.add_argument("--depth-range", default=None, metavar="NEAR,FAR",
                   help="fixed range (metres) of depth_preview.png's colours, e.g. 0.7,10, so that frames compare "
                        "(default: each frame's 1st-99th percentile)")
    p.add_argument("--ply-step", type=int, default=1, help="one point per N×N pixels in points.ply (default 1)")
    p.add_argument("--decoder", choices=("cnn", "classical", "learned"), default=None,
                   help=f"cnn: the shipped end-to-end network; classical: depth evidence from the camera's own "
                        f"(calibrated) kernels, no network, writes the depth 1σ; learned: the classical evidence "
                        f"refined by a network (learned.onnx), with a depth 1σ (default: the kind of --model, "
                        f"else {DEFAULT_DECODER}; docs/decoder.md)")
    add_window_arguments(p)
    p.add_argument("--noise-sigma", type=float, default=None,
                   help="classical: a constant raw noise σ in units of full scale (default: the frame's NoiseProfile "
                        "tag, the camera's photon transfer; estimated from the picture when the file has none)")
    p.add_argument("--pool-sigma-px", type=float, default=CLASSICAL_KNOBS["pool_sigma_px"],
                   help="classical: radius over which each window's evidence pools its like-coloured neighbours' "
                        "(default 48; 0: each window alone; docs/decoder.md, method step 4b)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier run's results in --out (they are replaced only once all new files "
                        "are written)")
    p.add_argument("--allow-test-pattern", action="store_true",
                   help="decode a frame flagged as the camera's test pattern (refused by default)")
    add_scheduler_argument(p)
    p.set_defaults(handler=_run)


def _print_clipped(stats: dict) -> None:
    """Say how many evidence windows held samples at the white level (they are read without those planes)."""
    if stats.get("windows_with_clipped_samples"):
        print(f"evidence windows holding clipped samples {stats['windows_with_clipped_samples']} (read without "
              f"those planes; {stats['windows_without_evidence']} clipped in every plane take their neighbours' depth)")
