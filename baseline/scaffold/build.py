"""Building a model and its entropy model from a config and a scene's points."""
from __future__ import annotations

import torch

from baseline import registry
from baseline.config import Config
from baseline.scaffold.anchors import auto_voxel_size, init_log_scaling, voxelize
from baseline.scaffold.model import AnchorModel


def build_model(cfg: Config, points: torch.Tensor) -> tuple[AnchorModel, float]:
    """Anchors from the scene's points; returns (model, voxel size)."""
    if points.numel() == 0:
        raise ValueError("the scene has no points to initialise anchors from")
    v = cfg.model.voxel_size
    if v <= 0:
        v = auto_voxel_size(points)
    xyz = voxelize(points, v)
    log_scaling = init_log_scaling(xyz)
    prov_cls = registry.get("feature_provider", cfg.model.feature_provider)
    ref_cls = None if cfg.model.refiner in ("", "none") else registry.get("refiner", cfg.model.refiner)
    model = AnchorModel(
        xyz, log_scaling, cfg.model,
        provider_factory=lambda m: prov_cls(m, cfg),
        refiner_factory=(lambda m: ref_cls(m, cfg)) if ref_cls else None,
        mask_threshold=cfg.entropy.mask_threshold)
    model.voxel_size = float(v)
    return model, v


def build_entropy(cfg: Config, model: AnchorModel):
    """The configured entropy model, its head sized from the provider's coded attributes."""
    cls = registry.component_class("entropy_model", cfg.entropy.model)
    if cfg.entropy.context == "provider":
        grid = model.provider.context_grid()
        if grid is None:
            raise ValueError(f"entropy.context = 'provider': the feature provider "
                             f"'{cfg.model.feature_provider}' has no grid to read")
        if "provider" not in getattr(cls, "CONTEXTS", ()):
            raise ValueError(f"entropy.context = 'provider': the '{cfg.entropy.model}' entropy "
                             f"model has no grid context to read a provider's grid with")
        return cls.build(cfg, model.coded_attributes(), model.n_offsets, model.n_anchors,
                         context_grid=grid)
    return cls.build(cfg, model.coded_attributes(), model.n_offsets, model.n_anchors)


def entropy_param_groups(cfg: Config, entropy) -> list[dict]:
    """Adam groups of an entropy model: hash-grid tables (``grid.*``) at the grid rate, channel
    context networks (``ctx.*``) at theirs, the rest (context MLP / hyperprior, factorized
    densities) at the context rate."""
    grid, channel, rest = [], [], []
    for name, p in entropy.named_parameters():
        (grid if name.startswith("grid.") else channel if name.startswith("ctx.")
         else rest).append(p)
    lr = cfg.lr
    groups = [dict(name="entropy_grid", params=grid, lr_init=lr.grid_init, lr_final=lr.grid_final),
              dict(name="entropy_context", params=rest, lr_init=lr.context_init,
                   lr_final=lr.context_final)]
    if channel:                       # channel context networks (their own schedule)
        groups.append(dict(name="entropy_channel", params=channel, lr_init=lr.channel_init,
                           lr_final=lr.channel_final))
    return groups
