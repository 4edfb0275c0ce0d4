"""Network, losses, training data, training loop, export and benchmark of the AiF + depth decoder (paper §3.4, §4).

Public API:

* ``DualHeadMimoUNet``, ``ModelConfig``, ``PRESETS``, ``preset_config`` — the network (``model``);
* ``total_loss`` and its terms ``content_loss``, ``fft_loss``, ``silog_loss`` (``losses``);
* ``CacheSpec``, ``build_cache``, ``PairCache``, ``simulate_sensor`` — training pairs (``data``);
* ``TrainConfig``, ``train``, ``load_weights`` (``train``); ``export_with_manifest`` (``export``);
* ``depth_metrics``, ``image_metrics`` (``metrics``); ``Benchmark``, ``run_benchmark`` (``evaluate``).

torch is imported by the modules that need it; ``metrics`` and ``data`` are numpy only.
"""

from bmi_sdk.nn.data import CacheSpec, PairCache, build_cache, simulate_sensor
from bmi_sdk.nn.evaluate import Benchmark, run_benchmark
from bmi_sdk.nn.export import export_with_manifest
from bmi_sdk.nn.losses import content_loss, fft_loss, silog_loss, total_loss
from bmi_sdk.nn.metrics import depth_metrics, image_metrics
from bmi_sdk.nn.model import PRESETS, DualHeadMimoUNet, ModelConfig, preset_config
from bmi_sdk.nn.train import TrainConfig, load_weights, train

__all__ = ["DualHeadMimoUNet", "ModelConfig", "PRESETS", "preset_config", "total_loss", "content_loss", "fft_loss",
           "silog_loss", "CacheSpec", "build_cache", "PairCache", "simulate_sensor", "TrainConfig", "train",
           "load_weights", "export_with_manifest", "depth_metrics", "image_metrics", "Benchmark", "run_benchmark"]
