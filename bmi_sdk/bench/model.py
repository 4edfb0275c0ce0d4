"""`bmi bench model`: each preset's accuracy on the synthetic benchmark against its run time; fp32 against int8.

Per preset: parameters, forward GFLOPs at 480×640 (1 multiply-add = 2 FLOPs),
onnxruntime CPU time per megapixel (2 intra-op threads, 512² tiles, median of
``repeats`` after a warm-up), torch training time per step (batch 8, 128²
crops, forward + backward + Adam, 2 threads). For every trained model given
with ``--models NAME=PATH`` (a verified ONNX + manifest): benchmark accuracy at
σ = 0.005 (``bmi eval``'s ``standard`` condition) of the fp32 model and of its
static int8 QDQ copy (``bmi_sdk.runtime.quantize_int8``, calibrated on
training-distribution tiles), each with its time per megapixel.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from ..option_values import whole
from . import add_json_argument, check_record_path, emit, markdown_table

TILE_PX = 512
PRESET_NAMES = ("tiny", "small", "paper")


def _onnx_ms_per_mp(path: Path, threads: int = 2, repeats: int = 3) -> float:
    """Median time of one 512² tile through onnxruntime with the runtime's session options (a speed probe:
    the file need not have a manifest)."""
    import onnxruntime as ort

    from bmi_sdk.runtime.model import session_options

    session = ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])
    feed = {"coded": np.random.default_rng(0).random((1, 6, TILE_PX, TILE_PX), dtype=np.float32)}
    session.run(None, feed)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        session.run(None, feed)
        times.append(time.perf_counter() - t)
    return statistics.median(times) / (TILE_PX * TILE_PX / 1e6) * 1e3


def _train_ms_per_step(preset: str, steps: int = 3) -> float:
    import torch

    from bmi_sdk.nn.losses import total_loss
    from bmi_sdk.nn.model import DualHeadMimoUNet, preset_config

    torch.set_num_threads(2)
    torch.manual_seed(0)
    net = DualHeadMimoUNet(preset_config(preset))
    opt = torch.optim.Adam(net.parameters())
    x, aif, depth, mask = torch.rand(8, 6, 128, 128), torch.rand(8, 3, 128, 128), 1 + torch.rand(8, 1, 128, 128), \
        torch.ones(8, 1, 128, 128)
    times = []
    for _ in range(steps + 1):
        t = time.perf_counter()
        preds, d = net(x)
        loss, _ = total_loss(preds, d, aif, depth, mask)
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t)
    return statistics.median(times[1:]) * 1e3


def _speed_rows(presets) -> list[list]:
    import torch

    from bmi_sdk.nn.export import export_onnx
    from bmi_sdk.nn.model import DualHeadMimoUNet, gflops, parameter_count, preset_config

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in presets:
            torch.manual_seed(0)
            net = DualHeadMimoUNet(preset_config(name))
            path = Path(tmp) / f"{name}.onnx"
            export_onnx(net, path)
            rows.append([name, f"{parameter_count(net) / 1e6:.3f}", f"{gflops(preset_config(name)):.1f}",
                         f"{_onnx_ms_per_mp(path) / 1e3:.2f}", f"{_train_ms_per_step(name):.0f}"])
    return rows


def _calibration_tiles(n: int = 8) -> list[np.ndarray]:
    """Network inputs like the training data: seeded renders through the sensor chain (nominal lens)."""
    from bmi_sdk.model_io import network_input
    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_sensor
    from bmi_sdk.nn.evaluate import Benchmark

    bench = Benchmark(tiles=n // 2, tile_px=128, seed=777)
    out = []
    from bmi_sdk.lenses import lens_geometry, lens_tensor

    geometry = lens_geometry(bench.lens)
    m, t = bench.margin_px, bench.tile_px
    for k, item in enumerate(bench.renders(lens_tensor(bench.lens))):
        seen = simulate_sensor(item["optical_full"][m:m + t, m:m + t], STANDARD_SIGMA, np.random.default_rng(k),
                               item["row0"], item["col0"])
        out.append(network_input(seen, geometry, item["row0"], item["col0"]))
    return out


def _manifest_like(onnx_path: Path, source: Path) -> None:
    """Write ``onnx_path``'s manifest from ``source``'s (same network, other bytes: e.g. its int8 version)."""
    from bmi_sdk.model_manifest import read_manifest, write_manifest

    keep = {k: v for k, v in read_manifest(source).items() if k not in ("schema", "sha256", "file")}
    write_manifest(onnx_path, **keep)


def _accuracy_rows(models: dict[str, Path], tiles: int) -> list[list]:
    from bmi_sdk.nn.evaluate import Benchmark, run_benchmark
    from bmi_sdk.runtime.quantize import quantize_int8

    rows = []
    bench = Benchmark(tiles=tiles)
    calib = _calibration_tiles()
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in models.items():
            int8 = quantize_int8(path, Path(tmp) / f"{name}-int8.onnx", calib)
            _manifest_like(int8, path)  # the benchmark runs verified models only
            for kind, p in (("fp32", Path(path)), ("int8", int8)):
                res = {r["region"]: r for r in run_benchmark(p, bench, ["standard"], progress=False,
                                                                   decoders=("cnn",))}
                c, e = res["centre"], res["edge"]
                rows.append([name, kind, f"{c['absrel']:.3f}", f"{c['rmse_m']:.3f}", f"{c['delta1']:.3f}",
                             f"{c['psnr_db']:.2f}", f"{e['rmse_m']:.3f}", f"{e['psnr_db']:.2f}",
                             f"{_onnx_ms_per_mp(p) / 1e3:.2f}"])
    return rows


def run(presets=PRESET_NAMES, models: dict[str, Path] | None = None, tiles: int = 12) -> str:
    out = ["### Size and speed per preset (untrained weights; speed does not depend on them)\n\n" + markdown_table(
        ["preset", "params (M)", "GFLOPs @480×640", "onnxruntime s/MP (2 threads)", "train ms/step (b8, 128²)"],
        _speed_rows(presets))]
    if models:
        out.append(f"### Accuracy at σ = 0.005 ({tiles} tiles per region) against time, fp32 and int8\n\n" +
                   markdown_table(["model", "weights", "centre AbsRel", "centre RMSE (m)", "centre δ1",
                                   "centre PSNR (dB)", "edge RMSE (m)", "edge PSNR (dB)", "s/MP"],
                                  _accuracy_rows(models, tiles)))
    return "\n\n".join(out)


def register(subparsers) -> None:
    p = subparsers.add_parser("model", help="network presets: accuracy against inference/training time, fp32 vs int8")
    p.add_argument("--presets", default=",".join(PRESET_NAMES))
    p.add_argument("--models", default="", help="comma list NAME=PATH of trained ONNX models to score")
    p.add_argument("--tiles", type=whole(1, 1000), default=12, help="benchmark tiles per field region")
    add_json_argument(p)
    p.set_defaults(handler=_handler)


def _handler(args) -> int:
    check_record_path(args.json, args.overwrite)
    models = dict(item.split("=", 1) for item in args.models.split(",") if item)
    text = run([p.strip() for p in args.presets.split(",") if p.strip()], {k: Path(v) for k, v in models.items()},
               args.tiles)
    emit(text, args.json, args.overwrite)
    return 0
