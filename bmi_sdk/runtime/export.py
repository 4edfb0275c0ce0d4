"""Export a torch network that follows the model_io contract to ONNX + manifest, measuring its receptive field.

The runtime's tile overlap comes from the manifest's ``receptive_field_px``;
``measure_receptive_field`` measures it on the network itself (the extent of
the input gradient of one output pixel) instead of trusting a hand count.
Used by the tests and ``bmi bench infer`` to export networks before the
shipped model exists; issue 6's training export writes the same manifest.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..model_io import INPUT_CHANNELS, INPUT_NAME, OUTPUT_NAMES, SIGMA_OUTPUT_NAME
from ..model_manifest import write_manifest


def measure_receptive_field(net, size_px: int = 256, seed: int = 0, channels: int = INPUT_CHANNELS) -> int:
    """Full width (px) of the input region that influences the centre output pixel, all outputs together.

    A random input and random weights make every path of the graph carry a
    non-zero gradient; the measured width is exact for the architecture (for
    ReLU nets a dead path can only make it smaller, so 3 seeds are combined).
    ``size_px`` must exceed the receptive field (an error says so otherwise).
    """
    import torch

    extent = 0
    c = size_px // 2
    for s in range(3):
        g = torch.Generator().manual_seed(seed + s)
        x = torch.rand(1, channels, size_px, size_px, generator=g, requires_grad=True)
        aif, *depth = net(x)
        (aif[0, :, c, c].sum() + sum(d[0, 0, c, c] for d in depth)).backward()
        hit = np.argwhere(x.grad.abs().sum(dim=(0, 1)).numpy() > 0)
        if len(hit) == 0:
            continue
        extent = max(extent, int(np.abs(hit - c).max()))
    if extent >= c - 1:
        raise ValueError(f"receptive field reaches the {size_px}-px probe's edge; measure with a larger size_px")
    return 2 * extent + 1


def export_model(net, onnx_path: str | os.PathLike, *, preset: str, lens: str = "bmi_monocentric",
                 calibration_id: str | None = None, training: dict | None = None, metrics: dict | None = None,
                 probe_px: int = 256, extra_channels: int = 0, classical_config: dict | None = None,
                 **extra) -> Path:
    """Export ``net`` (``coded`` → ``aif``, ``depth_m``) with dynamic H, W and write its manifest; return the .onnx path.

    ``lens`` names a lens profile (``bmi_sdk.lenses``): ``psf_tensor_key`` is its
    nominal PSF tensor's cache key unless ``extra`` names another one (a
    calibrated tensor's), and ``largest_psf_px`` its kernel size. With ``extra_channels`` > 0 the network
    is a learned refinement (6 + extra_channels inputs → ``aif``, ``depth_m``, ``depth_sigma_m``) whose
    classical channels are made with ``classical_config`` (required then).
    """
    import torch

    from ..lenses import LENS_KERNEL_PX, lens_tensor

    onnx_path = Path(onnx_path)
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    net = net.eval()
    channels = INPUT_CHANNELS + extra_channels
    names = (*OUTPUT_NAMES, SIGMA_OUTPUT_NAME) if extra_channels else OUTPUT_NAMES
    if extra_channels:
        if classical_config is None:
            raise ValueError("a learned refinement needs the classical_config its channels are made with")
        extra.update(decoder="learned", classical_config=classical_config)
    rf = measure_receptive_field(net, probe_px, channels=channels)
    x = torch.zeros(1, channels, 64, 64)
    tmp = onnx_path.with_name(f".{onnx_path.name}.tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        torch.onnx.export(net, (x,), str(tmp), input_names=[INPUT_NAME], output_names=list(names),
                          dynamic_axes={INPUT_NAME: {2: "height", 3: "width"},
                                        **{n: {2: "height", 3: "width"} for n in names}},
                          opset_version=17, dynamo=False)
    os.replace(tmp, onnx_path)
    nominal = lens_tensor(lens)
    key = extra.pop("psf_tensor_key", None) or nominal.spec.cache_key(nominal.lens)
    write_manifest(onnx_path, preset=preset, receptive_field_px=rf, lens=lens, psf_tensor_key=key,
                   calibration_id=calibration_id, training=training, metrics=metrics,
                   largest_psf_px=LENS_KERNEL_PX[lens], input_channels=channels, output_names=names, **extra)
    return onnx_path
