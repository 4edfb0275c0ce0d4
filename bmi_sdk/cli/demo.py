"""`bmi demo` (the `make demo` target): the SDK's main job, end to end, on the embedded procedural scene.

Stages, each timed, each showing its progress while it runs: the lens report and a PSF gallery across
depth and field; the procedural scene (seed 7 by default: the scene of ``sim://…?scene=procedural:7``,
RGB + range, over the whole 6000×4500 sensor); a capture of a window of it through the lens by the
simulated camera (saved as ``frame.dng`` + sidecar, so ``bmi infer`` can be re-run on it); the decode
with the default decoder (``runtime.decoders.DEFAULT_DECODER``, or ``--decoder``) and its output files
(AiF image, range map, point cloud, ``report.json``); the error of that decode against the scene's own
ground truth over the same window.

The window is ``--size`` (default 1536×1024, 1.6 MP, holding the optical axis): ~140 CPU-seconds with a
cold PSF cache, ~56 MB of files. ``--full-frame`` captures the whole 6000×4500 sensor (27 MP): its exact-mode
render (~95 s), the first tracing of a full frame's kernels (~190 s) and the decode (~55 s) take ~6 min on
an idle 2-core machine (docs/benchmarks.md), and its files ~1 GB, so it is an option, not the default.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..option_values import whole
from ._logging import bars_shown

DEFAULT_SIZE_PX = (1536, 1024)
"""The captured window (width, height), holding the optical axis (``centred_roi``): 1.6 MP, 1/17 of the sensor;
~140 CPU-seconds with a cold PSF cache, so under 5 min on 2 cores even with half of them taken by other work."""

MIN_SIZE_PX = 128
"""The smallest window side the demo takes: room for every decoder's evidence windows (the tests' fast demo)."""

DEFAULT_PLY_STEP_PX = 4
"""One point per 4×4 pixels: the default window gives ~0.1 M points (2 MB), a full frame ~1.7 M (~32 MB), both of
which a point-cloud viewer opens at once (every pixel of a full frame: 27 M points, ~400 MB)."""

CAPTURE_TIMEOUT_S = 1800.0
"""How long the camera may stay silent: the render heartbeats every second, so this only catches a hang."""

TICK_S = 0.5
"""How often a stage's elapsed-time line is redrawn."""


