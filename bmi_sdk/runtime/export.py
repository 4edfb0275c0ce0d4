"""The one ONNX exporter: a torch network on the model_io contract → a verified ``.onnx`` file + its manifest.

Every export goes through here: the test nets, ``bmi demo`` / ``bmi bench infer``'s untrained
stand-ins, and ``bmi train``'s trained network (``nn.export`` wraps it and passes its channels).
It

- measures the receptive field on the network itself (``measure_receptive_field``: the extent
  of the input gradient of the centre output pixel over 3 random inputs, refused when it reaches
  the probe's edge), because the runtime derives its tile overlap from the manifest's
  ``receptive_field_px`` and a hand count or a capped probe would make tiles seam;
- exports with the legacy TorchScript exporter (``dynamo=False``: ~0.2 s, every declared axis
  stays dynamic — batch, height, width), opset ``OPSET``, weights embedded, written atomically;
- runs the file with onnxruntime at ``CHECK_SHAPES`` (shapes the exporter never saw) against torch
  and refuses the export above ``TOLERANCE``, so a graph that tracing specialised to the example
  shape never ships;
- writes the manifest with the measured difference and opset, the lens profile's nominal PSF
  tensor key and its kernel size as ``largest_psf_px`` (provenance: the PSFs it was trained on; tiling
  needs only ``receptive_field_px``).

torch is imported inside the functions: ``import bmi_sdk.runtime`` stays free of it.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..io_atomic import atomic_path
from ..model_io import INPUT_CHANNELS, INPUT_NAME, OUTPUT_NAMES, SIGMA_OUTPUT_NAME
from ..model_manifest import write_manifest

OPSET = 17
TOLERANCE = 1e-4
"""Largest |onnxruntime − torch| an export may show at ``CHECK_SHAPES`` (measured ~1e-7 on the shipped nets)."""
CHECK_SHAPES = ((1, 64, 96), (2, 128, 72))
"""(batch, height, width) of the verification inputs: none is the export example's, so each dynamic axis is tried."""
EXAMPLE_PX = 128
"""Side of the 1-batch example input the exporter traces."""


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


def export_onnx(net, onnx_path: str | os.PathLike, *, channels: int = INPUT_CHANNELS,
                output_names: tuple[str, ...] = OUTPUT_NAMES) -> float:
    """Write ``net`` to ``onnx_path`` (atomically, dynamic batch/height/width) once onnxruntime agrees with torch.

    Returns the largest |onnxruntime − torch| over ``CHECK_SHAPES``; above ``TOLERANCE`` (or with another
    number of outputs than ``output_names``) it raises and leaves no file. No manifest: ``export_model``
    writes one.
    """
    import onnxruntime as ort
    import torch

    net = net.eval().cpu()
    names = list(output_names)
    gen = torch.Generator().manual_seed(0)
    example = torch.rand(1, channels, EXAMPLE_PX, EXAMPLE_PX, generator=gen)
    dynamic = {0: "batch", 2: "height", 3: "width"}
    with atomic_path(onnx_path, suffix=".onnx") as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice and tracer warnings
            torch.onnx.export(net, (example,), str(tmp), input_names=[INPUT_NAME], output_names=names,
                              dynamic_axes={INPUT_NAME: dynamic, **{n: dynamic for n in names}},
                              opset_version=OPSET, dynamo=False)
        session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        worst = 0.0
        for n, h, w in CHECK_SHAPES:
            x = torch.rand(n, channels, h, w, generator=gen)
            with torch.no_grad():
                ref = [t.numpy() for t in net(x)]
            if len(ref) != len(names):
                raise ValueError(f"the network returns {len(ref)} outputs, the export names {len(names)}: {names}")
            got = session.run(names, {INPUT_NAME: x.numpy()})
            worst = max(worst, *(float(np.max(np.abs(a - b))) if a.shape == b.shape else np.inf
                                 for a, b in zip(got, ref)))
        if not worst <= TOLERANCE:
            raise RuntimeError(f"the ONNX export of {Path(onnx_path).name} differs from torch by {worst:.3g} "
                               f"> {TOLERANCE} at {CHECK_SHAPES} (batch, height, width): not written")
    return worst


def export_model(net, onnx_path: str | os.PathLike, *, preset: str, lens: str = "bmi_monocentric",
                 calibration_id: str | None = None, training: dict | None = None, metrics: dict | None = None,
                 probe_px: int = 256, extra_channels: int = 0, classical_config: dict | None = None,
                 **extra) -> Path:
    """Export ``net`` (``coded`` → ``aif``, ``depth_m``) verified, and write its manifest; return the .onnx path.

    ``lens`` names a lens profile (``bmi_sdk.lenses``): ``psf_tensor_key`` is its
    nominal PSF tensor's cache key unless ``extra`` names another one (a
    calibrated tensor's), and ``largest_psf_px`` its kernel size. ``probe_px`` is the
    receptive-field probe's side (it must exceed the receptive field). With ``extra_channels`` > 0 the network
    is a learned refinement (6 + extra_channels inputs → ``aif``, ``depth_m``, ``depth_sigma_m``) whose
    classical channels are made with ``classical_config`` (required then).
    """
    from ..lenses import LENS_KERNEL_PX, lens_tensor

    onnx_path = Path(onnx_path)
    channels = INPUT_CHANNELS + extra_channels
    names = (*OUTPUT_NAMES, SIGMA_OUTPUT_NAME) if extra_channels else OUTPUT_NAMES
    if extra_channels:
        if classical_config is None:
            raise ValueError("a learned refinement needs the classical_config its channels are made with")
        extra.update(decoder="learned", classical_config=classical_config)
    nominal = lens_tensor(lens)  # an unknown lens is refused before anything is written
    key = extra.pop("psf_tensor_key", None) or nominal.spec.cache_key(nominal.lens)
    net = net.eval().cpu()
    rf = measure_receptive_field(net, probe_px, channels=channels)
    max_diff = export_onnx(net, onnx_path, channels=channels, output_names=names)
    write_manifest(onnx_path, preset=preset, receptive_field_px=rf, lens=lens, psf_tensor_key=key,
                   calibration_id=calibration_id, training=training, metrics=metrics,
                   largest_psf_px=LENS_KERNEL_PX[lens], input_channels=channels, output_names=names,
                   onnx_max_abs_diff_vs_torch=max_diff, onnx_opset=OPSET, **extra)
    return onnx_path
