"""`bmi eval`: the paper's table analogues on the fixed, seeded synthetic benchmark (bmi_sdk.nn.evaluate)."""

from __future__ import annotations

import json
import math

from ..option_values import SEED, OptionError, whole
from ._logging import bars_shown

KEYS = ("absrel", "absrel_se", "rmse_m", "delta1", "delta2", "delta3", "psnr_db", "ssim")
SIGMA_KEYS = ("confident_coverage", "confident_absrel", "sigma_z_rms", "sigma_z_std", "sigma_z_within_1")
STRATUM_KEYS = ("pixel_share", "error_share", "absrel", "rmse_m", "delta1")
PAIRED_KEYS = ("tiles", "absrel_diff", "absrel_diff_se", "better_share")


def register(subparsers) -> None:
    from bmi_sdk.bench.record import add_json_argument
    from bmi_sdk.cli.infer import WINDOW_KNOBS, add_classical_arguments
    from bmi_sdk.decode.classical import TEXTURE_EXPONENTS
    from bmi_sdk.nn.evaluate import PAPER_SCENE_SCALE
    from bmi_sdk.nn.sampled_cameras import SAMPLED_CAMERAS
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER
    from bmi_sdk.scaleout import add_scheduler_argument

    p = subparsers.add_parser(
        "eval", help="depth and image metrics per condition and field region on the synthetic benchmark",
        description="Noise sweep, hardware errors without retraining, built cameras read with their fitted "
                    "calibration and the fisheye baseline on seeded procedural tiles at the field centre (0–20°) and "
                    "edge (50–60°); every row broken down by range band and distance to a depth edge.")
    p.add_argument("--decoder", action="append", default=None, metavar="KIND",
                   help=f"decoder(s) to score, repeatable or a comma list, of {', '.join(DECODERS)} (default "
                        f"{DEFAULT_DECODER}, as bmi infer)")
    p.add_argument("--model", action="append", default=None, metavar="ONNX",
                   help="a model for the decoder its manifest names (repeatable, one per decoder); a decoder without "
                        "one reads its packaged model")
    p.add_argument("--fisheye-model", action="append", default=None, metavar="ONNX",
                   help="the same for the fisheye_standard condition (default: the packaged fisheye models; a "
                        "decoder with none for that lens is left out there)")
    p.add_argument("--conditions", default=None, help="comma list (default: all)")
    p.add_argument("--tiles", type=whole(1), default=12, help="tiles per field region")
    p.add_argument("--tile-px", type=whole(4, unit="px", multiple_of=4), default=192,
                   help="tile side, a multiple of 4 (whole Bayer cells)")
    p.add_argument("--seed", type=SEED, default=20260)
    p.add_argument("--scene-scale", type=float, default=PAPER_SCENE_SCALE, metavar="SCALE",
                   help="draw each tile's scene SCALE× larger and keep its centre: objects SCALE× larger against the "
                        "tile (default %(default)g, the seed paper's: a 640-px image in ~750 sensor px); 1 is the "
                        "stress test (a whole room in one tile)")
    p.add_argument("--scales", default=None, metavar="S1,S2,…",
                   help="run at each of these scene scales, e.g. 1,4,16 (the stress test, the paper's, large "
                        "surfaces); replaces --scene-scale")
    p.add_argument("--cameras", type=whole(1), default=SAMPLED_CAMERAS,
                   help="built_camera_sampled: cameras drawn from the calibration's error prior, each captured and "
                        "fitted (~35 s median, up to ~150 s each on 2 cores) and read with its fitted errors "
                        "(default %(default)s)")
    p.add_argument("--reference", default=None, metavar="KIND",
                   help="with two or more decoders: the decoder the others are compared with, tile by tile on the "
                        "same tiles (a third table; default the first --decoder)")
    p.add_argument("--texture-exponent", choices=tuple(TEXTURE_EXPONENTS), default="prior",
                   help="the texture model of the decoders that take one (evidence, classical), as bmi infer's "
                        "(default prior)")
    p.add_argument("--threads", type=whole(1, 1024), default=2, help="onnxruntime intra-op threads")
    add_classical_arguments(p, WINDOW_KNOBS)
    p.add_argument("--jsonl", action="store_true", help="print one JSON object per line per condition, decoder, "
                                                       "region and scale instead of the tables")
    add_json_argument(p)
    add_scheduler_argument(p)
    p.set_defaults(handler=_run)


