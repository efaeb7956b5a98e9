"""One view through the whole pipeline: prefilter -> (quantize) -> decode -> rasterize.

Shared by training, evaluation and decoded models, so the three render exactly the same way.

Phases (docs/method.md section 3):
  ``none``      raw attribute values;
  ``noise``     training adds U(-0.5, 0.5) * Q0 noise; evaluation rounds with Q0;
  ``adaptive``  the entropy model's adaptive steps: noise in training (plus the rate estimate),
                rounding (straight-through) at evaluation, with 16-bit anchor positions.
  ``decoded``   values are already the decoded ones: nothing is quantized again.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch

from baseline.camera import Camera
from baseline.device import uniform
from baseline.hac.quant import ste_round
from baseline.render import prefilter_anchors, rasterize
from baseline.timing import backward_mark, stage


@dataclass
class ViewResult:
    render: object                    # RenderOutput
    gaussians: object                 # Gaussians
    camera: Camera
    bits: dict = field(default_factory=dict)      # attribute -> [S] per-anchor bits on the sample
    n_rate_anchors: int = 0
    # training, adaptive phase: the share of the visible anchors that are valid (any Gaussian
    # mask on), detached: HAC's ``mask_anchor_rate``, a factor of the sampled rate
    valid_share: float = 1.0


def quantized_positions(xyz: torch.Tensor, coded: torch.Tensor, coding: str = "raw16",
                        box: Optional[tuple] = None) -> torch.Tensor:
    """[N,3] positions after the codec's 16-bit quantization (HAC's widened anchor bounds);
    ``coding`` "lattice" stores them exactly (the voxel-lattice coordinates): unchanged.
    ``box``: the model's :attr:`~baseline.scaffold.model.AnchorModel.position_box` (a run
    trained at its 16-bit positions), which the encoder then uses; None: the coded anchors'.

    ``coded`` [N] bool, required (no all-anchors default: that was the bug): the anchors the
    encoder writes (``model.anchor_valid()``); the bounds come from those alone, as in the file,
    so the pre-encode evaluation sees the positions the decoder will have. (Bounds over all
    anchors moved every position whenever an anchor with every mask off lay outside the coded
    ones' box: 26.156 dB before vs 26.198 decoded on a truck run.) Anchors outside the bounds
    are clipped; they are never coded.
    """
    from baseline.codec.rangecoder import anchor_bounds, dequantize_positions, quantize_positions

    if coding == "lattice":
        return xyz.detach().clone()
    x = xyz.detach().cpu()
    lo, hi = box if box is not None else anchor_bounds(x[coded.cpu()].numpy())
    q = quantize_positions(x.numpy(), lo, hi)
    return torch.from_numpy(dequantize_positions(q, lo, hi)).to(xyz.device)


@dataclass
class CodedState:
    """A trained model's anchors as the codec will store them, for pre-encode evaluation:
    ``index`` [M] the coded anchors (any Gaussian mask on), ``xyz`` [M,3] their 16-bit
    positions, ``values`` {attribute: [M,d]} quantized exactly as the encoder quantizes them (one
    pass over all coded anchors, so the clamp's mean is the encoder's). Rendering from it
    prefilters with these positions and scalings, as the decoded model does."""
    index: torch.Tensor
    xyz: torch.Tensor
    values: dict


@torch.no_grad()
def coded_state(model, entropy, positions: str = "raw16") -> CodedState:
    """The :class:`CodedState` of ``model`` in HAC's adaptive phase (``positions``: the codec's
    position coding, ``codec.positions``)."""
    valid = model.anchor_valid()
    index = valid.nonzero()[:, 0]
    xyz = quantized_positions(model.xyz, valid, positions, model.position_box)[index]
    hard = (model.gaussian_mask(index).detach() > 0).float()
    values = entropy.quantize_for_coding(xyz, model.coded_values(index), hard)
    return CodedState(index=index, xyz=xyz, values=values)


def visible_anchors(model, cam: Camera) -> torch.Tensor:
    """[M] indices of the anchors that pass the prefilter for ``cam``."""
    with torch.no_grad():
        scales = torch.exp(model.per_anchor["scaling"].detach()[:, :3])
        vis = prefilter_anchors(model.positions().detach(), scales, cam)
    return vis.nonzero()[:, 0]


def render_view(model, cam: Camera, background: torch.Tensor, *, phase: str = "none",
                training: bool = False, entropy=None, rate_sample: float = 0.0,
                backend: str = "auto", generator: Optional[torch.Generator] = None,
                coded: Optional[CodedState] = None,
                decoder_quant: str = "noise") -> ViewResult:
    """Render one view.

    Args:
        model: AnchorModel.
        cam: the view (possibly rescaled by the progressive schedule).
        background: [3].
        phase: none | noise | adaptive | decoded.
        entropy: entropy model (needed for ``adaptive``).
        rate_sample: fraction of visible, valid anchors on which bits are estimated (training).
        coded: evaluation of the ``adaptive`` phase: the anchors as the codec stores them
            (:func:`coded_state`: 16-bit positions, values quantized over all coded anchors),
            prefiltered with those positions and scalings, as the decoded model is. Without
            it the visible anchors' values are quantized per view (the clamp's mean then
            taken over the visible ones) and the prefilter reads the raw positions and
            scalings.
        decoder_quant: in training, what the decoder sees in the ``noise`` and ``adaptive``
            phases: ``noise`` (HAC: x + U(-0.5, 0.5) Q) or ``ste`` (the rounded values of
            evaluation, straight-through gradient; the rate is still estimated with noise).
    """
    if phase == "adaptive" and not training and coded is not None:
        scales = coded.values["scaling"][:, :3]
        vis = prefilter_anchors(coded.xyz, scales, cam)
        idx = coded.index[vis]
        g = model.decode(cam.center, idx, {k: v[vis] for k, v in coded.values.items()},
                         xyz=coded.xyz[vis])
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam,
                        background=background, backend=backend)
        return ViewResult(render=out, gaussians=g, camera=cam)
    with stage("prefilter"):
        idx = visible_anchors(model, cam)
    if phase == "decoded" and getattr(model, "baked", None) is not None \
            and not torch.is_grad_enabled():
        g = model.baked.decode(cam.center, idx)          # the decoded model's baked form
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam,
                        background=background, backend=backend)
        return ViewResult(render=out, gaussians=g, camera=cam, bits={}, n_rate_anchors=0)
    values = model.coded_values(idx)
    xyz = model.positions(idx)           # kept by the model: not boxed again per view
    bits: dict = {}
    n_rate = 0
    valid_share = 1.0
    attrs = {a.name: a for a in model.coded_attributes()}
    if phase == "noise":
        if training and decoder_quant == "ste":
            values = {k: ste_round(v, attrs[k].q0, q0=attrs[k].q0) if attrs[k].noise_phase
                      else v for k, v in values.items()}
        elif training:
            values = {k: v + (uniform(v.shape, generator, v.device) - 0.5) * attrs[k].q0
                      if attrs[k].noise_phase else v for k, v in values.items()}
        else:
            values = {k: torch.round(v / attrs[k].q0) * attrs[k].q0 for k, v in values.items()}
    elif phase == "adaptive":
        if entropy is None:
            raise ValueError("the adaptive phase needs an entropy model")
        gmask = model.gaussian_mask(idx)
        if training:
            valid = (gmask.detach() > 0).any(dim=1)
            valid_share = float(valid.float().mean()) if len(idx) else 1.0
            choose = (uniform(len(idx), generator, idx.device) <= rate_sample) & valid
            with stage("context + rate"):
                values, bits = entropy(xyz, values, gmask, training=True, rate_rows=choose,
                                       decoder_quant=decoder_quant)
            n_rate = int(choose.sum())
        else:
            hard = (gmask.detach() > 0).float()
            values = entropy.quantize_for_coding(xyz, values, hard)
    elif phase not in ("none", "decoded"):
        raise ValueError(f"unknown phase '{phase}'")
    with stage("decode"):
        g = model.decode(cam.center, idx, values, xyz=xyz)
    backward_mark(g.means, "rasterize bwd")
    with stage("rasterize"):
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam,
                        background=background, backend=backend)
    backward_mark(out.image, "losses bwd")
    return ViewResult(render=out, gaussians=g, camera=cam, bits=bits, n_rate_anchors=n_rate,
                      valid_share=valid_share)
