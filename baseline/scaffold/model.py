"""The anchor model: per-anchor parameters, feature provider, decoder MLPs, neural Gaussians.

Per-anchor tensors live in one place (:class:`AnchorModel.per_anchor`) so that growing and
pruning keep every one of them, and its Adam moments, aligned: moments of new anchors start at
zero and rows of removed anchors are dropped. A feature provider adds its own per-anchor
tensors (the explicit feature table, a residual, ...) through :meth:`add_per_anchor`, with a rule
that initialises the rows of grown anchors.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from baseline.codec.rangecoder import box_positions
from baseline.contracts import BakeHead, CodedAttribute
from baseline.scaffold.gaussians import Gaussians, kept_gaussians
from baseline.timing import backward_mark, stage

# grow rule: (values of this tensor [N, ...], parent index of each new-anchor candidate [C],
#             inverse index candidate -> new anchor [C], number of new anchors) -> [n_new, ...]
GrowRule = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], torch.Tensor]


def grow_zeros(values, parent, inverse, n_new):
    return values.new_zeros((n_new,) + tuple(values.shape[1:]))


def grow_max_of_parents(values, parent, inverse, n_new):
    """Per new anchor, the element-wise max of its parents' rows (Scaffold-GS feature rule)."""
    src = values[parent].reshape(len(parent), math.prod(values.shape[1:]))   # [P, D], P may be 0
    out = src.new_full((n_new, src.shape[1]), float("-inf"))
    out = out.scatter_reduce(0, inverse[:, None].expand_as(src), src, reduce="amax")
    return out.reshape((n_new,) + tuple(values.shape[1:]))


class DecoderMLPs(nn.Module):
    """Scaffold-GS / HAC heads: input feat + view direction (3) + distance (1).

    opacity: Linear(in,h) ReLU Linear(h,K)  -> tanh applied by the caller
    cov:     Linear(in,h) ReLU Linear(h,7K) -> no activation
    color:   Linear(in,h) ReLU Linear(h,3K) -> sigmoid applied by the caller
    The heads return pre-activation values so that a refiner can add corrections before the
    activations (see :class:`Gaussians`).
    """

    def __init__(self, feat_dim: int, n_offsets: int, hidden: int, use_distance: bool = True):
        super().__init__()
        d_in = feat_dim + 3 + (1 if use_distance else 0)
        self.use_distance = use_distance
        self.n_offsets = n_offsets
        self.mlp_opacity = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, n_offsets))
        self.mlp_cov = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, 7 * n_offsets))
        self.mlp_color = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, 3 * n_offsets))

    def forward(self, feat: torch.Tensor, view_dir: torch.Tensor, dist: torch.Tensor):
        """feat [M,F], view_dir [M,3], dist [M,1] -> raw opacity [M,K], cov [M,K,7], color [M,K,3]."""
        parts = [feat, view_dir] + ([dist] if self.use_distance else [])
        x = torch.cat(parts, dim=-1)
        K = self.n_offsets
        return (self.mlp_opacity(x), self.mlp_cov(x).view(-1, K, 7), self.mlp_color(x).view(-1, K, 3))

    def bake_heads(self, feat: torch.Tensor) -> list:
        """The three heads for :class:`~baseline.scaffold.baked.BakedDecoder`; feat [N,F]."""
        d = self.use_distance
        return [BakeHead(feat, self.mlp_opacity, d, {"opacity": (0, 1)}),
                BakeHead(feat, self.mlp_cov, d, {"cov": (0, 7)}),
                BakeHead(feat, self.mlp_color, d, {"color": (0, 3)})]


