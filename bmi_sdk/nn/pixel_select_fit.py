"""Fit the evidence decoder's per-pixel choice among its windows' reads (``decode.pixel_select``) on ``bmi eval`` tiles.

    python -m bmi_sdk.nn.pixel_select_fit --seed 4242 --tiles 6 --manifest bmi_sdk/models/evidence.manifest.json

Every tile of the benchmark at each given seed (6 per field region, scene scales 1, 4 and 16, noise σ 0.005 and 0.02,
the design camera's tensor kernels, as ``bmi eval`` renders them) is decoded by the evidence network; every
``SUBSAMPLE_PX``-th pixel on each axis whose 2 × 2 windows disagree (``FIT_DISAGREEMENT``) gives its 32 candidates'
features
(``pixel_select.candidate_features``) and its true range. A perceptron (``HIDDEN`` units twice, ReLU; Adam, seeded) is
fitted to the least mean relative range error of the candidates' softmax mixture, each (seed, scale, σ, region) group
weighted equally. The weights go into the manifest's ``pixel_select`` (written atomically), with the fit's command
and its error before and after on the fitted pixels (``pixel_select_fit``). The seeds must be ones no reported number
uses (``REPORTED_SEEDS``, refused); ``bmi eval`` then measures the result on others. Bad arguments are refused before
any tile is decoded, and so is a second fit into a manifest another fit is writing (``LOCK_SUFFIX``).

Several seeds (``--seed 4242,31337,555,9001 --steps 3000``) fit a scorer that reads ``bmi eval``'s scenes better but
weakly textured walls worse, so the shipped scorer is the one-seed fit (docs/decoder.md, step 5b).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from bmi_sdk.decode.pixel_select import FEATURES, Grids, PixelSelect, candidate_features, disagreeing_blocks

SUBSAMPLE_PX = 3
HIDDEN = 16
STEPS = 800
"""Adam steps (``--steps``'s default): the shipped scorer's."""
MAX_STEPS = 100_000
BATCH = 8000
LEARNING_RATE = 3e-3
REPORTED_SEEDS = (20260, 777)
"""Seeds whose tiles docs/results.md reports: a fit on them would be scored on its own data."""
MAX_TILES = 64
MAX_SEEDS = 16
"""Seeds one fit collects at most: each adds its tiles' decodes and about 100 k pixels × 32 candidates × 14 features
of float32 (180 MB) to the fit's memory."""
LOCK_SUFFIX = ".lock"
"""The lock file beside ``--manifest`` (``io_atomic.lock_folder``) a fit holds from reading the manifest to writing it:
two fits into one manifest at once would each write their weights over the other's."""
FIT_DISAGREEMENT = float(np.log(1.1))
"""The pixels fitted on: those whose 2 × 2 windows' support reads span more than 10 % in 1/d."""
DISAGREEMENT = float(np.log(1.35))
"""The pixels the shipped scorer reads (``PixelSelect.disagreement``): a span beyond 35 %. On ``bmi eval``'s held-out
seed 777 (6 tiles per region, ×1, ×4, ×16, σ 0.005 and 0.02) that keeps 82 % of the gain of reading every fitted
pixel (AbsRel −0.0164 against −0.0199 per row) and scores 54 % as many of a full frame's pixels (docs/decoder.md)."""


def collect(seeds: tuple[int, ...], tiles: int, scales=(1.0, 4.0, 16.0), sigmas=(0.005, 0.02),
            manifest: str | None = None, progress: bool = True) -> dict[str, np.ndarray]:
    """{"features", "inv", "usable", "range_m", "group"} of the scored pixels of the benchmark's tiles at each of
    ``seeds`` (module doc); a group is one (seed, scale, σ, region)."""
    from bmi_sdk.decode.volume import pixel_log_colour
    from bmi_sdk.lenses import lens_geometry
    from bmi_sdk.model_io import raw_to_rgb
    from bmi_sdk.nn.evaluate import Benchmark, BenchmarkCamera, open_tiles, tile_frame, tile_raw
    from bmi_sdk.sensor import NoiseProfile

    out: dict[str, list] = {"features": [], "inv": [], "usable": [], "range_m": [], "group": []}
    # one decoder for every seed and scale: it reads only the benchmark's lens, tile size and threads
    opening = Benchmark(tiles=tiles)
    camera = BenchmarkCamera(opening.lens)
    models = {} if manifest is None else {"evidence": str(Path(manifest).with_suffix("").with_suffix(".onnx"))}
    decoder = open_tiles(("evidence",), camera, models, None, opening)[0].decoder
    network, stage = decoder.model, decoder.stage
    geometry = lens_geometry(opening.lens)
    s, size = stage.config.stride_px, opening.tile_px
    group = 0
    for seed, scale in itertools.product(seeds, scales):
        bench = dataclasses.replace(opening, seed=seed, scene_scale=scale)
        renders = bench.renders(camera.psf_tensor())
        for sigma in sigmas:
            for region in ("centre", "edge"):
                for k, item in enumerate(renders):
                    if item["region"] != region:
                        continue
                    raw = tile_raw(bench, item, k, sigma)
                    frame = tile_frame(raw, geometry, item["row0"], item["col0"], NoiseProfile.additive(sigma),
                                       decoder.camera.lens_name)
                    decoded = decoder.decode(frame)
                    parts = decoded.parts
                    rgb = raw_to_rgb(frame.data, frame.black_level_dn, frame.white_level_dn, frame.cfa)
                    grids = Grids.of_frame(parts["grid_inv_depth"], parts["grid_sigma_inv"] ** 2,
                                           parts["grid_inv_depth_own"], parts["grid_sigma_inv_own"] ** 2, rgb,
                                           pixel_log_colour(rgb), s, stage.config.window_px,
                                           network.support.dark_floor)
                    blocks = disagreeing_blocks(grids.inv_support, FIT_DISAGREEMENT, -(-size // s), -(-size // s))
                    rows, cols = np.mgrid[0:size:SUBSAMPLE_PX, 0:size:SUBSAMPLE_PX]
                    rows, cols = rows.ravel(), cols.ravel()
                    truth = item["range_m"][rows, cols]
                    keep = (blocks[rows // s, cols // s] & decoded.valid[rows, cols] & np.isfinite(truth)
                            & (truth > 0))
                    rows, cols = rows[keep], cols[keep]
                    feats, inv, _, usable = candidate_features(grids, rows, cols)
                    for name, value in (("features", feats), ("inv", inv), ("usable", usable),
                                        ("range_m", truth[keep]), ("group", np.full(rows.size, group))):
                        out[name].append(value)
                    if progress:
                        print(f"seed {seed} scale {scale:g} σ {sigma:g} {region} tile {k}: {rows.size} pixels",
                              file=sys.stderr)
                group += 1
    return {k: np.concatenate(v, axis=1 if k == "features" else 0) for k, v in out.items()}


def fit(data: dict[str, np.ndarray], hidden: int = HIDDEN, steps: int = STEPS, batch: int = BATCH,
        seed: int = 0) -> tuple[PixelSelect, dict]:
    """The fitted scorer and {"relative_error_guided_mean", "relative_error_fitted"}: the group-weighted mean relative
    range error of the candidates' uniform mixture (the scorer at zero) and of the fitted one, on these pixels."""
    import torch

    torch.manual_seed(seed)
    usable = data["usable"]
    feats = np.moveaxis(data["features"], 0, -1)  # (n, 32, 14)
    mean = feats[usable].mean(0)
    std = feats[usable].std(0) + 1e-6
    x = torch.tensor((feats - mean) / std)
    inv = torch.tensor(data["inv"])
    ok = torch.tensor(usable)
    truth = torch.tensor(data["range_m"], dtype=torch.float32)
    _, group_index, counts = np.unique(data["group"], return_inverse=True, return_counts=True)
    weight = torch.tensor((1.0 / counts[group_index]).astype(np.float32))
    n = len(FEATURES)
    net = torch.nn.Sequential(torch.nn.Linear(n, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden),
                              torch.nn.ReLU(), torch.nn.Linear(hidden, 1))

    def error(sel) -> torch.Tensor:
        score = net(x[sel])[..., 0].masked_fill(~ok[sel], -1e9)
        read = (torch.softmax(score, 1) * inv[sel]).sum(1)
        return (((1.0 / read - truth[sel]).abs() / truth[sel]) * weight[sel]).sum() / weight[sel].sum()

    def uniform_error() -> float:
        w = ok.float() / ok.float().sum(1, keepdim=True).clamp(min=1)
        read = (w * inv).sum(1)
        return float((((1.0 / read - truth).abs() / truth) * weight).sum() / weight.sum())

    optimiser = torch.optim.Adam(net.parameters(), lr=LEARNING_RATE)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        sel = torch.randint(0, len(x), (batch,), generator=generator)
        optimiser.zero_grad()
        loss = error(sel)
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        fitted = float(error(slice(None)))
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    layers = tuple((m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()) for m in linears)
    select = PixelSelect(mean.astype(np.float32), std.astype(np.float32), layers, DISAGREEMENT)
    return select, {"relative_error_uniform": uniform_error(), "relative_error_fitted": fitted}


def seed_list(text: str) -> tuple[int, ...]:
    """``--seed``'s type: 1 to ``MAX_SEEDS`` distinct integers, comma-separated."""
    try:
        seeds = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must be integers separated by commas, got {text!r}") from None
    if not 1 <= len(seeds) <= MAX_SEEDS or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"1 to {MAX_SEEDS} distinct seeds, got {text!r}")
    return seeds


def main(argv=None) -> int:
    from bmi_sdk.io_atomic import FolderBusyError, lock_folder, unlock_folder

    parser = argparse.ArgumentParser(prog="python -m bmi_sdk.nn.pixel_select_fit", description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=seed_list, default=(4242,),
                        help="benchmark seeds to fit on, comma-separated (default 4242)")
    parser.add_argument("--steps", type=int, default=STEPS, help=f"Adam steps, 1..{MAX_STEPS} (default {STEPS})")
    parser.add_argument("--tiles", type=int, default=6, help="tiles per field region (default 6)")
    parser.add_argument("--manifest", required=True, help="the evidence network's manifest to write the weights into")
    args = parser.parse_args(argv)
    reported = sorted(set(args.seed) & set(REPORTED_SEEDS))
    if min(args.seed) < 0 or reported:
        parser.error(f"--seed must be >= 0 and none of the reported seeds {list(REPORTED_SEEDS)}, got "
                     f"{','.join(map(str, args.seed))}")
    if not 1 <= args.tiles <= MAX_TILES:
        parser.error(f"--tiles must be 1..{MAX_TILES}, got {args.tiles}")
    if not 1 <= args.steps <= MAX_STEPS:
        parser.error(f"--steps must be 1..{MAX_STEPS}, got {args.steps}")
    manifest_path = Path(args.manifest)
    lock = manifest_path.with_name(manifest_path.name + LOCK_SUFFIX)
    try:
        lock_fd = lock_folder(lock)
    except FolderBusyError as exc:
        print(f"{parser.prog}: error: --manifest {manifest_path}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        parser.error(f"--manifest {manifest_path}: cannot read it as JSON ({exc})")
    try:
        return _fit_into(manifest_path, args, argv, parser)
    finally:
        unlock_folder(lock, lock_fd)


def _fit_into(manifest_path: Path, args, argv, parser) -> int:
    """``main``'s work under the manifest's lock: read it, collect, fit, write the weights back (atomically)."""
    from bmi_sdk.io_atomic import write_json

    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, ValueError) as exc:
        parser.error(f"--manifest {manifest_path}: cannot read it as JSON ({exc})")
    if not isinstance(manifest, dict) or manifest.get("decoder") != "evidence":
        parser.error(f"--manifest {manifest_path} is not an evidence network's manifest")
    data = collect(args.seed, args.tiles, manifest=str(manifest_path))
    select, errors = fit(data, steps=args.steps)
    manifest["pixel_select"] = select.to_dict()
    command = "python -m bmi_sdk.nn.pixel_select_fit " + " ".join(argv or sys.argv[1:])
    manifest["pixel_select_fit"] = {"command": command,
                                    "seeds": list(args.seed), "tiles_per_region": args.tiles, "steps": args.steps,
                                    "pixels": int(len(data["range_m"])), **errors}
    write_json(manifest_path, manifest)
    print(json.dumps(manifest["pixel_select_fit"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
