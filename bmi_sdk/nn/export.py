"""Export a trained network to one ONNX file (dynamic N, H, W), check it against torch, write its manifest.

The graph is ``InferenceWrapper``: input ``coded`` N×6×H×W → ``aif`` N×3×H×W and
``depth_m`` N×1×H×W (model_io). The legacy TorchScript exporter is used
(``dynamo=False``): it exports in ~0.2 s, keeps every declared axis dynamic
and matches torch to ~1e-7 on this architecture (PACKAGES.md); opset 17.
Weights are embedded (one file, no external data). After export the file is
run with onnxruntime at two sizes that differ from the export size and
compared with torch; a difference above ``TOLERANCE`` refuses the export.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from bmi_sdk.io_atomic import atomic_path
from bmi_sdk.model_io import INPUT_CHANNELS, INPUT_NAME, OUTPUT_NAMES, SIGMA_OUTPUT_NAME
from bmi_sdk.nn.model import DualHeadMimoUNet, InferenceWrapper

OPSET = 17
TOLERANCE = 1e-4
CHECK_SHAPES = ((1, 64, 96), (2, 128, 72))


def input_channels(net: DualHeadMimoUNet) -> int:
    """Channels of the exported input: the contract's 6, plus a refinement's classical channels."""
    return INPUT_CHANNELS + net.config.extra_channels


def output_names(net: DualHeadMimoUNet) -> tuple[str, ...]:
    return (*OUTPUT_NAMES, SIGMA_OUTPUT_NAME) if net.config.sigma_head else OUTPUT_NAMES


def receptive_field_px(net: DualHeadMimoUNet, probe_px: int = 384) -> int:
    """Full receptive field (input pixels) of the centre output pixel, from the support of its input gradient.

    The gradient of both outputs at the centre pixel with respect to a random
    input is non-zero exactly on the pixels that can influence it; the side of
    the bounding square of that support is the receptive field (capped at the
    probe size; the runtime derives its tile overlap from this number).
    """
    net = net.eval()
    x = torch.rand(1, input_channels(net), probe_px, probe_px, requires_grad=True)
    aif, *depth = InferenceWrapper(net)(x)
    c = probe_px // 2
    (aif[0, :, c, c].sum() + sum(d[0, 0, c, c] for d in depth)).backward()
    support = x.grad.abs().sum(dim=(0, 1)) > 0
    rows = torch.nonzero(support.any(dim=1)).flatten()
    cols = torch.nonzero(support.any(dim=0)).flatten()
    return int(max(rows.max() - rows.min(), cols.max() - cols.min()) + 1)


def export_onnx(net: DualHeadMimoUNet, path: str | Path, example_px: int = 128) -> float:
    """Write ``path`` (atomically) and return the max |onnxruntime − torch| over the check shapes."""
    import onnxruntime as ort

    wrapper = InferenceWrapper(net.eval().cpu())
    channels, names = input_channels(net), output_names(net)
    example = torch.rand(1, channels, example_px, example_px)
    dynamic = {0: "batch", 2: "height", 3: "width"}
    path = Path(path)
    with atomic_path(path, suffix=".onnx") as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
            torch.onnx.export(wrapper, (example,), str(tmp), input_names=[INPUT_NAME], output_names=list(names),
                              dynamic_axes={INPUT_NAME: dynamic, **{n: dynamic for n in names}},
                              opset_version=OPSET, dynamo=False)
        session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        worst = 0.0
        gen = torch.Generator().manual_seed(0)
        for n, h, w in CHECK_SHAPES:
            x = torch.rand(n, channels, h, w, generator=gen)
            with torch.no_grad():
                ref = [t.numpy() for t in wrapper(x)]
            got = session.run(list(names), {INPUT_NAME: x.numpy()})
            worst = max(worst, *(float(np.max(np.abs(a - b))) for a, b in zip(got, ref)))
        if not worst <= TOLERANCE:
            raise RuntimeError(f"ONNX export differs from torch by {worst:.3g} > {TOLERANCE}")
    return worst


def export_with_manifest(net: DualHeadMimoUNet, path: str | Path, *, preset: str, lens: str,
                         training: dict, metrics: dict | None = None, classical_config: dict | None = None) -> Path:
    """Export, then write the SHA-256 manifest (bmi_sdk.model_manifest) beside the file; returns the manifest.

    A refinement (``net.config.extra_channels`` > 0) needs ``classical_config``, the decoder knobs its
    channels were made with; the manifest then says ``decoder: "learned"``."""
    from bmi_sdk.model_manifest import write_manifest
    from bmi_sdk.lenses import lens_tensor

    max_diff = export_onnx(net, path)
    tensor = lens_tensor(lens)
    extra = {}
    if net.config.extra_channels:
        if classical_config is None:
            raise ValueError("a refinement model needs the classical_config its channels were made with")
        extra = {"decoder": "learned", "classical_config": classical_config}
    return write_manifest(path, preset=preset, receptive_field_px=receptive_field_px(net), lens=lens,
                          psf_tensor_key=tensor.spec.cache_key(tensor.lens), calibration_id=None,
                          training=training, metrics=metrics or {}, onnx_max_abs_diff_vs_torch=max_diff,
                          onnx_opset=OPSET, input_channels=input_channels(net), output_names=output_names(net),
                          **extra)


def ship(src: str | Path, dst: str | Path, metrics: dict) -> Path:
    """Copy a verified run model to ``dst`` (e.g. bmi_sdk/models/default.onnx) with its manifest plus ``metrics``."""
    import shutil

    from bmi_sdk.model_manifest import verify_model, write_manifest

    manifest = verify_model(src)
    keep = {k: v for k, v in manifest.items() if k not in ("schema", "sha256", "file", "metrics")}
    with atomic_path(dst, suffix=".onnx") as tmp:
        shutil.copyfile(src, tmp)
    return write_manifest(dst, **keep, metrics=metrics)
