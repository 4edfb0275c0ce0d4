"""`bmi train`: train a network preset on cached forward-simulator pairs, then export ONNX + manifest."""

from __future__ import annotations

import json
from pathlib import Path

from ..option_values import SEED, OptionError, number, whole
from ._logging import bars_shown

LOCK_NAME = ".bmi-train.lock"
"""The lock one run holds in its --out from before its pairs render until its model is exported
(``io_atomic.lock_folder``): a second run into the same folder is refused, naming the first's process."""

PAIR_BYTES_PER_CROP_PX = 21
"""Disk space of one cached training pair per pixel of its crop: optical and RGB in float16 and range in float32
over the crop and its render margin (a shard of 4 pairs at --crop 128 holds 1.33 MB)."""


def register(subparsers) -> None:
    from bmi_sdk.scaleout import add_scheduler_argument

    p = subparsers.add_parser(
        "train", help="train the dual-head network (resumable) and export it to ONNX with a manifest",
        description="Render (and cache) training pairs through the forward simulator, train a preset with the "
                    "paper's losses, and export DIR/model.onnx + manifest. Re-running the same command resumes.")
    p.add_argument("--preset", default="tiny",
                   help="tiny | small | paper, optionally with -no_field or -single_scale (ablations)")
    p.add_argument("--steps", type=whole(1), default=6000, help="total optimiser steps of the run")
    p.add_argument("--out", required=True, help="run folder: checkpoint, logs, model.onnx")
    p.add_argument("--lens", default="bmi_monocentric", choices=["bmi_monocentric", "fisheye"])
    p.add_argument("--samples", type=whole(1), default=768, help="rendered pairs in the cache")
    p.add_argument("--crop", type=whole(4, unit="px", multiple_of=4), default=128,
                   help="training crop size in pixels (multiple of 4)")
    p.add_argument("--batch", type=whole(1), default=8)
    p.add_argument("--lr", type=number(0, 1, lo_open=True), default=5e-4,
                   help="initial learning rate (cosine decay to 1e-6)")
    p.add_argument("--decoder", default="cnn", choices=["cnn", "learned"],
                   help="cnn: the end-to-end network; learned: the refinement of the classical decoder "
                        "(its channels in, a depth σ out; docs/decoder.md)")
    p.add_argument("--init-from", default=None,
                   help="ONNX model whose weights start the run (default for --decoder learned: the shipped "
                        "default.onnx; its new input channels and σ output start at zero)")
    p.add_argument("--warmup-steps", type=whole(0), default=None,
                   help="linear learning-rate warm-up (default 0; 200 with --decoder learned)")
    p.add_argument("--sigma-head-only", action="store_true",
                   help="--decoder learned: train only the σ head of the --init-from refinement, on this run's pairs "
                        "(a --seed whose pairs its trunk never saw): its depth and AiF stay the source model's")
    p.add_argument("--refine-sigma", type=number(0, 1, lo_open=True, hi_open=True), nargs=2, default=(0.003, 0.012),
                   metavar=("MIN", "MAX"),
                   help="--decoder learned: noise σ range of the decoded training frames (log-uniform)")
    p.add_argument("--camera-errors", type=number(0, 1), default=0.0, metavar="FRACTION",
                   help="each pair's camera draws hardware errors within FRACTION of the paper's ranges (shift 0.5 px, "
                        "scale 5 %%, decenter 10 um, tilt 1', stray light 3 %%, sensor radius 2 %%) and is rendered, and "
                        "(--decoder learned) decoded, with its own exact kernels (default 0: the nominal camera)")
    p.add_argument("--scene-scale-max", type=number(1), default=1.0, metavar="SCALE",
                   help="procedural pairs: draw each scene at a scale log-uniform in [1, SCALE] and crop it, so its "
                        "objects are up to SCALE× larger against the crop, as a frame's are (default 1: the crop's "
                        "own scale, the `bmi eval` benchmark's)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--sigma", type=number(0, 1, lo_open=True, hi_open=True), default=None,
                   help="training noise σ, fraction of full scale (default 0.005, the paper's standard); "
                        "the lower end of the range with --sigma-max")
    p.add_argument("--sigma-max", type=number(0, 1, lo_open=True, hi_open=True), default=None,
                   help="draw each pair's σ log-uniform over [--sigma, --sigma-max] (default: every pair at --sigma)")
    p.add_argument("--cache", default=None, help="render cache folder (default .bmi_cache/train/<lens>-<samples>-<crop>-s<seed>)")
    p.add_argument("--render-workers", type=whole(1, 1024), default=2,
                   help="processes that build the PSF tensor, and render the cache without --scheduler")
    add_scheduler_argument(p)
    p.add_argument("--threads", type=whole(1, 1024), default=2, help="torch CPU threads")
    p.add_argument("--save-every", type=whole(1), default=250)
    p.add_argument("--no-export", action="store_true", help="skip the ONNX export at the end")
    p.set_defaults(handler=_run)


