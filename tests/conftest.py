"""Shared test set-up: PSF caches go to a per-session temporary folder, never the user's."""

import pytest


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    import os

    os.environ["BMI_CACHE_DIR"] = str(tmp_path_factory.mktemp("bmi_cache"))
    yield


@pytest.fixture(scope="session")
def passthrough_model(tmp_path_factory):
    """An ONNX model that follows the model_io contract and costs nothing: aif = the demosaiced input,
    depth = 1 + θ/60°. It exposes exactly what the runtime fed the network."""
    from torch import nn

    from bmi_sdk.runtime import export_model

    class PassThrough(nn.Module):
        def forward(self, x):
            return x[:, :3] * 1.0, 1.0 + x[:, 3:4]

    return export_model(PassThrough(), tmp_path_factory.mktemp("passthrough") / "pass.onnx", preset="test-pass")
