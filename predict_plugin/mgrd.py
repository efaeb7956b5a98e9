"""Multi-head Gaussian Residual Decoder (paper eq. 4): refiner ``mgrd``.

Two heads, each a two-layer MLP with ReLU, input f_r + view direction (3) + distance (1):
shape head -> K x 7 (delta scale 3, delta rotation 4), appearance head -> K x 4 (delta
opacity 1, delta colour 3).

Where the corrections enter (``predict.corrections``; eq. 5 adds them to the coarse Gaussians'
attributes): "pre" (default) in the pre-activation space of the decoder heads, i.e. refined
opacity = tanh(raw_o + d_o), colour = sigmoid(raw_c + d_c), scale = s_anchor * sigmoid(raw_s +
d_s), rotation = normalize(raw_r + d_r), which keeps every refined attribute in its valid range
with no clamping; "post" adds opacity and colour corrections to the activated values, tanh(raw_o)
+ d_o and sigmoid(raw_c) + d_c (Scaffold-GS's opacity and colour MLPs end in their activations,
so these are the attributes they output), and the shape corrections to the cov head's raw output
as "pre" does. Either way a zero correction leaves the predicted Gaussians exactly unchanged. The
heads' last layers start at zero (``predict.mgrd_init``), so switching the residual branch on
(stage 2) does not disturb the prediction learned in stage 1.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from baseline.contracts import BakeHead, Refiner


class MGRD(Refiner):
    SECTION_LABELS = {"weights": ""}        # its one section: "mgrd" in pgs info and reports

    def __init__(self, model, cfg):
        super().__init__()
        p = cfg.ext["predict"]
        K = cfg.model.n_offsets
        self.n_offsets = K
        d_in = p.residual_dim + 3 + 1
        h = p.mgrd_hidden
        self.shape_head = nn.Sequential(nn.Linear(d_in, h), nn.ReLU(), nn.Linear(h, 7 * K))
        self.appearance_head = nn.Sequential(nn.Linear(d_in, h), nn.ReLU(), nn.Linear(h, 4 * K))
        if p.mgrd_init not in ("zero", "default"):
            raise ValueError(f"predict.mgrd_init must be 'zero' or 'default', got '{p.mgrd_init}'")
        if p.mgrd_init == "zero":
            for head in (self.shape_head, self.appearance_head):
                nn.init.zeros_(head[2].weight)
                nn.init.zeros_(head[2].bias)
        self.active = False        # stage 1: residual branch off (set by the predict_stages hooks)
        if p.corrections not in ("pre", "post"):
            raise ValueError(f"predict.corrections must be 'pre' or 'post', got '{p.corrections}'")
        self.post_activation = ("opacity", "color") if p.corrections == "post" else ()
        if p.mgrd_lr not in ("own", "heads"):
            raise ValueError(f"predict.mgrd_lr must be 'own' or 'heads', got '{p.mgrd_lr}'")

    def forward(self, idx, values, view_dir, dist):
        """values["residual"] [M,R], view_dir [M,3], dist [M,1] -> corrections:
        opacity [M,K], cov [M,K,7] (scale 3 | rotation 4), color [M,K,3]."""
        x = torch.cat([values["residual"], view_dir, dist], dim=-1)
        K = self.n_offsets
        shape = self.shape_head(x).view(-1, K, 7)
        app = self.appearance_head(x).view(-1, K, 4)
        return {"opacity": app[..., 0], "color": app[..., 1:4], "cov": shape}

    def bake_heads(self, values):
        """Both heads for :class:`~baseline.scaffold.baked.BakedDecoder` (values: all anchors'
        decoded values): shape -> cov, appearance -> opacity (channel 0) and color (1-3)."""
        r = values["residual"]
        return [BakeHead(r, self.shape_head, True, {"cov": (0, 7)}),
                BakeHead(r, self.appearance_head, True, {"opacity": (0, 1), "color": (1, 4)})]

    def param_groups(self, cfg):
        p = cfg.ext["predict"]
        if p.mgrd_lr == "heads":     # each head at the schedule of the head it corrects
            lr = cfg.lr
            return [dict(name="mgrd_shape", params=list(self.shape_head.parameters()),
                         lr_init=lr.mlp_cov, lr_final=lr.mlp_cov),
                    dict(name="mgrd_appearance", params=list(self.appearance_head.parameters()),
                         lr_init=lr.mlp_color_init, lr_final=lr.mlp_color_final)]
        return [dict(name="mgrd", params=list(self.parameters()), lr_init=p.lr_mgrd_init,
                     lr_final=p.lr_mgrd_final)]
