"""`bmi demo` (the `make demo` target): the SDK's main job on the embedded default.

Stages, each timed: the lens report and a PSF gallery across depth and field;
a procedural scene (RGB + range); a full-resolution capture of it from the
simulated camera (saved as ``frame.dng`` + sidecar, so ``bmi infer`` can be
re-run on it); tiled inference with the packaged model; the output files
(AiF image, depth map, point cloud, report); the error against the scene's
ground truth.

The capture goes through the optical simulation (source ``procedural:SEED``)
when ``firmware_sim`` has it registered, else through the optics-free
in-focus stand-in (said loudly: depth is then not encoded in the frame). The
model is ``bmi_sdk/models/default.onnx`` when shipped, else an *untrained*
export of the ``tiny`` preset (said loudly: its errors mean nothing).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

OPTICAL_SCENE_SOURCE = "procedural"
"""Name under which the forward simulator registers its procedural scene source (``procedural:SEED``)."""

CAPTURE_TIMEOUT_S = 1800.0



def _stage(timings: dict, name: str, t0: float) -> None:
    timings[name] = time.perf_counter() - t0
    print(f"[{timings[name]:7.2f} s] {name}", flush=True)


def _source(seed: int, scene):
    import firmware_sim
    from firmware_sim.sources import InFocusImageStandIn

    if OPTICAL_SCENE_SOURCE in firmware_sim.source_names():
        return firmware_sim.make_source(f"{OPTICAL_SCENE_SOURCE}:{seed}"), None
    warning = (f"firmware_sim has no {OPTICAL_SCENE_SOURCE!r} optical source yet: capturing through the optics-free "
               "in-focus stand-in (no PSF, no depth encoding; the depth error below is not meaningful)")
    return InFocusImageStandIn(scene.rgb, label=f"procedural seed {seed}"), warning


def _model(out: Path, explicit: str | None):
    from bmi_sdk.runtime import DEFAULT_MODEL, export_model

    if explicit:
        return Path(explicit), None
    if DEFAULT_MODEL.is_file():
        return DEFAULT_MODEL, None
    import torch

    from bmi_sdk.nn.model import DualHeadMimoUNet, InferenceWrapper, preset_config

    path = out / "untrained_tiny.onnx"
    if not path.is_file():
        torch.manual_seed(0)
        export_model(InferenceWrapper(DualHeadMimoUNet(preset_config("tiny"))), path, preset="tiny",
                     probe_px=512, training={"weights": "untrained (random, seed 0): no shipped model yet"})
    return path, (f"no shipped model at {DEFAULT_MODEL}: using an UNTRAINED tiny-preset export "
                  "(the pipeline runs end to end; its AiF/depth errors mean nothing)")


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


def _run(args) -> int:
    from bmi_sdk.cli.lens import _print_table
    from bmi_sdk.io_atomic import write_json
    from bmi_sdk.optics import get_lens, lens_report
    from bmi_sdk.optics.gallery import psf_gallery

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    lens = get_lens("bmi_monocentric")
    _print_table(lens_report(lens))
    _stage(timings, "lens report", t0)
    t0 = time.perf_counter()
    gallery = out / "psf_gallery.png"
    psf_gallery(lens, gallery)
    _stage(timings, f"PSF gallery → {gallery}", t0)

    from bmi_sdk.runtime import Model, run_job
    from bmi_sdk.scenes import generate_scene
    from devices import open_camera
    from firmware_sim import FirmwareDevice

    t0 = time.perf_counter()
    scene = generate_scene(4500, 6000, args.seed)
    _stage(timings, f"procedural scene (seed {args.seed}, 6000×4500, range "
                    f"{np.nanmin(scene.range_m):.2f}–{np.nanmax(scene.range_m):.2f} m)", t0)

    t0 = time.perf_counter()
    source, source_warning = _source(args.seed, scene)
    if source_warning:
        logging.getLogger("bmi.demo").warning("%s", source_warning)
    device = FirmwareDevice(seed=args.seed)
    device.load_source(source)
    # The capture is a full-frame exact-mode optical render: ~160 s on an idle 2-core machine, several
    # times that when the machine is shared; the wait is generous so a slow machine is not a failure.
    with open_camera("sim://demo", device=device, timeout_s=CAPTURE_TIMEOUT_S) as cam:
        frame = cam.capture(timeout_s=CAPTURE_TIMEOUT_S)
    dng = out / "frame.dng"
    frame.save_dng(dng)
    _stage(timings, f"acquire full-resolution frame {frame.data.shape[1]}×{frame.data.shape[0]} from sim:// "
                    f"({source.name}) → {dng}", t0)

    t0 = time.perf_counter()
    model_path, model_warning = _model(out, args.model)
    if model_warning:
        logging.getLogger("bmi.demo").warning("%s", model_warning)
        _stage(timings, f"export untrained stand-in model → {model_path}", t0)
    t0 = time.perf_counter()
    model = Model(model_path, tile_px=args.tile_px)
    _stage(timings, f"load model {model_path.name} (SHA-256 checked, preset {model.manifest['preset']}) "
                    f"+ warm-up {model.warmup_s:.2f} s", t0)

    t0 = time.perf_counter()
    result, report = run_job(frame, out, model=model, progress=True, overwrite=True)  # the demo regenerates its folder
    for name, value in result.timings_s.items():
        print(f"            {name[:-2]:>10}: {value:7.2f} s")
    _stage(timings, f"infer {result.tiles_run} tiles ({result.tiles_skipped} skipped) + write outputs "
                    f"({report['stage_timings_s']['write_outputs_s']:.2f} s) → {out}", t0)

    t0 = time.perf_counter()
    err = errors_against_truth(result.aif, result.depth_m, result.valid, scene)
    _stage(timings, "error against ground truth", t0)
    print(f"AiF  MAE {err['aif_mae']:.4f}  PSNR {err['aif_psnr_db']:.2f} dB (linear RGB)")
    print(f"depth MAE {err['depth_mae_m']:.3f} m  AbsRel {err['depth_abs_rel']:.3f}  "
          f"δ<1.25 {100 * err['depth_delta_1.25']:.1f} %  over {err['pixels']} pixels")
    for w in (source_warning, model_warning):
        if w:
            print(f"WARNING: {w}")
    print(f"peak memory {report['peak_rss_mb']:.0f} MB; total {sum(timings.values()):.1f} s")
    write_json(out / "demo_report.json", {"stages_s": timings, "errors": err, "warnings": [w for w in (
        source_warning, model_warning) if w], "infer_report": "report.json"})
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the SDK's main job on the embedded default scene",
                              description=__doc__)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--seed", type=int, default=7, help="procedural scene seed (default 7)")
    p.add_argument("--model", default=None, help="ONNX model + manifest (default: the shipped model)")
    p.add_argument("--tile-px", type=int, default=512, help="inference tile size (default 512)")
    p.set_defaults(handler=_run)