def _scales(args) -> list[float]:
    if args.scales is None:
        values = [args.scene_scale]
    else:
        try:
            values = [float(s) for s in args.scales.split(",") if s.strip()]
        except ValueError:
            raise OptionError(f"--scales {args.scales}: give a comma list of numbers >= 1, e.g. 1,4,16",
                              "--scales") from None
    bad = [v for v in values if not v >= 1.0]
    if not values or bad:
        flag = "--scales" if args.scales is not None else "--scene-scale"
        raise OptionError(f"{flag} {args.scales or args.scene_scale}: scene scales must be numbers >= 1 (1: the "
                          "tile's own scale)", flag)
    return values


def _check_memory(args, largest) -> None:
    """Refuse, before drawing anything, a run whose tiles' renders or whose largest scene (``largest``: the benchmark
    at its largest scene scale) would not fit in memory (``memory_budget``), naming the option that sized it."""
    from bmi_sdk.memory_budget import check_allocation

    check_allocation("--tiles/--tile-px", f"{args.tiles}/{args.tile_px}", largest.renders_bytes(),
                     "fewer or smaller tiles")
    scale_flag = "--scales" if args.scales is not None else "--scene-scale"
    check_allocation(scale_flag, args.scales or args.scene_scale, largest.scene_bytes(),
                     "a smaller scene scale or --tile-px")


def _run(args) -> int:
    from dataclasses import replace

    from bmi_sdk.bench.record import check_record_path, write_record
    from bmi_sdk.cli.infer import WINDOW_KNOBS, changed_classical_flags, classical_config
    from bmi_sdk.nn.eval_paired import paired_differences
    from bmi_sdk.nn.evaluate import Benchmark, run_benchmark
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER, decoder_kind
    from bmi_sdk.scaleout import scheduler_address

    named = [d.strip() for given in args.decoder or [DEFAULT_DECODER] for d in given.split(",") if d.strip()]
    kinds = []
    for name in named:
        try:
            kinds.append(decoder_kind(name))
        except ValueError as exc:  # the registry's own refusal of a name it does not hold
            raise OptionError(f"--decoder {name}: {exc}", "--decoder") from None
    decoders = tuple(dict.fromkeys(kinds))
    reference = args.reference if args.reference is not None else decoders[0]
    if reference not in decoders:
        raise OptionError(f"--reference {args.reference}: not one of the decoders run ({', '.join(decoders)})",
                          "--reference")
    if args.texture_exponent != "prior" and not any(DECODERS[d].takes_texture_exponent for d in decoders):
        raise OptionError(f"--texture-exponent {args.texture_exponent}: --decoder {','.join(decoders)} runs no "
                          "decoder that takes a texture model (the evidence and classical decoders do)",
                          "--texture-exponent")
    changed = changed_classical_flags(args, WINDOW_KNOBS)
    if changed and not any(DECODERS[d].takes_config for d in decoders):
        raise OptionError(f"{', '.join(changed)} set(s) the classical decoder's knobs, and --decoder "
                          f"{','.join(decoders)} runs no decoder that takes them (a learned refinement decodes with "
                          "the knobs its manifest was trained with)", changed[0])
    scales = _scales(args)
    check_record_path(args.json, args.overwrite)
    bench = Benchmark(tiles=args.tiles, tile_px=args.tile_px, seed=args.seed, threads=args.threads,
                      scene_scale=scales[0], texture_exponent=args.texture_exponent)
    _check_memory(args, replace(bench, scene_scale=max(scales)))
    conditions = [c.strip() for c in args.conditions.split(",")] if args.conditions else None
    config = classical_config(args, WINDOW_KNOBS)
    rows = []
    with scheduler_address(args.scheduler, announce=not args.jsonl) as scheduler:  # benchmark tiles render there
        for scale in scales:
            rows += run_benchmark(args.model, replace(bench, scheduler=scheduler, scene_scale=scale), conditions,
                                  args.fisheye_model, progress=bars_shown(args.jsonl), decoders=decoders,
                                  classical_config=config, cameras=args.cameras)
    tables = [eval_table(rows, bench), strata_table(rows, bench)]
    pairs = paired_differences(rows, reference)
    if pairs:
        tables.append(paired_table(pairs, bench))
    if args.json:
        write_record(args.json, tables, overwrite=args.overwrite)
    if args.jsonl:
        for row in rows:
            print(json.dumps(row))
        return 0
    print("\n\n".join(_markdown(t) for t in tables))
    return 0


