"""Predict-GS configuration section ``[predict]`` (paper section 3, appendix A.2).

Milestones are at the paper's 30k scale and scale with ``train.iterations`` like the baseline's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar


@dataclass
class PredictConfig:
    # numeric ranges, checked as the baseline's sections declare theirs (baseline.config.validate)
    RANGES: ClassVar[dict] = {
        "fusion_hidden": (1, 4096), "residual_dim": (0, 1024), "residual_from": (0, 1 << 31),
        "mgrd_hidden": (1, 4096), "d_s": (1e-3, 16.0), "d_e": (1e-3, 16.0), "T": (0, 1 << 31),
        "lr_residual": (0, 1e3), "lr_grid_init": (0, 1e3), "lr_grid_final": (0, 1e3),
        "lr_fusion_init": (0, 1e3), "lr_fusion_final": (0, 1e3), "lr_mgrd_init": (0, 1e3),
        "lr_mgrd_final": (0, 1e3), "box_quantile": (0.0, 0.25)}
    # options added after runs were archived, with the value that reproduces those runs: left
    # out of the config hash at that value (baseline.config.identity)
    LATER_KEYS: ClassVar[dict] = {"fusion_init": "zero", "grid_init": "random", "box": "extent",
                                  "box_quantile": 0.01, "residual_grow": "zero",
                                  "corrections": "pre", "mgrd_lr": "own",
                                  "residual_noise": "always", "mgrd_init": "zero"}
    # options only the SFP reads: left out of the hash of a config without it
    COMPONENT_KEYS: ClassVar[dict] = {"fusion_init": ("feature_provider", "sfp"),
                                      "grid_init": ("feature_provider", "sfp"),
                                      "residual_grow": ("feature_provider", "sfp"),
                                      "corrections": ("refiner", "mgrd"),
                                      "mgrd_lr": ("refiner", "mgrd"),
                                      "residual_noise": ("feature_provider", "sfp"),
                                      "mgrd_init": ("refiner", "mgrd")}

    # Spatial Feature Pool (its own binary hash grid, HAC layout) + two-layer fusion MLP -> 50.
    fusion_hidden: int = 64            # choose: the paper gives two layers and the 50-dim output only
    # The SFP's start (the paper is silent; docs/notes/predict-gs-gaussian-count.md).
    # grid_init: "shared" = every entry of the SFP's tables starts at +init_range, so every
    # anchor reads one binarized code and starts with one feature, as Scaffold-GS's anchors all
    # start at feature 0, and each cell's entries then move by their own gradients; "random" =
    # HAC's U(-1e-4, 1e-4), a random +-1 code per cell from the first step.
    grid_init: str = "shared"
    # fusion_init: the fusion MLP's last layer: "default" (PyTorch's init) or "zero" (f_c = 0
    # for every anchor, but no gradient reaches the grid until that layer has moved: the field
    # learns one pattern for all anchors first; on a random initialisation in front of a black
    # background every Gaussian's opacity fell below zero within 12 steps and training
    # collapsed)
    fusion_init: str = "default"
    grid_auto: bool = False            # size the SFP tables from the anchor count
    # the SFP's normalisation (the paper is silent): "extent" = the initial anchors' box + 10%;
    # "contract" = their [q, 1-q] quantile box + 10% fills the middle half of the grid and the
    # space outside is contracted into the rest (predict_plugin/sfp.py)
    box: str = "extent"
    box_quantile: float = 0.01
    # Residual compensation
    residual: bool = True              # False: SFP only (ablation)
    residual_dim: int = 25
    # what a grown anchor's residual starts at (the paper is silent): "zero" = no correction
    # (its Gaussians start as the field predicts them there); "parent" = the element-wise max
    # of its parents' residuals, the rule Scaffold-GS and HAC apply to the per-anchor feature
    # that the residual takes the place of
    residual_grow: str = "zero"
    residual_from: int = 5000          # stage 2 starts here (stage 1: SFP only)
    # the residual in training's noise phase (the paper is silent; HAC adds U(-0.5, 0.5) x Q0
    # to every coded value from 3k until the rate starts): "always" = as every coded value;
    # "rate" = left exact until the rate starts (its adaptive quantization then reaches it)
    residual_noise: str = "always"
    mgrd_hidden: int = 64              # choose: hidden width of each MGRD head
    # the MGRD heads' output layers at the start (the paper is silent): "zero" = no correction
    # until they have trained, so switching stage 2 on leaves the stage-1 prediction exactly as
    # it was; "default" = PyTorch's initialisation, what HAC-based code gives a new layer (a
    # random correction of the view direction and distance from stage 2's first step)
    mgrd_init: str = "zero"
    # where MGRD's corrections enter (eq. 5 adds them to the coarse Gaussians' attributes):
    # "pre" = before every activation (refined opacity tanh(raw + d), colour sigmoid(raw + d),
    # scale and rotation from raw cov + d: a zero correction changes nothing and every refined
    # attribute stays in range); "post" = opacity and colour after their activations (tanh(raw)
    # + d, sigmoid(raw) + d: eq. 5 read on the attributes Scaffold-GS's MLPs output, whose
    # opacity and colour heads end in Tanh and Sigmoid), scale and rotation on the cov head's
    # raw output (it has no activation of its own)
    corrections: str = "pre"
    # Progressive downsampling of the training view (equation 6)
    schedule: str = "cosine"           # cosine | linear | none (fixed d_s until stage 2)
    d_s: float = 0.7
    d_e: float = 1.0
    T: int = 9000
    # learning rates
    lr_residual: float = 0.0075
    lr_grid_init: float = 0.005
    lr_grid_final: float = 0.00001
    lr_fusion_init: float = 0.004
    lr_fusion_final: float = 0.00004
    lr_mgrd_init: float = 0.004
    lr_mgrd_final: float = 0.00004
    # the MGRD heads' learning rates (the paper gives none: "the same hyperparameter settings as
    # HAC"): "own" = both heads lr_mgrd_init -> lr_mgrd_final over the whole schedule; "heads" =
    # each head the schedule of the decoder head whose output it corrects, the shape head the
    # cov head's (lr.mlp_cov, constant), the appearance head the colour head's (lr.mlp_color_*)
    mgrd_lr: str = "own"