def _run(args) -> int:
    import time

    import torch

    from bmi_sdk.io_atomic import locked_folder
    from bmi_sdk.nn.data import STANDARD_SIGMA, CacheSpec, build_cache
    from bmi_sdk.nn.export import export_with_manifest
    from bmi_sdk.nn.model import preset_config
    from bmi_sdk.nn.train import TrainConfig, check_sigma_head_source, load_weights, train

    try:
        preset_config(args.preset)
    except ValueError as e:
        raise OptionError(f"--preset {args.preset}: {e}", "--preset") from None
    _check_memory(args)
    torch.set_num_threads(args.threads)
    spec = CacheSpec(lens=args.lens, samples=args.samples, crop_px=args.crop, seed=args.seed,
                     camera_errors=args.camera_errors, scene_scale_max=args.scene_scale_max)
    sigma = STANDARD_SIGMA if args.sigma is None else args.sigma
    refine, init_from = None, args.init_from
    if args.decoder == "learned":
        from bmi_sdk.nn.refine_data import RefineSpec
        from bmi_sdk.runtime.model import DEFAULT_MODEL

        refine = RefineSpec(sigma_min=args.refine_sigma[0], sigma_max=args.refine_sigma[1], seed=args.seed)
        init_from = init_from or str(DEFAULT_MODEL)
    if args.sigma_head_only and (args.decoder != "learned" or args.init_from is None):  # not the default model
        raise ValueError("--sigma-head-only retrains the σ head of a learned refinement: it needs "
                         "--decoder learned and --init-from MODEL.onnx")
    warmup = args.warmup_steps if args.warmup_steps is not None else (200 if args.decoder == "learned" else 0)
    config = TrainConfig(preset=args.preset, steps=args.steps, batch_size=args.batch, lr=args.lr, sigma=sigma,
                         sigma_max=args.sigma_max, seed=args.seed, cache=spec, refine=refine, init_from=init_from,
                         warmup_steps=warmup, sigma_head_only=args.sigma_head_only)
    check_sigma_head_source(config)  # before this command renders the pairs itself
    errors = f"-e{args.camera_errors:g}" if args.camera_errors else ""
    errors += f"-x{args.scene_scale_max:g}" if args.scene_scale_max > 1 else ""
    cache = Path(args.cache or f".bmi_cache/train/{args.lens}-{args.samples}-{args.crop}-s{args.seed}{errors}")
    _check_disk(cache, args.samples, args.crop)
    with locked_folder(Path(args.out) / LOCK_NAME):  # one run at a time trains into --out
        t0 = time.perf_counter()
        build_cache(cache, spec, workers=args.render_workers, scheduler=args.scheduler,
                    progress=bars_shown())
        t_render = time.perf_counter() - t0
        ckpt = train(config, args.out, cache, save_every=args.save_every, workers=args.render_workers,
                     progress=bars_shown())
        if args.no_export:
            return 0
        net, _ = load_weights(ckpt)
        log = json.loads((Path(args.out) / "train_log.json").read_text())
        training = {"command": "bmi train " + " ".join(_argv(args)), "config": config.to_dict(),
                    "train_seconds": sum(s["seconds"] for s in log["sessions"]),
                    "cache_seconds_this_call": round(t_render, 1),
                    "final_loss": log["curve"][-1] if log["curve"] else None}
        classical = refine.classical_config().to_dict() if refine is not None else None
        manifest = export_with_manifest(net, Path(args.out) / "model.onnx", preset=args.preset, lens=args.lens,
                                        training=training, classical_config=classical)
        print(f"exported {Path(args.out) / 'model.onnx'} ({manifest.name})")
        return 0