class Heads(NamedTuple):
    """What :meth:`AnchorModel.raw_heads` returns for ``M`` visible anchors.

    ``raw_op`` [M,K], ``raw_cov`` [M,K,7], ``raw_col`` [M,K,3]: the heads' pre-activations, a
    refiner's pre-activation corrections included; ``post``: its corrections added after the
    activations (``{"opacity": [M,K], "color": [M,K,3]}``, any subset; empty without such a
    refiner). :meth:`opacity` and :meth:`colors` apply both.
    """

    values: dict
    xyz: torch.Tensor
    raw_op: torch.Tensor
    raw_cov: torch.Tensor
    raw_col: torch.Tensor
    post: dict

    def opacity(self) -> torch.Tensor:
        """[M,K] tanh opacity of every candidate (before the masks)."""
        op = torch.tanh(self.raw_op)
        return op + self.post["opacity"] if "opacity" in self.post else op

    def color_add(self, keep: torch.Tensor) -> Optional[torch.Tensor]:
        """[G,3] colour corrections after the sigmoid of the candidates ``keep`` [G] (indices
        into the M*K candidates), or None."""
        c = self.post.get("color")
        return None if c is None else c.reshape(-1, 3)[keep]

    def colors(self, keep: torch.Tensor, dtype: Optional[torch.dtype] = None) -> torch.Tensor:
        """[G,3] colours of the candidates ``keep`` [G], activated in ``dtype`` (default: as
        computed)."""
        raw = self.raw_col.reshape(-1, 3)[keep]
        col = torch.sigmoid(raw if dtype is None else raw.to(dtype))
        add = self.color_add(keep)
        return col if add is None else col + (add if dtype is None else add.to(dtype))


# the provider's own random stream: the run's seed + this (see AnchorModel.__init__)
PROVIDER_SEED_OFFSET = 0x5EED

