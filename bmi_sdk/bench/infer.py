"""`bmi bench infer`: full-frame inference time and peak memory per model, seam error against tile size and
overlap, fp32 against int8.

Models: the ones given with ``--model``, else the packaged default model (if
shipped) plus untrained exports of the ``bmi_sdk.nn`` presets named by
``--presets`` (random weights: run time and memory do not depend on the
weights; the seam error is a property of the tiling). The frame is a
full-resolution capture from the simulated camera, saved as a DNG and read
back like a user's file. Each full-frame run happens in a fresh process so
that its peak RSS is its own.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..option_values import number, size_hw, whole, whole_list
from . import add_json_argument, check_record_path


def register(subparsers) -> None:
    p = subparsers.add_parser("infer", help="full-frame time/memory per model, seams vs tile/overlap, fp32 vs int8")
    p.add_argument("--model", action="append", default=None, help="ONNX model with manifest (repeatable)")
    p.add_argument("--presets", default="tiny,small",
                   help="bmi_sdk.nn presets to export untrained when no --model is given (default tiny,small)")
    p.add_argument("--tile-px", type=whole(64, 4096, unit="px"), default=512)
    p.add_argument("--threads", type=whole(1, 1024), default=None,
                   help="onnxruntime intra-op threads (default: all cores)")
    p.add_argument("--frame-tiles", type=whole_list(64, 4096, unit="px"), default="512,768,1024",
                   help="tile sizes for the full-frame time/memory table of the first model")
    p.add_argument("--seam-tiles", type=whole_list(64, 4096, unit="px"), default="256,512",
                   help="tile sizes for the seam table")
    p.add_argument("--seam-frame", type=size_hw(64, 4096), default="512x768",
                   help="H×W of the frame run whole and tiled")
    p.add_argument("--peak-gflops", type=number(0, lo_open=True), default=175.0,
                   help="the machine's practical onnxruntime peak, GFLOP/s (PACKAGES.md: 150–200 on 2 cores)")
    p.add_argument("--work-dir", default="out/bench_infer")
    add_json_argument(p)
    p.set_defaults(handler=_run)


def _capture(work: Path) -> Path:
    """A full-resolution simulated capture of a procedural scene as DNG (reused between runs)."""
    dng = work / "frame.dng"
    if dng.is_file():
        return dng
    from bmi_sdk.scenes import generate_scene
    from devices import open_camera
    from firmware_sim import FirmwareDevice
    from firmware_sim.sources import InFocusImageStandIn

    dev = FirmwareDevice(seed=1)
    dev.load_source(InFocusImageStandIn(generate_scene(4500, 6000, 7).rgb, label="procedural seed 7"))
    with open_camera("sim://bench-infer", device=dev, timeout_s=120) as cam:
        cam.capture(timeout_s=120).save_dng(dng)
    return dng


def _models(args, work: Path) -> list[Path]:
    from bmi_sdk.runtime import DEFAULT_MODEL, export_model

    if args.model:
        return [Path(m) for m in args.model]
    models = [DEFAULT_MODEL] if DEFAULT_MODEL.is_file() else []
    import torch

    from bmi_sdk.nn.model import DualHeadMimoUNet, InferenceWrapper, preset_config

    for preset in filter(None, args.presets.split(",")):
        path = work / f"untrained_{preset}.onnx"
        if not path.is_file():
            torch.manual_seed(0)
            export_model(InferenceWrapper(DualHeadMimoUNet(preset_config(preset))), path, preset=preset,
                         probe_px=512, training={"weights": "untrained (random, seed 0): speed and seams only"})
        models.append(path)
    return models


def full_frame_child(model_path: str, dng: str, tile_px: int, threads: int | None) -> None:
    """Run in a fresh process: load, warm up, infer one DNG; print timings and peak RSS as one JSON line."""
    from bmi_sdk.bench import peak_rss_mb
    from bmi_sdk.runtime import Model, count_macs, infer_frame
    from devices import load_raw

    model = Model(model_path, tile_px=tile_px, threads=threads)
    frame = load_raw(dng)
    t0 = time.perf_counter()
    result = infer_frame(model, frame)
    wall = time.perf_counter() - t0
    macs = count_macs(model_path, model.tile_px)
    print(json.dumps({"wall_s": wall, "peak_rss_mb": peak_rss_mb(), "tiles": result.tiles_run,
                      "skipped": result.tiles_skipped, "timings_s": result.timings_s, "load_s": model.load_s,
                      "warmup_s": model.warmup_s, "macs_per_tile": macs, "overlap_px": result.plan.overlap_px,
                      "receptive_field_px": model.receptive_field_px}))


def _full_frame(model: Path, dng: Path, tile_px: int, threads: int | None) -> dict:
    code = ("import sys; from bmi_sdk.bench.infer import full_frame_child; "
            f"full_frame_child({str(model)!r}, {str(dng)!r}, {tile_px}, {threads!r})")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"full-frame run of {model.name} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _seam_rows(model_path: Path, frame, window, tiles: list[int], threads) -> tuple[list[list], dict]:
    """Tiled vs untiled on a window of the frame, for several tile sizes and overlaps."""
    from bmi_sdk.model_manifest import verify_model
    from bmi_sdk.runtime import Model, TilePlan, infer_raw
    from bmi_sdk.runtime.tiling import round_up

    r0, c0, h, w = window
    raw = np.ascontiguousarray(frame.data[r0:r0 + h, c0:c0 + w])
    kw = dict(black_level_dn=frame.black_level_dn, white_level_dn=frame.white_level_dn, cfa=frame.cfa,
              geometry=frame.geometry, row0=r0, col0=c0)
    manifest = verify_model(model_path)
    rf = int(manifest["receptive_field_px"])
    pad = TilePlan.for_model(h, w, 1 << 20, rf).pad_px
    whole = Model(model_path, tile_px=round_up(max(h, w) + 2 * pad, 4), threads=threads)
    t0 = time.perf_counter()
    ref = infer_raw(whole, raw, **kw)
    ref_s = time.perf_counter() - t0
    rows = [["untiled", whole.tile_px, "-", 1, ref_s, 0.0, 0.0]]
    for tile in tiles:
        model = Model(model_path, tile_px=tile, threads=threads)
        default = TilePlan.for_model(h, w, tile, rf).overlap_px
        for overlap in sorted({0, round_up(rf // 4, 4), round_up(rf // 2, 4), round_up(rf, 4), default}):
            if overlap >= tile - 4:
                continue
            t0 = time.perf_counter()
            res = infer_raw(model, raw, overlap_px=overlap, **kw)
            dt = time.perf_counter() - t0
            ok = ref.valid & res.valid
            rows.append([f"{tile}", overlap, "default" if overlap == default else "", res.tiles_run, dt,
                         float(np.abs(res.aif - ref.aif)[ok].mean()),
                         float(np.abs(res.depth_m - ref.depth_m)[ok].mean())])
    return rows, {"ref": ref, "raw": raw, "kw": kw}


def _run(args) -> int:
    from bmi_sdk.bench import emit, markdown_table
    from bmi_sdk.model_io import network_input, raw_to_rgb, window_cfa
    from bmi_sdk.model_manifest import read_manifest
    from bmi_sdk.runtime import Model, infer_raw, quantize_int8
    from devices import load_raw

    check_record_path(args.json, args.overwrite)

    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    dng = _capture(work)
    models = _models(args, work)
    frame = load_raw(dng)
    sections = []

    # 1. full frame per model
    rows, rows_by_tile = [], {}
    for m in models:
        r = _full_frame(m, dng, args.tile_px, args.threads)
        if m == models[0]:
            rows_by_tile[args.tile_px] = r
        gflops = 2 * r["macs_per_tile"] * r["tiles"] / r["timings_s"]["network_s"] / 1e9
        rows.append([m.name, read_manifest(m)["preset"], r["receptive_field_px"], r["overlap_px"], r["tiles"],
                     r["wall_s"], r["timings_s"]["network_s"], r["peak_rss_mb"] / 1024, gflops,
                     f"{100 * gflops / args.peak_gflops:.0f} %"])
        print(rows[-1], flush=True)
    table1 = markdown_table(["model", "preset", "receptive field px", "overlap px", "tiles", "frame s",
                             "network s", "peak RSS GB", "GFLOP/s", "of peak"], rows)
    sections.append(f"### Full 6000×4500 frame, {args.tile_px}² tiles\n\n{table1}")

    # 1b. tile size against full-frame time and memory (first model): the overlap is fixed by the model,
    # so bigger tiles recompute less of it, at the cost of a bigger session arena and band
    rows1b = []
    for tile in args.frame_tiles:
        r = rows_by_tile.get(tile) or _full_frame(models[0], dng, tile, args.threads)
        computed_mp = r["tiles"] * tile * tile / 1e6
        rows1b.append([tile, r["overlap_px"], r["tiles"], f"{computed_mp / 27.0:.2f}", r["wall_s"],
                       r["timings_s"]["network_s"], r["peak_rss_mb"] / 1024])
        print(rows1b[-1], flush=True)
    table1b = markdown_table(["tile px", "overlap px", "tiles", "computed px / frame px", "frame s", "network s",
                              "peak RSS GB"], rows1b)
    sections.append(f"### Tile size, model {models[0].name}\n\n{table1b}")

    # 2. seams on a window run whole and tiled (first model)
    h, w = args.seam_frame
    window = ((frame.data.shape[0] - h) // 4 * 2, (frame.data.shape[1] - w) // 4 * 2, h, w)
    seam, ctx = _seam_rows(models[0], frame, window, args.seam_tiles, args.threads)
    table2 = markdown_table(["tile px", "overlap px", "", "tiles", "time s", "AiF MAD", "depth MAD m"], seam)
    sections.append(f"### Seams: tiled vs untiled, {h}×{w} window, model {models[0].name}\n\n{table2}")
    print(table2, flush=True)

    # 3. fp32 vs int8 (first model)
    src = models[0]
    tiles = []
    for k in range(8):
        r0 = (k * 509) % (frame.data.shape[0] - args.tile_px) // 2 * 2
        c0 = (k * 743) % (frame.data.shape[1] - args.tile_px) // 2 * 2
        raw = frame.data[r0:r0 + args.tile_px, c0:c0 + args.tile_px]
        rgb = raw_to_rgb(raw, frame.black_level_dn, frame.white_level_dn, window_cfa(frame.cfa, r0, c0))
        tiles.append(network_input(rgb, frame.geometry, r0, c0))
    q = quantize_int8(src, work / f"{src.stem}_int8.onnx", tiles)
    rows3 = []
    for path in (src, q):
        model = Model(path, tile_px=args.tile_px, threads=args.threads)
        t = []
        for x in tiles[:4]:
            t0 = time.perf_counter()
            model.run(x)
            t.append(time.perf_counter() - t0)
        small = Model(path, tile_px=256, threads=args.threads)
        res = infer_raw(small, ctx["raw"], **ctx["kw"])
        ok = res.valid & ctx["ref"].valid
        full = _full_frame(path, dng, args.tile_px, args.threads)
        rows3.append([read_manifest(path)["preset"], path.stat().st_size / 1e6, float(np.median(t)), full["wall_s"],
                      full["peak_rss_mb"] / 1024, float(np.abs(res.aif - ctx["ref"].aif)[ok].mean()),
                      float(np.abs(res.depth_m - ctx["ref"].depth_m)[ok].mean())])
        print(rows3[-1], flush=True)
    table3 = markdown_table(["model", "file MB", f"s per {args.tile_px}² tile", "frame s", "peak RSS GB",
                             "AiF MAD vs fp32 untiled", "depth MAD m vs fp32 untiled"], rows3)
    sections.append(f"### fp32 vs int8 (static QDQ, per-channel, 8 calibration tiles)\n\n{table3}")
    body = "\n\n".join(sections)
    emit(body, args.json, args.overwrite)
    return 0
