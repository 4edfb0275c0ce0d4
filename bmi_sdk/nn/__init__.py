"""Network, losses, training data, training loop, export and benchmark of the AiF + depth decoder (paper §3.4, §4).

Public API:

* ``DualHeadMimoUNet``, ``ModelConfig``, ``PRESETS``, ``preset_config`` — the network (``model``);
* ``total_loss`` and its terms ``content_loss``, ``fft_loss``, ``silog_loss`` (``losses``);
* ``CacheSpec``, ``build_cache``, ``PairCache``, ``simulate_sensor`` — training pairs (``data``);
* ``TrainConfig``, ``load_weights`` and the training loop ``train.train`` (``train``);
  ``export_with_manifest`` (``export``);
* ``Benchmark``, ``run_benchmark`` (``evaluate``; the metrics themselves are ``bmi_sdk.metrics``).

The names resolve lazily (PEP 562): ``bmi_sdk.nn.X`` imports only the
submodule that defines X. So ``import bmi_sdk.nn.data`` (numpy only) does
not load torch (4 s); ``model``, ``losses``, ``train`` and ``export`` do.
``bmi_sdk.nn.train`` is therefore always the submodule (importing a submodule
binds its name on the package); the function is ``bmi_sdk.nn.train.train``.
"""

from __future__ import annotations

import importlib

_HOME = {
    "CacheSpec": "data", "PairCache": "data", "build_cache": "data", "simulate_sensor": "data",
    "Benchmark": "evaluate", "run_benchmark": "evaluate",
    "export_with_manifest": "export",
    "content_loss": "losses", "fft_loss": "losses", "silog_loss": "losses", "total_loss": "losses",
    "PRESETS": "model", "DualHeadMimoUNet": "model", "ModelConfig": "model", "preset_config": "model",
    "TrainConfig": "train", "load_weights": "train",
}
"""Public name → the submodule that defines it."""

__all__ = list(_HOME)


def __getattr__(name: str):
    """A public name (from its submodule) or a submodule, imported on first use."""
    if name in _HOME:
        value = getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    elif name in _HOME.values():
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # resolved once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME))
