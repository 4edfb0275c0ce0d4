"""`bmi fit-fusion`: fit a learned refinement's fusion weights (``nn.fusion_fit``) and write them into its manifest."""

from __future__ import annotations

import logging

from ..option_values import SEED, OptionError, whole

READ_BYTES_PER_PX = 6 * 8
"""What the fit holds per valid pixel of every tile it decodes (``nn.fusion_fit.collect_reads``): six float64
columns (both reads, both 1σ, the truth and the depth variation)."""


def register(subparsers) -> None:
    from bmi_sdk.nn.fusion_fit import FIT_PIXELS_PER_SET, FIT_SCALES, FIT_SEED, FIT_SIGMAS

    p = subparsers.add_parser(
        "fit-fusion", help="fit how a learned refinement fuses its network's depth with its classical stage's",
        description="Decode benchmark tiles of a seed no reported number uses, at several scene scales and noise "
                    "levels, with the learned refinement's two stages; fit the fusion's weights (decode.fusion: "
                    "both relative σs, the two reads' disagreement and how much the classical depth varies around "
                    "each pixel, at each noise level) to the least "
                    "mean |log depth error|; print the error of each read, the inverse-variance fusion and the "
                    "fitted one per set of tiles; and write the weights into the model's manifest, which bmi infer "
                    "and bmi eval read. Re-running it gives the same weights.")
    p.add_argument("--model", default=None, help="learned refinement ONNX model (default: the shipped learned.onnx)")
    p.add_argument("--seed", type=SEED, default=FIT_SEED,
                   help=f"benchmark seed of the fit's tiles (default {FIT_SEED}; 20260 is the benchmark's own)")
    p.add_argument("--scales", default=",".join(f"{s:g}" for s in FIT_SCALES),
                   help="comma list of scene scales, each weighing the same (default: %(default)s)")
    p.add_argument("--tiles", type=whole(1), default=12, help="tiles per field region, scale and noise σ (default 12)")
    p.add_argument("--sigmas", default=",".join(f"{s:g}" for s in FIT_SIGMAS),
                   help="comma list of noise σs (fraction of full scale) the tiles are taken at, each with every "
                        "scale; the weights are fitted at each and interpolated in log σ between them (default: "
                        "%(default)s)")
    p.add_argument("--pixels", type=whole(100), default=FIT_PIXELS_PER_SET,
                   help="pixels per set of tiles the fit reads, drawn from the tiles' valid ones (default %(default)s)")
    p.add_argument("--threads", type=whole(1, 1024), default=2)
    p.add_argument("--dry-run", action="store_true", help="print the fit; leave the manifest as it is")
    p.set_defaults(handler=_run)


def _run(args) -> int:
    import numpy as np

    from bmi_sdk.decode.fusion import INVERSE_VARIANCE
    from bmi_sdk.io_atomic import write_json
    from bmi_sdk.model_manifest import manifest_path, model_decoder, verify_model
    from bmi_sdk.nn.evaluate import Benchmark
    from bmi_sdk.nn.fusion_fit import (
        abs_log_error,
        collect_reads,
        fit_fusion_weights,
        fit_objective,
        mean_abs_log_error,
    )
    from bmi_sdk.runtime.model import LEARNED_MODEL

    model = args.model or str(LEARNED_MODEL)
    manifest = verify_model(model)
    if model_decoder(manifest) != "learned":
        raise ValueError(f"--model {model} is not a learned refinement: it has no classical read to fuse with")
    scales = _numbers(args.scales, "--scales", "numbers ≥ 1", lambda s: s >= 1.0)
    sigmas = _numbers(args.sigmas, "--sigmas", "noise σs in (0, 1)", lambda s: 0 < s < 1)
    _check_memory(args, scales, sigmas)
    if args.seed == Benchmark.seed:
        logging.getLogger("bmi.fit-fusion").warning(
            "seed %d is the benchmark's own: bmi eval's numbers would no longer be held out", args.seed)
    sets = [collect_reads(model, scale, seed=args.seed, tiles=args.tiles, sigma=sigma, threads=args.threads)
            for sigma in sigmas for scale in scales]
    weights = fit_fusion_weights(sets, pixels_per_set=args.pixels)
    objective = {name: fit_objective(sets, w, args.pixels) for name, w in
                 (("inverse_variance", INVERSE_VARIANCE), ("fitted", weights))}
    rows, errors = [], {}
    for s in sets:
        classical, network = abs_log_error(s.classical_m, s.truth_m), abs_log_error(s.network_m, s.truth_m)
        errors[s.name] = {"pixels": len(s), "classical": classical, "network": network,
                          "inverse_variance": mean_abs_log_error(s, INVERSE_VARIANCE),
                          "fitted": mean_abs_log_error(s, weights)}
        e = errors[s.name]
        rows.append(f"| {s.name} | {len(s)} | {classical:.4f} | {network:.4f} | {e['inverse_variance']:.4f} | "
                    f"{e['fitted']:.4f} |")
    print(f"Fusion fit for {model} (seed {args.seed}, {args.tiles} tiles per region, scale and noise σ): "
          "mean |log(d / d_true)| over each set's valid pixels")
    print()
    print("| tiles | pixels | classical | network | inverse-variance fusion | fitted fusion |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    print()
    print(f"objective (mean of the sets' mean |log error| on the fit's pixel samples): inverse-variance "
          f"{objective['inverse_variance']:.4f}, fitted {objective['fitted']:.4f}")
    print("weights: " + ", ".join(f"{k} {np.round(v, 4)}" for k, v in weights.to_dict().items()))
    if args.dry_run:
        return 0
    command = (f"bmi fit-fusion --seed {args.seed} --scales {','.join(f'{s:g}' for s in scales)} --tiles {args.tiles} "
               f"--sigmas {','.join(f'{s:g}' for s in sigmas)} --pixels {args.pixels} --threads {args.threads}")
    manifest["fusion"] = {"weights": weights.to_dict(),
                          "fit": {"command": command, "seed": args.seed, "scales": scales, "tiles": args.tiles,
                                  "sigmas": sigmas, "pixels_per_set": args.pixels, "mean_abs_log_error": errors,
                                  "objective": objective}}
    write_json(manifest_path(model), manifest)
    print(f"wrote the weights into {manifest_path(model)}")
    return 0


def _numbers(text: str, option: str, what: str, ok) -> list[float]:
    """The numbers of a comma list option, each passing ``ok``; a one-line error naming ``option`` otherwise."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or not all(ok(v) for v in values):
        raise OptionError(f"{option} must be a comma list of {what}, got {text!r}", option)
    return values


def _check_memory(args, scales: list[float], sigmas: list[float]) -> None:
    """Refuse, before any tile renders, a fit whose reads (every set's tiles, ``READ_BYTES_PER_PX``) with one set's
    renders and its largest scene would not fit in memory (``memory_budget``), naming ``--tiles``."""
    from bmi_sdk.memory_budget import check_allocation
    from bmi_sdk.nn.evaluate import Benchmark

    largest = Benchmark(tiles=args.tiles, seed=args.seed, scene_scale=max(scales))
    reads = len(scales) * len(sigmas) * 2 * args.tiles * largest.tile_px ** 2 * READ_BYTES_PER_PX
    check_allocation("--tiles", args.tiles, reads + largest.renders_bytes() + largest.scene_bytes(),
                     "fewer tiles, scales or σs")