class Stage:
    """One timed stage of the demo (a context manager).

    It prints its name when it starts and its time when it ends (recorded in ``timings``). A stage with no
    progress of its own (``ticker=True``) shows a live elapsed-time line on stderr (tqdm, like the
    decoders' own bars), so no stage is silent for more than ``TICK_S``; none under ``bmi -q``.
    """

    def __init__(self, timings: dict, name: str, ticker: bool = True):
        self.timings, self.name, self.ticker = timings, name, ticker
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Stage:
        print(f"▶ {self.name}", flush=True)
        self.t0 = time.perf_counter()
        if self.ticker and bars_shown():
            from tqdm import tqdm

            bar = tqdm(total=None, desc=f"  {self.name}", bar_format="{desc}: {elapsed}", leave=False)

            def tick():
                while not self._stop.wait(TICK_S):
                    bar.refresh()
                bar.close()

            self._thread = threading.Thread(target=tick, name="demo-stage-ticker", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        elapsed_s = time.perf_counter() - self.t0
        self.timings[self.name] = elapsed_s
        if exc[0] is None:
            print(f"[{elapsed_s:7.2f} s] {self.name}", flush=True)


def parse_size(text: str) -> tuple[int, int]:
    """``--size WxH`` (``×`` also taken) as (width_px, height_px): even (whole RGGB cells), at least
    ``MIN_SIZE_PX``, inside the 6000×4500 sensor."""
    from bmi_sdk.geometry import BMI_SENSOR

    sensor = BMI_SENSOR
    valid = (f"WIDTHxHEIGHT, even, {MIN_SIZE_PX}–{sensor.width_px} × {MIN_SIZE_PX}–{sensor.height_px} px "
             "(or --full-frame)")
    try:
        width_px, height_px = (int(v) for v in text.lower().replace("×", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT; valid: {valid}") from None
    if not (MIN_SIZE_PX <= width_px <= sensor.width_px and MIN_SIZE_PX <= height_px <= sensor.height_px) \
            or width_px % 2 or height_px % 2:
        raise argparse.ArgumentTypeError(f"{text} is outside {valid}")
    return width_px, height_px


def centred_roi(width_px: int, height_px: int):
    """The ``devices.Roi`` of that size nearest the sensor's optical axis whose offsets fall on the simulator's
    render blocks (``firmware_sim.optical.BLOCK_PX``, 512 px): the default 1536×1024 window then needs 6 blocks
    rendered instead of 12, and still holds the optical axis (~200 px from its centre)."""
    from bmi_sdk.geometry import BMI_SENSOR
    from devices import Roi
    from firmware_sim.optical import BLOCK_PX

    def offset(size_px: int, sensor_px: int) -> int:  # never past sensor_px - size_px: it rounds half of that
        return round((sensor_px - size_px) / 2 / BLOCK_PX) * BLOCK_PX

    return Roi(offset(width_px, BMI_SENSOR.width_px), offset(height_px, BMI_SENSOR.height_px), width_px, height_px)


def errors_against_truth(aif: np.ndarray, depth_m: np.ndarray, valid: np.ndarray, scene) -> dict:
    """AiF MAE / PSNR (linear RGB) and depth MAE, AbsRel, δ<1.25 over the valid pixels where both ranges are
    finite and > 0. PSNR, AbsRel and δ are ``bmi eval``'s, from ``bmi_sdk.metrics``; the MAEs only the demo reports."""
    from bmi_sdk.metrics import depth_metrics, psnr_db

    ok = valid & np.isfinite(scene.range_m) & np.isfinite(depth_m) & (scene.range_m > 0) & (depth_m > 0)
    if not ok.any():
        raise ValueError("no pixel has both a valid prediction and a known ground-truth range")
    aif_ok, truth_ok = aif[ok], scene.rgb[ok]  # N×3: the metric's float64 copies hold these pixels, not the frame
    depth = depth_metrics(depth_m, scene.range_m, ok)
    d, g = depth_m[ok].astype(np.float64), scene.range_m[ok].astype(np.float64)
    return {"aif_mae": float(np.abs(aif_ok - np.clip(truth_ok, 0, 1)).mean()), "aif_psnr_db": psnr_db(aif_ok, truth_ok),
            "depth_mae_m": float(np.abs(d - g).mean()), "depth_abs_rel": depth["absrel"],
            "depth_delta_1.25": depth["delta1"], "pixels": int(ok.sum())}


def peak_memory_mb() -> dict:
    """Peak resident memory so far, MB: this process's, and that of the largest of its finished child processes
    (the PSF tracing and the classical stage's worker pools). ``/usr/bin/time``'s maximum RSS is the larger."""
    me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {"process_mb": me, "largest_child_mb": kids, "peak_mb": max(me, kids)}


def files_written(out: Path) -> dict:
    """{relative path: bytes} of every file under ``out`` (the demo's whole footprint)."""
    return {str(p.relative_to(out)): p.stat().st_size for p in sorted(out.rglob("*")) if p.is_file()}


def _capture(scene, roi, seed: int, timings: dict, dng: Path):
    """The frame of ``roi`` from a simulated camera looking at ``scene`` through the lens, saved as ``dng``;
    a progress bar follows the render's heartbeats (blocks rendered / needed)."""
    from tqdm import tqdm

    from devices import open_camera
    from firmware_sim import FirmwareDevice
    from firmware_sim.optical import RenderedScene

    # the scene already generated, seen through the lens: the same pixels as the `procedural:SEED` source renders
    source = RenderedScene(scene.rgb, scene.range_m, 0, 0, name="procedural", label=f"procedural seed {seed}")
    device = FirmwareDevice(seed=seed)
    device.load_source(source)
    name = f"capture {roi.width_px}×{roi.height_px} at ({roi.x_px}, {roi.y_px}) through the lens (exact-mode render)"
    with Stage(timings, name, ticker=False):
        bar = tqdm(total=None, desc="  render", unit="block", leave=False, disable=not bars_shown())

        def on_progress(_frame_id: int, done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        try:
            with open_camera("sim://demo", device=device, timeout_s=CAPTURE_TIMEOUT_S, on_progress=on_progress) as cam:
                cam.settings.roi = roi
                frame = cam.capture(timeout_s=CAPTURE_TIMEOUT_S)
        finally:
            bar.close()
        frame.save_dng(dng, overwrite=True)  # the demo's folder is its own: a second run replaces its frame
    return frame


def _run(args) -> int:
    from bmi_sdk.cli.lens import _print_table
    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.io_atomic import write_json
    from bmi_sdk.optics import get_lens, lens_report
    from bmi_sdk.optics.gallery import psf_gallery
    from bmi_sdk.runtime import DECODERS, BuiltCamera, DecoderOptions, open_decoder, run_job
    from bmi_sdk.runtime.decoders import decoder_kind
    from bmi_sdk.scenes import Scene, generate_scene
    from devices import Roi

    kind = decoder_kind(args.decoder, args.model)  # the default decoder unless asked; refused before any work
    width_px, height_px = (BMI_SENSOR.width_px, BMI_SENSOR.height_px) if args.full_frame else args.size
    roi = Roi(0, 0, width_px, height_px) if args.full_frame else centred_roi(width_px, height_px)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    if args.full_frame:
        print("full frame: 6000×4500 px; ~6 min on an idle 2-core machine with a cold PSF cache, ~1 GB of files",
              flush=True)
    else:
        print(f"window {width_px}×{height_px} px of the 6000×4500 sensor, near the optical axis "
              "(--size WxH for another, --full-frame for the whole sensor)", flush=True)

    lens = get_lens("bmi_monocentric")
    with Stage(timings, "lens report", ticker=False):
        _print_table(lens_report(lens))
    gallery = out / "psf_gallery.png"
    with Stage(timings, f"PSF gallery → {gallery}"):
        psf_gallery(lens, gallery)

    with Stage(timings, f"procedural scene, seed {args.seed}, 6000×4500"):
        scene = generate_scene(BMI_SENSOR.height_px, BMI_SENSOR.width_px, args.seed)
    window = (slice(roi.y_px, roi.y_px + roi.height_px), slice(roi.x_px, roi.x_px + roi.width_px))
    truth = Scene(scene.rgb[window], scene.range_m[window], name=f"{scene.name} window")
    print(f"  range in the window {np.nanmin(truth.range_m):.2f}–{np.nanmax(truth.range_m):.2f} m", flush=True)

    frame = _capture(scene, roi, args.seed, timings, out / "frame.dng")
    del scene  # the window's truth is all the error needs

    with Stage(timings, f"open the {kind} decoder ({DECODERS[kind].title}): its model and kernels"):
        decoder = open_decoder(BuiltCamera.for_frame(frame), kind, args.model, options=DecoderOptions(args.tile_px))
    model = getattr(decoder, "model", None)
    with Stage(timings, f"decode with the {kind} decoder + write outputs → {out}"):
        # the demo's folder is its own: a second run replaces its earlier set
        decoded, report = run_job(frame, out, decoder=decoder, progress=bars_shown(), overwrite=True,
                                  ply_step_px=args.ply_step, input_path=out / "frame.dng")
    for name, value in report["stage_timings_s"].items():
        print(f"            {name.removesuffix('_s'):>16}: {value:7.2f} s")

    with Stage(timings, "error against the scene's ground truth"):
        err = errors_against_truth(decoded.aif, decoded.depth_m, decoded.valid, truth)
    model_text = f", model {model.path.name}" if model is not None and hasattr(model, "path") else ""
    source = (f"{DECODERS[kind].title} ({kind} decoder{model_text}) on procedural scene seed {args.seed}, the "
              f"{width_px}×{height_px} window at ({roi.x_px}, {roi.y_px}) of the 6000×4500 sensor, against the "
              "scene's own all-in-focus RGB and range along each pixel's chief ray, over "
              f"{err['pixels']} pixels the decoder marks valid")
    print(f"error of the {source}:")
    print(f"  AiF   MAE {err['aif_mae']:.4f}  PSNR {err['aif_psnr_db']:.2f} dB (linear RGB)")
    print(f"  depth MAE {err['depth_mae_m']:.3f} m  AbsRel {err['depth_abs_rel']:.3f}  "
          f"δ<1.25 {100 * err['depth_delta_1.25']:.1f} %")
    print("  (docs/results.md holds each decoder's errors on bmi eval's tile sets; docs/benchmarks.md its "
          "full-frame ones)")

    memory = peak_memory_mb()
    demo_report = {"schema": "bmi-demo-report/1", "decoder": kind, "scene": {"procedural_seed": args.seed,
                   "roi": vars(roi), "sensor_px": [BMI_SENSOR.width_px, BMI_SENSOR.height_px]},
                   "errors_against": source, "errors": err, "stages_s": timings, "peak_memory": memory,
                   "infer_report": "report.json"}
    write_json(out / "demo_report.json", demo_report)
    files = files_written(out)
    largest = max(files, key=files.get)
    print(f"peak memory {memory['peak_mb']:.0f} MB (this process {memory['process_mb']:.0f} MB, its largest child "
          f"process {memory['largest_child_mb']:.0f} MB); total {sum(timings.values()):.1f} s")
    print(f"wrote {len(files)} files, {sum(files.values()) / 1e6:.1f} MB in {out} (largest: {largest}, "
          f"{files[largest] / 1e6:.1f} MB); points.ply: one point per {args.ply_step}×{args.ply_step} pixels")
    sys.stdout.flush()
    return 0


def register(subparsers) -> None:
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER

    p = subparsers.add_parser("demo", help="run the SDK's main job on the embedded procedural scene",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.path.join("out", "demo"), help="output folder (default out/demo); a second "
                   "run replaces the demo's files there")
    p.add_argument("--seed", type=whole(0), default=7, help="procedural scene seed (default 7)")
    p.add_argument("--size", type=parse_size, default=DEFAULT_SIZE_PX, metavar="WxH",
                   help=f"captured window, near the optical axis (default {DEFAULT_SIZE_PX[0]}x{DEFAULT_SIZE_PX[1]})")
    p.add_argument("--full-frame", action="store_true",
                   help="capture the whole 6000×4500 sensor (~6 min on 2 idle cores, ~1 GB of files)")
    p.add_argument("--decoder", choices=tuple(DECODERS), default=None,
                   help=f"decoder (default: the kind of --model, else the SDK's default, {DEFAULT_DECODER})")
    p.add_argument("--model", default=None, help="ONNX model + manifest for the decoder (default: the packaged one)")
    p.add_argument("--tile-px", type=whole(4, multiple_of=4), default=512,
                   help="inference tile size, a multiple of 4 (default 512)")
    p.add_argument("--ply-step", type=whole(1), default=DEFAULT_PLY_STEP_PX,
                   help=f"one point per N×N pixels in points.ply (default {DEFAULT_PLY_STEP_PX})")
    p.set_defaults(handler=_run)
