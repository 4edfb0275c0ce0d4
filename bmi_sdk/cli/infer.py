"""`bmi infer RAW.dng --out DIR`: decode one raw frame into AiF RGB, range map, point cloud and a report."""

from __future__ import annotations


def _run(args) -> int:
    from bmi_sdk.cli._infer_many import infer_many, wants_batch
    from bmi_sdk.runtime import run_job

    if wants_batch(args):
        return infer_many(args)
    args.raw = args.raw[0]

    result, report = run_job(args.raw, args.out, model_path=args.model, calibration_id=args.calibration_id,
                             calibration_path=args.calibration,
                             tile_px=args.tile_px, threads=args.threads, overlap_px=args.overlap_px,
                             ply_step_px=args.ply_step, progress=not args.quiet)
    if report["calibration_note"]:
        print(f"note: {report['calibration_note']}")
    t = report["stage_timings_s"]
    print(f"model {report['model']['preset']} sha256 {report['model']['sha256'][:12]}…, "
          f"calibration {report['calibration_id'] or 'nominal PSFs'}")
    print(f"tiles run {result.tiles_run}, skipped {result.tiles_skipped} (outside the image circle); "
          f"peak memory {report['peak_rss_mb']:.0f} MB")
    print("stages: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in t.items()))
    print(f"wrote {args.out}/aif.png, aif.npy, depth.npy, depth_mm.png, points.ply ({report['ply_points']} points), "
          "report.json")
    return 0


def register(subparsers) -> None:
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
                   help="tile overlap (default: receptive field + half the largest PSF, from the manifest)")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: all cores)")
    p.add_argument("--ply-step", type=int, default=1, help="one point per N×N pixels in points.ply (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_scheduler_argument(p)
    p.set_defaults(handler=_run)