def _argv(args) -> list[str]:
    """The run's options as ``bmi train`` takes them: ``--out``, ``--threads`` (CPU float reductions depend on it:
    part of a bit-exact rerun) and every option whose value is not its default (``--cache`` included), in the
    parser's order; parsed again they give the same arguments."""
    import argparse
    import shlex

    parser = argparse.ArgumentParser(prog="bmi").add_subparsers()
    register(parser)
    defaults = vars(parser.choices["train"].parse_args(["--out", args.out]))
    out = []
    for name, default in defaults.items():
        value = getattr(args, name)
        if name == "handler" or (value == default and name not in ("out", "threads")):
            continue
        flag = f"--{name.replace('_', '-')}"
        if isinstance(value, bool):
            out.append(flag)  # a store_true switch that is on
        elif isinstance(value, (list, tuple)):
            if tuple(value) != tuple(default):
                out.append(" ".join([flag, *(shlex.quote(str(v)) for v in value)]))
        else:
            out.append(f"{flag} {shlex.quote(str(value))}")
    return out


def _check_memory(args) -> None:
    """Refuse, before any pair renders, a training step (``--batch`` × ``--crop``², ``nn.train.TRAIN_BYTES_PER_PX``
    of the preset, a known one) or a training scene (a crop drawn ``--scene-scale-max`` × larger) that would not
    fit in memory (``memory_budget``), naming the option that sized it."""
    from bmi_sdk.memory_budget import check_allocation
    from bmi_sdk.nn.evaluate import SCENE_DRAW_BYTES_PER_PX
    from bmi_sdk.nn.train import TRAIN_BYTES_PER_PX

    per_px = TRAIN_BYTES_PER_PX[args.preset.partition("-")[0]]
    check_allocation("--batch/--crop", f"{args.batch}/{args.crop}", per_px * args.batch * args.crop ** 2,
                     "a smaller batch or crop")
    check_allocation("--scene-scale-max", args.scene_scale_max,
                     SCENE_DRAW_BYTES_PER_PX * (args.crop * args.scene_scale_max) ** 2, "a smaller scale or crop")


def _check_disk(cache: Path, samples: int, crop_px: int) -> None:
    """Refuse, before any pair renders, a cache (``samples`` pairs of ``crop_px``², ``PAIR_BYTES_PER_CROP_PX``) that
    would not fit the free space of its disk, less what the folder already holds (a resumed run's shards)."""
    import shutil

    held = sum(f.stat().st_size for f in cache.glob("*.npz")) if cache.is_dir() else 0
    planned = samples * crop_px ** 2 * PAIR_BYTES_PER_CROP_PX - held
    existing = next(p for p in (cache, *cache.resolve().parents) if p.exists())
    free = shutil.disk_usage(existing).free
    if planned > free:
        raise OptionError(f"--samples {samples}: {samples} pairs of {crop_px}² px need about {planned / 1e9:.2f} GB; "
                          f"{existing} has {free / 1e9:.2f} GB free (lower --samples or --crop, or give --cache "
                          "on a larger disk)", "--samples")
