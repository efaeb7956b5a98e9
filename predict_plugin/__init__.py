"""Predict-GS as a plugin of the baseline: registered through the ``pgs.plugins`` entry point.

The baseline never imports this package; :func:`register` adds to the baseline's registry, when
the plugin is discovered at start-up: the method spec ``predict-gs`` (its label and patches),
its patch folder, the config section ``predict``, the feature provider ``sfp``, the refiner
``mgrd`` and the training hooks ``predict_stages``.
"""
from __future__ import annotations

from pathlib import Path

from baseline.contracts import MethodSpec

PATCH_DIR = Path(__file__).resolve().parent / "patches"

SPEC = MethodSpec(
    name="predict-gs", label="Predict-GS",
    description="Spatial Feature Pool + residual decoded by MGRD + prediction-tailored "
                "progressive training",
    patches=("predict-gs", "predict-gs-high-rate", "sfp-only", "no-progressive", "no-anneal",
             "linear-anneal", "fusion-default", "sfp-zero-fusion", "sfp-lr-low", "sfp-contract",
             "sfp-grid-auto", "residual-grow-parent", "mgrd-post"),
    notes=(("feature_sections", "SFP grid + fusion MLP + residual"),
           ("grown_anchors", "grown in stage 1 / after"),
           ("training_curve", "progressive training renders downsampled views for the first 30% "
                              "of the schedule: its L1 there is on smaller images.")),
    demo=True)


def register(registry) -> None:
    from predict_plugin.config import PredictConfig

    registry.register_method(SPEC)
    registry.register_patch_dir("predict-gs", PATCH_DIR)
    registry.register("config_section", "predict", PredictConfig)
    # Components that need the baseline's compiled pieces are imported when first used.
    registry.register("feature_provider", "sfp", registry.lazy("predict_plugin.sfp",
                                                               "SpatialFeaturePool"))
    registry.register("refiner", "mgrd", registry.lazy("predict_plugin.mgrd", "MGRD"))
    registry.register("hooks", "predict_stages", registry.lazy("predict_plugin.hooks",
                                                               "PredictStages"))
