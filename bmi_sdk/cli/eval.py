"""`bmi eval`: the paper's table analogues on the fixed, seeded synthetic benchmark (bmi_sdk.nn.evaluate)."""

from __future__ import annotations

import json
from pathlib import Path

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "models" / "default.onnx"
KEYS = ("absrel", "rmse_m", "delta1", "delta2", "delta3", "psnr_db", "ssim")


def register(subparsers) -> None:
    from bmi_sdk.bench.record import add_json_argument
    from bmi_sdk.cli.infer import WINDOW_KNOBS, add_classical_arguments
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER
    from bmi_sdk.scaleout import add_scheduler_argument

    p = subparsers.add_parser(
        "eval", help="depth and image metrics per condition and field region on the synthetic benchmark",
        description="Noise sweep, hardware errors without retraining and the fisheye baseline on seeded "
                    "procedural tiles at the field centre (0–20°) and edge (50–60°).")
    p.add_argument("--model", default=None,
                   help="the cnn decoder's ONNX model (default: the shipped default.onnx); the learned decoder's is "
                        "--learned-model")
    p.add_argument("--fisheye-model", default=None, help="fisheye-baseline ONNX model (adds fisheye_standard)")
    p.add_argument("--learned-model", default=None,
                   help="learned refinement ONNX model for --decoder learned (default: the shipped learned.onnx)")
    p.add_argument("--conditions", default=None, help="comma list (default: all that apply)")
    p.add_argument("--tiles", type=int, default=12, help="tiles per field region")
    p.add_argument("--tile-px", type=int, default=192)
    p.add_argument("--seed", type=int, default=20260)
    p.add_argument("--scene-scale", type=float, default=1.0, metavar="SCALE",
                   help="draw each tile's scene SCALE× larger and keep its centre: objects SCALE× larger against the "
                        "tile, as a frame's are (default 1: the benchmark's own scale, where only ~3 %% of 64-px "
                        "windows hold one depth); rows then carry a scene_scale key")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    p.add_argument("--decoder", default=DEFAULT_DECODER,
                   help=f"comma list of decoders ({', '.join(DECODERS)}): learned (the classical evidence refined by "
                        f"--learned-model), classical (bmi_sdk.decode, no network), cnn (the ONNX model of --model); "
                        f"e.g. cnn,classical,learned (default {DEFAULT_DECODER})")
    p.add_argument("--no-fusion", action="store_true",
                   help="learned: score the network's depth and AiF alone, not fused with its classical stage's (with the "
                        "weights of its manifest, as bmi infer returns it) nor, on a built camera, pulled to the "
                        "frame through its kernels; its rows carry fusion false")
    add_classical_arguments(p, WINDOW_KNOBS)
    p.add_argument("--jsonl", action="store_true", help="print one JSON object per line per condition and region "
                                                       "instead of the table")
    add_json_argument(p)
    add_scheduler_argument(p)
    p.set_defaults(handler=_run)