def scale_name(scale: float) -> str:
    """How a table names a scene scale: ×4 (paper), ×1 (stress test), ×16 (large surfaces), ×2.5."""
    from bmi_sdk.nn.evaluate import SCENE_SCALES

    return f"×{scale:g}" + (f" ({SCENE_SCALES[scale]})" if scale in SCENE_SCALES else "")


def _cell(value, digits: int = 3):
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return None
    return round(value, digits) if isinstance(value, float) else value


def eval_table(rows: list[dict], bench) -> dict:
    """The headline table of ``run_benchmark``'s rows: one row per scene scale, condition, decoder and region."""
    columns = ["scale", "condition", "decoder", "region", *KEYS, *SIGMA_KEYS]
    return {"title": "Synthetic benchmark",
            "columns": columns,
            "rows": [[scale_name(r["scene_scale"]), r["condition"], r["decoder"], r["region"],
                      *(_cell(r.get(k)) for k in (*KEYS, *SIGMA_KEYS))] for r in rows],
            "notes": f"{bench.tiles} tiles of {bench.tile_px}² px per field region (centre 0–20°, edge 50–60°), seed "
                     f"{bench.seed}; metrics per tile averaged over a region's tiles (built_camera_sampled: over its "
                     "cameras' tiles too); absrel_se: the standard error of that mean over the tiles (their spread "
                     "/ √n), the benchmark's own sampling uncertainty. confident_coverage: share of scored pixels "
                     "with σ/depth ≤ 0.1, confident_absrel their AbsRel; sigma_z_std: std of error/σ (1: an honest σ); "
                     "sigma_z_within_1: share of pixels with |error/σ| ≤ 1 (0.683: an honest σ; near 1: too wide)."}


def strata_table(rows: list[dict], bench) -> dict:
    """The breakdown table: each row's pixels by true range band, by distance to a depth edge and by noiseless signal
    at the sensor (``nn.eval_strata``), pooled over a region's tiles."""
    from bmi_sdk.nn.eval_strata import EDGE_LOG_STEP

    columns = ["scale", "condition", "decoder", "region", "stratum", *STRATUM_KEYS]
    out = []
    for r in rows:
        for stratum, metrics in (*r["by_range"].items(), *r["by_edge"].items(), *r["by_signal"].items()):
            out.append([scale_name(r["scene_scale"]), r["condition"], r["decoder"], r["region"], stratum,
                        *(_cell(metrics[k]) for k in STRATUM_KEYS)])
    return {"title": "Synthetic benchmark by range, by distance to a depth edge and by signal",
            "columns": columns, "rows": out,
            "notes": f"Pixels pooled over a region's tiles; range bands of the true range; a depth edge is a pixel whose "
                     f"true log range differs from a 4-neighbour's by more than {EDGE_LOG_STEP:g}; signal: the pixel's "
                     "noiseless mean over colours at the sensor (relative illumination applied), a fraction of white; "
                     "pixel_share and error_share: the stratum's share of the scored pixels and of their summed "
                     "|error|/range."}


def paired_table(pairs: list[dict], bench) -> dict:
    """The paired comparison (``nn.eval_paired.paired_differences``): each decoder against the reference decoder on
    the same tiles."""
    columns = ["scale", "condition", "region", "decoder", "reference", *PAIRED_KEYS]
    return {"title": f"Paired per-tile AbsRel difference from {pairs[0]['reference']}",
            "columns": columns,
            "rows": [[scale_name(p["scene_scale"]), p["condition"], p["region"], p["decoder"], p["reference"],
                      *(_cell(p[k], 4) for k in PAIRED_KEYS)] for p in pairs],
            "notes": f"Seed {bench.seed}: absrel_diff is the mean over the tiles of the decoder's AbsRel less the "
                     "reference's on the same tile and noise draw, absrel_diff_se its standard error over the tiles "
                     "(negative: the decoder reads better); better_share the share of tiles it reads better. The "
                     "tile-to-tile spread both decoders share cancels, so a difference beyond 2 absrel_diff_se is "
                     "resolved where the rows' own absrel_se would not resolve it."}


def _markdown(table: dict) -> str:
    def text(v) -> str:
        return "–" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = [f"| {' | '.join(table['columns'])} |", "|" + "---|" * len(table["columns"])]
    lines += [f"| {' | '.join(text(v) for v in row)} |" for row in table["rows"]]
    return "\n".join(lines)
