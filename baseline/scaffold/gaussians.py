"""Neural Gaussians of one view: what the anchor model's decoding and baked decoding return."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F


@dataclass
class Gaussians:
    """Neural Gaussians of the visible anchors of one view (after the opacity > 0 selection).

    Attributes:
        means [G,3], quats [G,4] (normalized), scales [G,3], opacities [G], colors [G,3].
        anchor_index [G]: index (into all anchors) of the anchor each Gaussian belongs to.
        selection [M*K] bool: which of the visible anchors' K Gaussians were kept.
        opacity_all [M,K]: masked tanh opacity of every candidate Gaussian (growing statistics);
            None from a baked decoded model (:mod:`baseline.scaffold.baked`), which only renders.
        visible [N] bool: the anchors that passed the prefilter.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    anchor_index: torch.Tensor
    selection: torch.Tensor
    opacity_all: Optional[torch.Tensor]
    visible: torch.Tensor


def kept_gaussians(*, means, cov, raw_color, opacities, scales_base, anchor_index, selection,
                   opacity_all, idx, n_anchors, visible=None, color_add=None) -> Gaussians:
    """The activation tail shared by :meth:`AnchorModel.decode` and baked decoding: kept
    Gaussians' pre-activation cov [G,7] and color [G,3] -> scales (``scales_base`` [G,3] x
    sigmoid), normalized quaternions, sigmoid colours (+ ``color_add`` [G,3], a refiner's
    corrections after the activation); ``visible`` [N] built from ``idx`` when not given."""
    if visible is None:
        visible = torch.zeros(n_anchors, dtype=torch.bool, device=idx.device)
        visible[idx] = True
    colors = torch.sigmoid(raw_color)
    if color_add is not None:
        colors = colors + color_add
    return Gaussians(means=means, quats=F.normalize(cov[:, 3:7], dim=-1),
                     scales=scales_base * torch.sigmoid(cov[:, :3]), opacities=opacities,
                     colors=colors, anchor_index=anchor_index,
                     selection=selection, opacity_all=opacity_all, visible=visible)
