"""The baseline's feature provider ``explicit``: a per-anchor table
(contract: :class:`baseline.contracts.FeatureProvider`)."""
from __future__ import annotations

import torch

from baseline import registry
from baseline.contracts import FeatureProvider, scaffold_coded_attributes
from baseline.scaffold.model import grow_max_of_parents


class ExplicitFeatures(FeatureProvider):
    """Scaffold-GS / HAC: a learned 50-dim feature per anchor (init 0, grown = max of parents)."""

    def __init__(self, model, cfg):
        super().__init__()
        self.feature_dim = cfg.model.feat_dim
        self.n_offsets = cfg.model.n_offsets
        self._model = [model]  # not a submodule: avoid a reference cycle in the module tree
        model.add_per_anchor("feat", torch.zeros(model.n_anchors, self.feature_dim), grow_max_of_parents)

    def coded_attributes(self):
        return scaffold_coded_attributes(self.feature_dim, self.n_offsets)

    def coded_values(self, idx):
        return {"feat": self._model[0].per_anchor["feat"][idx]}

    def decoder_features(self, idx, values, xyz):
        return values["feat"]

    def param_groups(self, cfg):
        return [dict(name="feat", params=[self._model[0].per_anchor["feat"]],
                     lr_init=cfg.lr.feature, lr_final=cfg.lr.feature)]


registry.register("feature_provider", "explicit", ExplicitFeatures)
