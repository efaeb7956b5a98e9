"""Predict-GS as a plugin of the baseline: registered through the ``pgs.plugins`` entry point.

The baseline never imports this package; :func:`register` adds its components to the baseline's
registry when the plugin is discovered at start-up:
    config_section ``predict``, feature_provider ``sfp``, refiner ``mgrd``,
    hooks ``predict_stages``.
"""
from __future__ import annotations


def register(registry) -> None:
    from predict_plugin.config import PredictConfig

    registry.register("config_section", "predict", PredictConfig)
    # Components that need the baseline's compiled pieces are imported lazily by name.
    registry.register("feature_provider", "sfp", _lazy("predict_plugin.sfp", "SpatialFeaturePool"))
    registry.register("refiner", "mgrd", _lazy("predict_plugin.mgrd", "MGRD"))
    registry.register("hooks", "predict_stages", _lazy("predict_plugin.hooks", "PredictStages"))


def _lazy(module: str, name: str):
    def factory(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    def resolve():
        import importlib

        return getattr(importlib.import_module(module), name)

    factory.__qualname__ = f"{module}.{name}"
    factory.resolve = resolve          # registry.component_class: the class itself
    return factory
