"""Predict-GS as a plugin of the baseline: registered through the ``pgs.plugins`` entry point.

The baseline never imports this package; :func:`register` adds its components to the baseline's
registry when the plugin is discovered at start-up.
"""
from __future__ import annotations


def register(registry) -> None:
    from predict_plugin.config import PredictConfig

    registry.register("config_section", "predict", PredictConfig)
