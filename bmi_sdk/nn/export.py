"""Export a trained ``DualHeadMimoUNet``: its exported graph and channels, and its training metadata.

The exporting itself (receptive-field probe, ONNX with dynamic N, H, W, atomic write, the
onnxruntime-against-torch check, the manifest with ``largest_psf_px``) is
``bmi_sdk.runtime.export``, the one exporter: the runtime may not import this training package,
so the home is there. What is left here is what only the trained network knows: the graph is
``InferenceWrapper`` (input ``coded`` N×(6 + extra)×H×W → full-resolution ``aif``, ``depth_m``
[, ``depth_sigma_m``]) and its channels and outputs come from ``net.config``.
"""

from __future__ import annotations

from pathlib import Path

from bmi_sdk.model_io import INPUT_CHANNELS, OUTPUT_NAMES, SIGMA_OUTPUT_NAME
from bmi_sdk.model_manifest import manifest_path
from bmi_sdk.nn.model import DualHeadMimoUNet, InferenceWrapper
from bmi_sdk.runtime import export as runtime_export

RF_PROBE_PX = 512
"""Side of the receptive-field probe: above every preset's receptive field (tiny 89, small 141, paper 429 px)."""


def input_channels(net: DualHeadMimoUNet) -> int:
    """Channels of the exported input: the contract's 6, plus a refinement's classical channels."""
    return INPUT_CHANNELS + net.config.extra_channels


def output_names(net: DualHeadMimoUNet) -> tuple[str, ...]:
    return (*OUTPUT_NAMES, SIGMA_OUTPUT_NAME) if net.config.sigma_head else OUTPUT_NAMES


def export_onnx(net: DualHeadMimoUNet, path: str | Path) -> float:
    """Write ``net``'s graph to ``path`` without a manifest (speed probes); returns |onnxruntime − torch| max."""
    return runtime_export.export_onnx(InferenceWrapper(net), path, channels=input_channels(net),
                                      output_names=output_names(net))


def export_with_manifest(net: DualHeadMimoUNet, path: str | Path, *, preset: str, lens: str,
                         training: dict, metrics: dict | None = None, classical_config: dict | None = None) -> Path:
    """Export through ``runtime.export.export_model``, then return the manifest's path.

    A refinement (``net.config.extra_channels`` > 0) needs ``classical_config``, the decoder knobs its
    channels were made with; the manifest then says ``decoder: "learned"``."""
    onnx_path = runtime_export.export_model(InferenceWrapper(net), path, preset=preset, lens=lens,
                                            training=training, metrics=metrics, probe_px=RF_PROBE_PX,
                                            extra_channels=net.config.extra_channels,
                                            classical_config=classical_config)
    return manifest_path(onnx_path)


