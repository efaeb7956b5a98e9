"""Baked Gaussian decoding for decoded models: what does not depend on the view, computed once.

A decoded model is frozen: its anchors, coded values, masks and (for a predicting provider) predicted
features never change between frames. Every head that turns an anchor into its K neural Gaussians
(the decoder's opacity, cov and color MLPs, and a refiner's heads such as MGRD's shape and
appearance heads) is ``Linear(x ; v ; d) -> ReLU -> Linear`` with ``x`` per anchor and ``v, d``
the view direction and distance, so its first layer splits into

    W1 [x ; v ; d] + b1  =  (W1_x x + b1)  +  W1_v v + W1_d d
                             per anchor, once    [M,4] x [4,H] per view

and heads whose outputs add into the same pre-activation attribute (a refiner's correction
enters before the activations, :meth:`AnchorModel.raw_heads`) share one second-layer GEMM over
their concatenated hidden units. A frame then costs one gather, one small GEMM for all first
layers of all heads, and three second-layer GEMMs (opacity, cov, color), for the baseline and a
refined model alike; Gaussians whose mask is off or whose opacity is <= 0 are dropped before any
activation, as in :meth:`AnchorModel.decode`.

What changes against :meth:`AnchorModel.decode`: the first layer's sums run in another order
(float32 rounding: pre-activations differ by ~1e-6 relative), so a Gaussian whose opacity
logit is within rounding of 0 may be kept by one form and not the other (its opacity is then
~1e-7: invisible), and where a Gaussian's alpha at a pixel lies within rounding of the
rasterizer's 1/255 cut-off, one form composites it and the other skips it: a few pixels move
by up to about 1/255 (``pgs bench fps`` prints the largest difference). Tests compare the two
forms on trained models, image and Gaussians.

The bake holds ``(N, H)`` floats for H hidden units in all (baseline 3 x 50 = 150; with a
refiner of 2 x 64 more, 278), built by :meth:`AnchorModel.bake`. Decoded models are baked on CUDA
(:meth:`AnchorModel.bake_if_faster`; on the CPU they stay plain, whose frames are the records');
``pgs bench fps`` times both forms anywhere and prints how far their images differ.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable, Optional

import torch

from baseline.contracts import BakeHead, Refiner  # noqa: F401  (BakeHead: the heads it bakes)
from baseline.scaffold.gaussians import kept_gaussians

# Pre-activation attributes a head can add to, with their channels per neural Gaussian.
ATTR_CHANNELS = {"opacity": 1, "cov": 7, "color": 3}


@dataclass
class _Second:
    lo: int                 # hidden units [lo, hi) feed this attribute
    hi: int
    weight: torch.Tensor    # [hi - lo, K * C]
    bias: torch.Tensor      # [K * C]


def _order_heads(heads: list[BakeHead]) -> list[int]:
    """An order of the heads in which every attribute's contributing heads are adjacent (so
    each second layer reads one contiguous slice of the hidden units); the given order if
    none exists (the slices then also cover non-contributing heads, with zero weights)."""
    def contiguous(order):
        for a in ATTR_CHANNELS:
            pos = [i for i, h in enumerate(order) if a in heads[h].targets]
            if pos and pos[-1] - pos[0] + 1 != len(pos):
                return False
        return True

    if len(heads) <= 7:
        for order in itertools.permutations(range(len(heads))):
            if contiguous(order):
                return list(order)
    return list(range(len(heads)))


class BakedDecoder:
    """Render-time decoding of a frozen (decoded) :class:`AnchorModel`; see the module doc.

    Build with :meth:`from_model`; :meth:`decode` returns the same :class:`Gaussians` as
    ``model.decode(cam_center, idx)`` (``opacity_all`` is None: only training reads it).
    """

    def __init__(self, *, P, Wv, second, gmask, xyz, offsets_world, scales_base, n_offsets):
        self.P = P                          # [N, H] first-layer per-anchor term (+ bias)
        self.Wv = Wv                        # [4, H] view direction (3) and distance rows
        self.second = second                # attr -> _Second
        self.gmask = gmask                  # [N, K] bool: the Gaussian masks
        self.xyz = xyz                      # [N, 3]
        self.offsets_world = offsets_world  # [N*K, 3] offsets * anchor scaling[:3]
        self.scales_base = scales_base      # [N, 3] anchor scaling[3:]
        self.n_offsets = n_offsets

    @classmethod
    @torch.no_grad()
    def from_model(cls, model) -> Optional["BakedDecoder"]:
        """Bake ``model`` (it must hold decoded values: ``model.fixed_values``). None when a
        refiner does not declare its heads (``bake_heads``) or adds corrections after the
        activations (``post_activation``): such a model renders unbaked."""
        if model.fixed_values is None:
            raise ValueError("only a decoded model (fixed values) can be baked")
        N, K = model.n_anchors, model.n_offsets
        dev = model.xyz.device
        idx = torch.arange(N, device=dev)
        values = model.coded_values(idx)
        xyz = model.positions().detach()
        feat = model.provider.decoder_features(idx, values, xyz)
        heads = model.decoder.bake_heads(feat)
        ref = model.refiner
        if ref is not None and ref.active:
            # a refiner outside the Refiner contract declares no heads either; one that adds
            # corrections after the activations cannot share the pre-activation second layers
            ref_heads = (ref.bake_heads(values)
                         if isinstance(ref, Refiner) and not ref.post_activation else None)
            if ref_heads is None:               # a refiner that declares no heads
                return None
            heads = heads + list(ref_heads)
        order = _order_heads(heads)
        heads = [heads[i] for i in order]
        widths = [h.mlp[0].out_features for h in heads]
        starts = [sum(widths[:i]) for i in range(len(heads))]
        H = sum(widths)
        P = torch.empty(N, H, device=dev)
        Wv = torch.zeros(4, H, device=dev)
        for h, s, w in zip(heads, starts, widths):
            lin = h.mlp[0]
            D = h.x.shape[1]
            P[:, s:s + w] = torch.addmm(lin.bias, h.x.float(), lin.weight[:, :D].t())
            Wv[:3, s:s + w] = lin.weight[:, D:D + 3].t()
            if h.uses_distance:
                Wv[3, s:s + w] = lin.weight[:, D + 3]
        second = {}
        for a, C in ATTR_CHANNELS.items():
            users = [i for i, h in enumerate(heads) if a in h.targets]
            if not users:
                raise ValueError(f"bake: no head produces '{a}'")
            lo, hi = starts[users[0]], starts[users[-1]] + widths[users[-1]]
            W = torch.zeros(hi - lo, K * C, device=dev)
            b = torch.zeros(K * C, device=dev)
            for i in users:
                h = heads[i]
                first, stop = h.targets[a]
                lin = h.mlp[2]
                Ch = lin.out_features // K
                if stop - first != C or not 0 <= first < stop <= Ch:
                    raise ValueError(f"bake: a head maps channels {first}:{stop} of its {Ch} "
                                     f"to '{a}', which has {C} channels per Gaussian")
                w2 = lin.weight.view(K, Ch, -1)[:, first:stop, :]        # [K, C, width]
                W[starts[i] - lo:starts[i] - lo + widths[i]] += w2.reshape(K * C, -1).t()
                b += lin.bias.view(K, Ch)[:, first:stop].reshape(-1)
            second[a] = _Second(lo, hi, W.contiguous(), b)
        gmask = model.gaussian_mask().detach() > 0.5
        scaling = values["scaling"].float()
        off = (values["offsets"].float().view(N, K, 3) * scaling[:, None, :3]).reshape(N * K, 3)
        return cls(P=P, Wv=Wv, second=second, gmask=gmask, xyz=xyz.clone(),
                   offsets_world=off, scales_base=scaling[:, 3:].contiguous(), n_offsets=K)

    def apply(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> "BakedDecoder":
        """The same bake with ``fn`` (``.to(device)``, ...) applied to every tensor."""
        second = {a: _Second(s.lo, s.hi, fn(s.weight), fn(s.bias)) for a, s in self.second.items()}
        return BakedDecoder(P=fn(self.P), Wv=fn(self.Wv), second=second, gmask=fn(self.gmask),
                            xyz=fn(self.xyz), offsets_world=fn(self.offsets_world),
                            scales_base=fn(self.scales_base), n_offsets=self.n_offsets)

    def _second(self, attr: str, hid: torch.Tensor) -> torch.Tensor:
        s = self.second[attr]
        return torch.addmm(s.bias, hid[:, s.lo:s.hi], s.weight)

    @torch.no_grad()
    def hidden(self, cam_center: torch.Tensor, idx: torch.Tensor):
        """Anchors ``idx`` [M] seen from ``cam_center`` [3]: their positions [M, 3] and every
        head's hidden units after the ReLU [M, H] (the first layers of all heads)."""
        xyz = self.xyz[idx]
        view = xyz - cam_center.to(xyz)[None, :]
        dist = view.norm(dim=1, keepdim=True).clamp_min(1e-8)
        vd = torch.cat([view / dist, dist], dim=1)                         # [M, 4]
        return xyz, self.P[idx].addmm_(vd, self.Wv).relu_()                # [M, H]

    @torch.no_grad()
    def kept(self, hid: torch.Tensor, idx: torch.Tensor):
        """The opacity head's pre-activations [M, K] of anchors ``idx`` from their hidden units
        ``hid`` [M, H], and which of their M*K candidates are drawn [M*K] (bool)."""
        raw_op = self._second("opacity", hid)
        # tanh(x) * mask > 0  <=>  x > 0 and mask on
        return raw_op, ((raw_op > 0) & self.gmask[idx]).reshape(-1)

    @torch.no_grad()
    def decode(self, cam_center: torch.Tensor, idx: torch.Tensor,
               visible: Optional[torch.Tensor] = None):
        """Neural Gaussians of anchors ``idx`` [M] seen from ``cam_center`` [3] (a
        :class:`~baseline.scaffold.model.Gaussians`, ``opacity_all`` None)."""
        K = self.n_offsets
        M = len(idx)
        xyz, hid = self.hidden(cam_center, idx)
        raw_op, sel = self.kept(hid, idx)                                  # [M, K], [M*K]
        keep = sel.nonzero()[:, 0]                                         # [G]
        row = torch.div(keep, K, rounding_mode="floor")                    # [G]
        anchor = idx[row]
        return kept_gaussians(
            means=xyz[row] + self.offsets_world[anchor * K + keep - row * K],
            cov=self._second("cov", hid).reshape(M * K, 7)[keep],
            raw_color=self._second("color", hid).reshape(M * K, 3)[keep],
            opacities=torch.tanh(raw_op.reshape(-1)[keep]), scales_base=self.scales_base[anchor],
            anchor_index=anchor, selection=sel, opacity_all=None, idx=idx,
            n_anchors=self.P.shape[0], visible=visible)
