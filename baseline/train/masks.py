"""How the Gaussian masks are trained: a strategy chosen by ``entropy.mask_training``, so that
neither a method nor an entropy model branches on it (contract:
:class:`baseline.contracts.MaskTraining`).

* ``hac`` (HAC's reference code): the rate is estimated on a ~5% sample of the *visible, valid*
  anchors inside the render (:func:`baseline.pipeline.render_view`), the offsets' bits weighted
  by the straight-through Gaussian mask, the sampled term multiplied by the share of valid
  visible anchors; a mask loss ``mask_lambda x mean(sigmoid(mask))``; masks multiply the
  opacity *before* the opacity > 0 selection.
* ``hacpp`` (HAC++'s code): no mask loss; the rate alone trains the masks. It is estimated on a
  ``rate_sample`` share of *all* anchors: feature and scaling bits weighted by an anchor mask
  (1 if any of its K masks is on; straight-through, gradient through the mean of the K masks),
  offsets' bits by anchor mask x Gaussian mask. In training the masks multiply opacity and scale
  *after* the opacity > 0 selection (a masked Gaussian is drawn with opacity 0, so the
  reconstruction can switch it back on). The mask learning rate decays to
  ``min(lr.mask_final_per_mlambda x lambda / 1e-3, lr.mask_final_cap)`` (x the scene extent;
  cap 0: none): HAC++'s per-dataset values are in the dataset patches.
"""
from __future__ import annotations

import torch

from baseline import registry
from baseline.contracts import MaskTraining
from baseline.device import uniform
from baseline.train.losses import rate_term


class HACMaskTraining(MaskTraining):
    name = "hac"
    mask_after_selection = False

    def __init__(self, trainer):
        self.t = trainer

    @property
    def render_rate_sample(self) -> float:
        return self.t.cfg.entropy.rate_sample

    def mask_lr_final(self, cfg, extent: float):
        return None

    def _hash_bits(self):
        t = self.t
        hb = t.entropy.hash_bits()
        own = t.model.provider.rate_bits()          # a provider's own hash grid, if any
        return hb if own is None else hb + own

    def loss(self, res):
        t, cfg = self.t, self.t.cfg
        rate, bpv = rate_term(res.bits, res.n_rate_anchors, res.valid_share, self._hash_bits(),
                              t.model.n_anchors, t.rate_values_per_anchor,
                              t.hash_values_per_anchor)
        terms = {}
        if bpv is not None:
            terms["bpp"] = bpv
            terms["valid_share"] = res.valid_share
        return ([cfg.entropy.lmbda * rate,
                 cfg.entropy.mask_lambda * torch.sigmoid(t.model.per_anchor["mask"]).mean()],
                terms)


class HACPPMaskTraining(HACMaskTraining):
    name = "hacpp"
    mask_after_selection = True

    @property
    def render_rate_sample(self) -> float:
        return 0.0                      # the rate is sampled over all anchors, in loss()

    def mask_lr_final(self, cfg, extent: float):
        v = cfg.lr.mask_final_per_mlambda * cfg.entropy.lmbda / 1e-3
        if cfg.lr.mask_final_cap > 0:
            v = min(v, cfg.lr.mask_final_cap)
        return v * extent

    def loss(self, res):
        t, cfg = self.t, self.t.cfg
        model, ent = t.model, t.entropy
        n = model.n_anchors
        dev = model.xyz.device
        rows = (uniform(n, t.step_generator, dev) <= cfg.entropy.rate_sample).nonzero()[:, 0]
        terms = {}
        rate = 0.0
        if len(rows):
            gm = model.gaussian_mask(rows)                              # [S, K] STE float
            share = gm.mean(dim=1)
            am = ((share > 0).float() - share).detach() + share          # [S] anchor mask
            weights = {}
            for a in model.coded_attributes():
                if a.masked:
                    per = a.dims // model.n_offsets
                    weights[a.name] = am[:, None] * gm.repeat_interleave(per, dim=1)
                else:
                    weights[a.name] = am[:, None].expand(-1, a.dims)
            _, bits = ent(model.positions(rows), model.coded_values(rows), gm, training=True,
                          bit_weights=weights)
            rate, bpv = rate_term(bits, len(rows), 1.0, None, n, t.rate_values_per_anchor)
            terms["bpp"] = bpv
            terms["valid_share"] = float((share > 0).float().mean())
        hb = self._hash_bits()
        if torch.is_tensor(hb):
            rate = rate + hb / (max(n, 1) * t.hash_values_per_anchor)
        return [cfg.entropy.lmbda * rate], terms


registry.register("mask_training", "hac", HACMaskTraining)
registry.register("mask_training", "hacpp", HACPPMaskTraining)
