"""The metrics' former path: they live in ``bmi_sdk.metrics``.

Kept only because ``nn.evaluate`` (being changed elsewhere) imports them from
here; remove this module once it imports ``bmi_sdk.metrics``.
"""

from bmi_sdk.metrics import depth_metrics, image_metrics, mean_metrics

__all__ = ["depth_metrics", "image_metrics", "mean_metrics"]
