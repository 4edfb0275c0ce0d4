"""`bmi infer A.dng B.dng … | FOLDER | replay://FOLDER --out DIR [--scheduler …]`: many frames, DIR/<stem>/ each.

Kept apart from ``infer.py`` (the single-frame command) so that the batch and the Dask wiring stay in one
place; ``infer.py`` hands over here when its arguments name a batch or a scheduler.
"""

from __future__ import annotations

from ._logging import bars_shown


def wants_batch(args) -> bool:
    """True when the frames are several, a folder or a replay, or a scheduler is given."""
    from bmi_sdk.runtime.batch import is_batch

    return bool(args.scheduler) or is_batch(args.raw)


def infer_many(args) -> int:
    """Decode every frame; print one line per frame and a total; exit status 1 when any frame failed."""
    import time

    from bmi_sdk.runtime.batch import DecodeOptions, plan_outputs, run_batch
    from bmi_sdk.scaleout import open_client

    jobs = plan_outputs(args.raw, args.out)
    options = DecodeOptions(model_path=args.model, calibration_path=args.calibration, tile_px=args.tile_px,
                            threads=args.threads, overlap_px=args.overlap_px, ply_step_px=args.ply_step,
                            decoder=args.decoder, classical_config=args.classical_config, overwrite=args.overwrite,
                            allow_test_pattern=args.allow_test_pattern, providers=args.provider,
                            depth_range_m=args.depth_range, texture_exponent=args.texture_exponent)
    t0 = time.perf_counter()
    with open_client(args.scheduler) as client:
        summaries = run_batch(jobs, options, client=client, progress=bars_shown(args.quiet))
    wall_s = time.perf_counter() - t0
    failed = [s for s in summaries if not s["ok"]]
    for s in summaries:
        if s["ok"]:
            ran = [f"{s['decoder']} decoder"]
            ran += [f"{s['blocks_run']} blocks"] if s["blocks_run"] is not None else []
            ran += [f"{s['tiles_run']} tiles"] if s["tiles_run"] is not None else []
            ran += [f"{s['seconds']:.1f} s"]
            ran += [f"model {s['model_sha256'][:12]}…"] if s["model_sha256"] else []
            ran += [f"camera {s['camera_sha256'][:12]}…"] if s["camera_sha256"] else []
            print(f"{s['frame']} → {s['out']}: {', '.join(ran)}")
        else:
            print(f"{s['frame']}: FAILED: {s['error']}")
    print(f"{len(summaries) - len(failed)} of {len(summaries)} frames decoded in {wall_s:.1f} s "
          f"({len(summaries) / wall_s:.2f} frames/s) on {args.scheduler or 'this process'}")
    return 1 if failed else 0