class AnchorModel(nn.Module):
    """Anchors + feature provider + decoder (+ optional refiner).

    Per-anchor tensors (``per_anchor``): xyz [N,3] (frozen), offsets [N,K,3], scaling [N,6]
    (log), mask [N,K,1] (logits), plus whatever the provider adds (e.g. feat [N,50]).
    """

    def __init__(self, xyz: torch.Tensor, log_scaling: torch.Tensor, cfg_model, provider_factory,
                 refiner_factory=None, mask_threshold: float = 0.01):
        super().__init__()
        N = xyz.shape[0]
        K = cfg_model.n_offsets
        self.n_offsets = K
        self.cfg = cfg_model
        self.mask_threshold = mask_threshold
        self.fixed_values: Optional[dict[str, torch.Tensor]] = None
        # training only: masks multiply opacity and scale after the opacity > 0 selection
        # (HAC++) instead of the opacity before it (HAC); set by the mask-training strategy
        self.mask_after_selection = False
        self.baked = None           # BakedDecoder of a decoded model (bake()), used to render
        # the voxel lattice the anchors sit on (set by build_model, a checkpoint's restore or the
        # lattice position decoder; the lattice position coder needs it)
        self.voxel_size: Optional[float] = None
        # training with train.positions = "coded" and 16-bit position coding: the anchor box
        # (lo [3], hi [3], float32 numpy, HAC's widened bounds) whose 16-bit positions
        # training draws (positions()) and the encoder stores; None: the stored floats
        self.position_box: Optional[tuple] = None
        self._positions_cache: Optional[tuple] = None     # see _boxed_positions
        self.per_anchor = nn.ParameterDict()
        self.grow_rules: dict[str, Optional[GrowRule]] = {}
        self.add_per_anchor("xyz", xyz.float().clone(), None, trainable=False)
        self.add_per_anchor("offsets", torch.zeros(N, K, 3), grow_zeros)
        self.add_per_anchor("scaling", log_scaling.float().clone(), None)  # set by the grower
        self.add_per_anchor("mask", torch.ones(N, K, 1), None)            # init logit 1
        # the iteration each anchor was created at (0: initial; -1: unknown, a checkpoint
        # written before births were kept); never coded, read by the census (eval/census.py)
        self.iteration = 0          # set by the trainer before each step
        self.add_per_anchor("birth", torch.zeros(N), self._grow_birth, trainable=False)
        # The provider draws its initial values from a stream of its own (seeded from the run's
        # seed), so every method trained with one seed starts from the same decoder. The heads'
        # initial weights decide which of the K slots start opaque (features start at zero), a
        # lottery that training barely changes; a provider that draws random values (a grid,
        # an MLP) would otherwise shift the decoder's draw and with it the lottery (on truck,
        # seed 0: 42% against 70% kept at the start; docs/notes/predict-gs-gaussian-count.md).
        # The per-anchor provider draws nothing, so its decoder is the same either way.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed((torch.initial_seed() + PROVIDER_SEED_OFFSET) % (1 << 63))
            self.provider = provider_factory(self)
        self.decoder = DecoderMLPs(self.provider.feature_dim, K, cfg_model.hidden, cfg_model.use_distance)
        self.refiner = refiner_factory(self) if refiner_factory is not None else None

    def _apply(self, fn, *args, **kwargs):
        """``.to()`` / ``.cuda()`` / ``.cpu()`` also move a decoded model's fixed values."""
        super()._apply(fn, *args, **kwargs)
        if self.fixed_values is not None:
            self.fixed_values = {k: fn(v) for k, v in self.fixed_values.items()}
        if self.baked is not None:
            self.baked = self.baked.apply(fn)
        return self

    def bake(self) -> bool:
        """Precompute the view-independent part of Gaussian decoding of a decoded model
        (:mod:`baseline.scaffold.baked`); renders of the ``decoded`` phase then use it. A
        snapshot: call again after changing the model. False when the model cannot be baked
        (a refiner that does not declare its heads)."""
        from baseline.scaffold.baked import BakedDecoder

        self.baked = BakedDecoder.from_model(self)
        return self.baked is not None

    def unbake(self) -> None:
        self.baked = None

    def bake_if_faster(self) -> bool:
        """Bake a decoded model on CUDA, where baking is faster. On the CPU it can be faster
        too, but it is not the same frame: its first layers sum in another order, so an alpha
        within rounding of the rasterizer's 1/255 cut-off may be composited by one form and
        skipped by the other. A model decoded on the CPU stays plain, so its renders are the
        records' bit for bit (measurements: docs/RESULTS.md, "Speed (CPU)"; ``pgs bench fps``
        times both forms and prints their image difference).
        Returns whether the model is now baked."""
        if self.fixed_values is None or not self.xyz.is_cuda:
            self.baked = None
            return False
        return self.bake()

    # ------------------------------------------------------------------ per-anchor bookkeeping
    def _grow_birth(self, values, parent, inverse, n_new):
        return values.new_full((n_new,), float(self.iteration))

    def add_per_anchor(self, name: str, value: torch.Tensor, grow_rule: Optional[GrowRule],
                       trainable: bool = True) -> None:
        self.per_anchor[name] = nn.Parameter(value, requires_grad=trainable)
        self.grow_rules[name] = grow_rule

    @property
    def n_anchors(self) -> int:
        return self.per_anchor["xyz"].shape[0]

    @property
    def xyz(self) -> torch.Tensor:
        return self.per_anchor["xyz"]

    def positions(self, idx: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[M,3] the positions training draws anchors ``idx`` (all: None) at: with a
        :attr:`position_box`, the 16-bit positions the file will store (HAC's ``get_anchor``;
        the anchors never train, so no gradient is lost); else the stored floats."""
        if self.position_box is None:
            return self.xyz if idx is None else self.xyz[idx]
        full = self._boxed_positions()
        return full if idx is None else full[idx]

    def _boxed_positions(self) -> torch.Tensor:
        """[N,3] every anchor's 16-bit position, computed once per set of anchors and box.

        A step reads them for the prefilter, the decoder and the rate's sample; the anchors do
        not train, so the result only changes when the anchors (growth, pruning, a device move,
        an in-place write: the tensor's version counter) or the box change. Boxing is
        elementwise, so rows of the cached result equal boxing those rows alone, bit for bit.
        The result is shared: callers must not write into it."""
        xyz, box = self.xyz, self.position_box
        c = self._positions_cache
        if c is not None and c[0] is xyz and c[1] == xyz._version \
                and all(np.array_equal(a, b) for a, b in zip(c[2], box)):
            return c[3]
        out = box_positions(xyz.detach(), *box)
        self._positions_cache = (xyz, xyz._version, tuple(np.array(b, copy=True) for b in box), out)
        return out

    def coded_attributes(self) -> tuple[CodedAttribute, ...]:
        return tuple(self.provider.coded_attributes())

    def gaussian_mask(self, idx: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[M,K] binary mask (sigmoid(logit) > threshold) with a sigmoid straight-through grad."""
        logits = self.per_anchor["mask"] if idx is None else self.per_anchor["mask"][idx]
        s = torch.sigmoid(logits[..., 0])
        hard = (s > self.mask_threshold).float()
        if not torch.is_grad_enabled():   # exactly 0/1 (hard + s - s may be 1 -+ an ulp)
            return hard
        return hard + s - s.detach()

    def anchor_valid(self) -> torch.Tensor:
        """[N] bool: an anchor is valid (coded) if any of its K masks is on."""
        with torch.no_grad():
            return (torch.sigmoid(self.per_anchor["mask"][..., 0]) > self.mask_threshold).any(dim=1)

    def set_fixed_values(self, values: dict[str, torch.Tensor]) -> None:
        """Render ``values`` (name -> [N, dims], as the codec decodes them) as a decoded model
        does: the decoder reads them, and the per-anchor scaling and offsets, which the prefilter
        and the exports read, are set to match (scaling coded after exp, so its log here)."""
        n = values["scaling"].shape[0]
        self.per_anchor["scaling"].data = torch.log(values["scaling"].clamp_min(1e-30))
        self.per_anchor["offsets"].data = values["offsets"].view(n, self.n_offsets, 3).clone()
        self.fixed_values = values

    def coded_values(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """Values of every coded attribute for anchors ``idx`` [M]: name -> [M, dims].

        scaling is coded AFTER exp (docs/method.md section 3); offsets flattened to [M, 3K].
        """
        if self.fixed_values is not None:       # a decoded model: the values are the decoded ones
            return {k: v[idx] for k, v in self.fixed_values.items()}
        vals = dict(self.provider.coded_values(idx))
        vals["scaling"] = torch.exp(self.per_anchor["scaling"][idx])
        vals["offsets"] = self.per_anchor["offsets"][idx].flatten(1)   # [M, 3K], M may be 0
        return vals

    # ------------------------------------------------------------------------- decoding
    def raw_heads(self, cam_center: torch.Tensor, idx: torch.Tensor,
                  values: Optional[dict[str, torch.Tensor]] = None,
                  xyz: Optional[torch.Tensor] = None) -> Heads:
        """Pre-activation head outputs of anchors ``idx`` [M] (refiner corrections included:
        those the refiner adds after the activations in :attr:`Heads.post`)."""
        if values is None:
            values = self.coded_values(idx)
        if xyz is None:
            xyz = self.positions(idx)
        with stage("provider"):
            feat = self.provider.decoder_features(idx, values, xyz)
        backward_mark(feat, "decoder MLPs + refiner bwd")
        view_dir, dist = view_inputs(xyz, cam_center)
        with stage("decoder MLPs"):
            raw_op, raw_cov, raw_col = self.decoder(feat, view_dir, dist)
        post: dict[str, torch.Tensor] = {}
        if self.refiner is not None and self.refiner.active:
            with stage("refiner"):
                d = self.refiner(idx, values, view_dir, dist)
                # Corrections enter before the activations, except those the refiner adds to
                # the activated values (contracts.Refiner.post_activation).
                after = self.refiner.post_activation
                for name in ("opacity", "color"):
                    if name in after and name in d:
                        post[name] = d.pop(name)
                if "opacity" in d:
                    raw_op = raw_op + d["opacity"]
                if "cov" in d:
                    raw_cov = raw_cov + d["cov"]
                if "color" in d:
                    raw_col = raw_col + d["color"]
        for t in (raw_op, raw_cov, raw_col):
            backward_mark(t, "activations bwd")
        return Heads(values, xyz, raw_op, raw_cov, raw_col, post)

    def decode(self, cam_center: torch.Tensor, idx: torch.Tensor,
               values: Optional[dict[str, torch.Tensor]] = None,
               xyz: Optional[torch.Tensor] = None, visible: Optional[torch.Tensor] = None,
               opacity_floor: float = 0.0) -> Gaussians:
        """Neural Gaussians of anchors ``idx`` [M] seen from ``cam_center`` [3].

        Args:
            values: coded attribute values for ``idx`` (possibly quantized); default: raw values.
            xyz: [M,3] anchor positions to use (e.g. 16-bit quantized); default: stored ones.
            opacity_floor: keep Gaussians with (masked) opacity above this (Scaffold-GS: 0);
                the census's threshold sweep raises it.
        """
        h = self.raw_heads(cam_center, idx, values, xyz)
        values, xyz, raw_cov = h.values, h.xyz, h.raw_cov
        M, K = len(idx), self.n_offsets
        gmask = self.gaussian_mask(idx)                             # [M,K]
        after = self.mask_after_selection and torch.is_grad_enabled()
        # HAC: the mask multiplies the opacity before the selection (a masked Gaussian is not
        # drawn); HAC++ (training): it multiplies opacity and scale of the selected ones
        opacity = h.opacity() if after else h.opacity() * gmask    # [M,K]
        sel = (opacity > opacity_floor).reshape(-1)                 # [M*K]
        # The kept Gaussians are chosen first and only their attributes are activated: the
        # same per-element arithmetic as activating all M*K candidates and selecting after,
        # without the work on the ~70-80% that a trained model drops (masks off, opacity <= 0).
        keep = sel.nonzero()[:, 0]                                  # [G] into the M*K candidates
        row = torch.div(keep, K, rounding_mode="floor")             # [G] visible-anchor row
        scaling = values["scaling"][row]                            # [G,6] activated
        offsets = values["offsets"].reshape(M * K, 3)[keep] * scaling[:, :3]
        means = xyz[row] + offsets
        opacities, scales_base = opacity.reshape(-1)[keep], scaling[:, 3:]
        if after:
            gk = gmask.reshape(-1)[keep]
            opacities, scales_base = opacities * gk, scales_base * gk[:, None]
        return kept_gaussians(means=means, cov=raw_cov.reshape(M * K, 7)[keep],
                              raw_color=h.raw_col.reshape(M * K, 3)[keep],
                              color_add=h.color_add(keep),
                              opacities=opacities, scales_base=scales_base,
                              anchor_index=idx[row], selection=sel, opacity_all=opacity,
                              idx=idx, n_anchors=self.n_anchors, visible=visible)

    # ------------------------------------------------------------------- growing / pruning
    def append_anchors(self, new_xyz: torch.Tensor, new_log_scaling: torch.Tensor,
                       parent: torch.Tensor, inverse: torch.Tensor, optimizer=None) -> None:
        """Add anchors. ``parent`` [C] / ``inverse`` [C] map candidate Gaussians to the new anchors."""
        n_new = new_xyz.shape[0]
        if n_new == 0:
            return
        K = self.n_offsets
        explicit = {
            "xyz": new_xyz.float(),
            "scaling": new_log_scaling.float(),
            "mask": torch.ones(n_new, K, 1),
        }
        for name, p in self.per_anchor.items():
            if name in explicit:
                rows = explicit[name].to(p)
            else:
                rows = self.grow_rules[name](p.detach(), parent, inverse, n_new).to(p)
            _replace_param(self.per_anchor, name, torch.cat([p.detach(), rows], 0), optimizer,
                           n_append=n_new)

    def keep_anchors(self, keep: torch.Tensor, optimizer=None) -> None:
        """Keep only anchors where ``keep`` [N] is True (prune the rest)."""
        for name, p in list(self.per_anchor.items()):
            _replace_param(self.per_anchor, name, p.detach()[keep], optimizer, keep=keep)


def view_inputs(xyz: torch.Tensor, cam_center: torch.Tensor):
    """The heads' view inputs of anchors at ``xyz`` [M,3] seen from ``cam_center`` [3]:
    ``(view_dir [M,3] unit, dist [M,1])``."""
    view = xyz - cam_center.to(xyz)[None, :]
    dist = view.norm(dim=1, keepdim=True).clamp_min(1e-8)
    return view / dist, dist


def decode_all_then_select(model: AnchorModel, cam_center: torch.Tensor, idx: torch.Tensor,
                           values: Optional[dict[str, torch.Tensor]] = None,
                           xyz: Optional[torch.Tensor] = None) -> dict[str, torch.Tensor]:
    """Reference form of :meth:`AnchorModel.decode`'s last step, in Scaffold-GS's own order:
    activate all M*K candidate Gaussians, then keep those with masked opacity > 0.

    Returns the kept Gaussians' ``means, quats, scales, opacities, colors, anchor_index``.
    ``decode`` keeps first and activates only the kept ones; tests and ``pgs bench frame``
    compare the two.
    """
    h = model.raw_heads(cam_center, idx, values, xyz)
    values, xyz, raw_cov = h.values, h.xyz, h.raw_cov
    M, K = len(idx), model.n_offsets
    opacity = h.opacity() * model.gaussian_mask(idx)
    sel = (opacity > 0).reshape(-1)
    scaling = values["scaling"]
    offsets = values["offsets"].view(M, K, 3) * scaling[:, None, :3]
    means = (xyz[:, None, :] + offsets).reshape(-1, 3)
    scales = (scaling[:, None, 3:] * torch.sigmoid(raw_cov[..., :3])).reshape(-1, 3)
    quats = F.normalize(raw_cov[..., 3:7].reshape(-1, 4), dim=-1)
    colors = h.colors(torch.arange(M * K, device=idx.device))
    anchor_index = idx[:, None].expand(M, K).reshape(-1)
    return dict(means=means[sel], quats=quats[sel], scales=scales[sel],
                opacities=opacity.reshape(-1)[sel], colors=colors[sel],
                anchor_index=anchor_index[sel])


def _replace_param(pdict: nn.ParameterDict, name: str, new_value: torch.Tensor, optimizer,
                   keep: Optional[torch.Tensor] = None, n_append: int = 0) -> None:
    """Swap a per-anchor parameter for a resized one, carrying its Adam moments along."""
    old = pdict[name]
    new = nn.Parameter(new_value.contiguous(), requires_grad=old.requires_grad)
    if optimizer is not None:
        for group in optimizer.param_groups:
            for i, q in enumerate(group["params"]):
                if q is old:
                    state = optimizer.state.pop(old, None)
                    if state:
                        for k in ("exp_avg", "exp_avg_sq"):
                            if k in state:
                                s = state[k]
                                if keep is not None:
                                    s = s[keep]
                                if n_append:
                                    s = torch.cat([s, s.new_zeros((n_append,) + tuple(s.shape[1:]))], 0)
                                state[k] = s.contiguous()
                        optimizer.state[new] = state
                    group["params"][i] = new
    pdict[name] = new


# ------------------------------------------------------------------------- bounds
# Anchors, Gaussian scales and offsets must lie within this multiple of the scene extent (1.1 x
# the largest distance of a training camera from their mean): SfM points of unbounded scenes
# reach tens of extents; an anchor at 1e4 extents would already leave HAC's 16-bit positions a
# step of a third of the scene, so anything beyond is damage, not content.
SCENE_EXTENT_MULTIPLE = 1e4


def check_bounds(model: AnchorModel, where: str, center: torch.Tensor | None = None,
                 extent: float | None = None) -> None:
    """Refuse (``ValueError``, one line with the count and the worst value) a model whose
    anchor positions, activated scales (``exp`` of the log-scales, or a decoded model's values)
    or offsets (times their scale) are non-finite, or, given the scene's ``center`` [3] and
    ``extent``, farther than :data:`SCENE_EXTENT_MULTIPLE` x ``extent`` (positions from
    ``center``, per coordinate). float32, as the model renders them; no per-anchor loop."""
    n = model.n_anchors
    if n == 0:
        return
    with torch.no_grad():
        xyz = model.xyz.detach().float().cpu()                              # [N, 3]
        vals = model.coded_values(torch.arange(n, device=model.xyz.device))
        scale = vals["scaling"].detach().float().cpu()                      # [N, 6]
        off = vals["offsets"].detach().float().cpu().view(n, -1, 3) * scale[:, None, :3]
        c = torch.zeros(3) if center is None else torch.as_tensor(center).float().cpu()
        checks = (("anchor positions", "from the cameras' centre", (xyz - c).abs().amax(1)),
                  ("Gaussian scales", "", scale.abs().amax(1)),
                  ("Gaussian offsets", "from their anchor", off.abs().flatten(1).amax(1)))
    lim = None if extent is None else SCENE_EXTENT_MULTIPLE * float(extent)
    for what, rel, d in checks:
        bad = ~torch.isfinite(d)
        if lim is not None:
            bad |= d > lim
        if bad.any():
            worst = float(d[bad].max()) if torch.isfinite(d[bad]).all() else float("inf")
            bound = ("non-finite" if lim is None else
                     f"non-finite or beyond {SCENE_EXTENT_MULTIPLE:g} x the scene extent "
                     f"{float(extent):.4g} ({lim:.4g}){' ' + rel if rel else ''}")
            raise ValueError(f"{where}: {int(bad.sum())} of {n} anchors have {what} {bound}; "
                             f"the worst is {worst:.4g} (a damaged or foreign model)")