def _run(args) -> int:
    from dataclasses import replace

    from bmi_sdk.cli.infer import WINDOW_KNOBS, changed_classical_flags, classical_config, classical_defaults
    from bmi_sdk.model_manifest import verify_model
    from bmi_sdk.nn.evaluate import Benchmark, run_benchmark
    from bmi_sdk.runtime.decoders import decoder_kind
    from bmi_sdk.scaleout import scheduler_address

    decoders = tuple(decoder_kind(d.strip()) for d in args.decoder.split(",") if d.strip())
    if args.model is not None and "cnn" not in decoders:
        raise ValueError(f"--model {args.model} is the cnn decoder's model, and --decoder {args.decoder} does not run "
                         "it (a learned refinement is --learned-model)")
    args.model = args.model or str(DEFAULT_MODEL)
    changed = changed_classical_flags(args, WINDOW_KNOBS)
    if changed and "classical" not in decoders:
        raise ValueError(f"{', '.join(changed)} set(s) the classical decoder, and --decoder {args.decoder} does not "
                         "run it (a learned refinement decodes with the knobs its manifest was trained with)")
    if "cnn" in decoders:
        verify_model(args.model)
    if args.fisheye_model:
        verify_model(args.fisheye_model)
    windows = {"classical": args.window_px} if "classical" in decoders else {}
    if "learned" in decoders:
        from bmi_sdk.model_manifest import model_decoder
        from bmi_sdk.runtime.model import LEARNED_MODEL

        args.learned_model = args.learned_model or str(LEARNED_MODEL)
        manifest = verify_model(args.learned_model)
        if model_decoder(manifest) != "learned":
            raise ValueError(f"--learned-model {args.learned_model} is not a learned refinement model")
        windows["learned"] = int(manifest["classical_config"].get("window_px", classical_defaults()["window_px"]))
    for decoder, window_px in windows.items():
        if args.tile_px < window_px:
            raise ValueError(f"--tile-px {args.tile_px} holds no {window_px}-px evidence window of the {decoder} "
                             "decoder: its depth would be a guess")
    if args.no_fusion and "learned" not in decoders:
        raise ValueError("--no-fusion scores the learned decoder's network alone; add learned to --decoder")
    bench = Benchmark(tiles=args.tiles, tile_px=args.tile_px, seed=args.seed, threads=args.threads,
                      scene_scale=args.scene_scale)
    conditions = [c.strip() for c in args.conditions.split(",")] if args.conditions else None
    config = classical_config(args, WINDOW_KNOBS)
    with scheduler_address(args.scheduler, announce=not args.jsonl) as scheduler:  # benchmark tiles render there
        rows = run_benchmark(args.model, replace(bench, scheduler=scheduler), conditions, args.fisheye_model,
                             progress=not args.jsonl, decoders=decoders, classical_config=config,
                             learned_model=args.learned_model, learned_fusion=not args.no_fusion)
    if args.json:
        from bmi_sdk.bench.record import write_record

        write_record(args.json, [eval_table(rows, bench)])
    if args.jsonl:
        scale = {"scene_scale": bench.scene_scale} if bench.scene_scale != 1 else {}
        for row in rows:
            print(json.dumps({**{k: row[k] for k in ("condition", "decoder", "region", *KEYS, "sigma_z_rms",
                                                     "sigma_z_std", "fusion") if k in row}, **scale}))
        return 0
    print("| condition | decoder | region | AbsRel | RMSE (m) | δ<1.25 | δ<1.25² | δ<1.25³ | PSNR (dB) | SSIM | σ z std |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        z = f"{r['sigma_z_std']:.2f}" if "sigma_z_std" in r else "–"
        print(f"| {r['condition']} | {_decoder_name(r)} | {r['region']} | {r['absrel']:.3f} | {r['rmse_m']:.3f} | "
              f"{r['delta1']:.3f} | {r['delta2']:.3f} | {r['delta3']:.3f} | {r['psnr_db']:.2f} | {r['ssim']:.3f} | {z} |")
    return 0


def _decoder_name(row: dict) -> str:
    return row["decoder"] + (" (network alone)" if row.get("fusion") is False else "")


def eval_table(rows: list[dict], bench) -> dict:
    """The ``--json`` record's table of ``run_benchmark``'s rows: one row per condition, decoder and region."""
    columns = ["condition", "decoder", "region", *KEYS, "sigma_z_rms", "sigma_z_std"]
    return {"title": "Synthetic benchmark",
            "columns": columns,
            "rows": [[_decoder_name(r) if k == "decoder" else r.get(k) for k in columns] for r in rows],
            "notes": f"{bench.tiles} tiles of {bench.tile_px}² px per field region (centre 0–20°, edge 50–60°), "
                     f"seed {bench.seed}, scene scale {bench.scene_scale:g}."}
