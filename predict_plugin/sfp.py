"""Spatial Feature Pool (paper section 3.2, appendix A.2): feature provider ``sfp``.

f_c = F(I(H_xyz, H_xy, H_xz, H_yz; x)): the anchor position queries a binarized hash grid with
HAC's layout (its own instance), the concatenated level features go through a two-layer fusion
MLP to the 50-dim predicted feature that replaces the per-anchor feature as input of the
unchanged decoder MLPs. Each anchor also carries a residual f_r (25 dims; a grown anchor's starts at
zero, or with ``predict.residual_grow = "parent"`` at its parents' max as HAC grows features)
that the MGRD refiner decodes; the entropy model codes f_r instead of the feature.

Choices (documented): the SFP normalisation box is fixed at start from the initial anchors,
widened by 10% of the extent per side, so that grown anchors still fall inside and the learned
field is never re-indexed (a point outside reads zero features, as HAC's grid). With
``predict.box = "contract"`` the box is the anchors' inner quantiles instead and the space
outside it is contracted into the grid's outer shell (`baseline.hac.hashgrid.contract_unit`):
on captures whose SfM points reach far beyond the object (truck: 255 x 45 x 159 units for all
anchors, 39 x 10 x 51 for the inner 98%) the extent box leaves the finest levels far coarser
than the anchor spacing where most anchors are. The fusion hidden
width (``predict.fusion_hidden``) is not given by the paper.

Decoded models cache f_c for every anchor (:meth:`SpatialFeaturePool.build_cache`): it depends
on the anchor position only, so rendering skips the grid query and the fusion MLP.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Optional, cast

import torch
import torch.nn as nn

from baseline.codec.fields import dict_field, unknown_keys
from baseline.contracts import CodedAttribute, FeatureProvider
from baseline.hac.hashgrid import BinaryHashGrid
from baseline.hac.layout import check_grid_options, grid_options
from baseline.scaffold.model import grow_max_of_parents, grow_zeros

# predict.residual_grow -> the grow rule of the residual (baseline.scaffold.model.GrowRule)
RESIDUAL_GROW_RULES = {"zero": grow_zeros, "parent": grow_max_of_parents}


def _layout_from_json(layout: dict) -> dict:
    return {k: tuple(int(x) for x in v) if isinstance(v, (list, tuple)) else int(v)
            for k, v in layout.items()}


class SpatialFeaturePool(FeatureProvider):
    # what its bitstream sections hold (pgs info / reports: "sfp.grid", "sfp.fusion")
    SECTION_LABELS = {"grid": "grid", "weights": "fusion"}
    # its training-semantics version (baseline.config.component_semantics): 4 = its tables
    # start at one shared code and the fusion MLP at PyTorch's init (predict.grid_init =
    # "shared", predict.fusion_init = "default"); 3 = its initial
    # values come from a random stream of its own, so the decoder starts as HAC's with the same
    # seed (baseline.scaffold.model); 2 = the fusion MLP's last layer starts at zero
    # (predict.fusion_init = "zero"); 1 = PyTorch's default init
    TRAINING_SEMANTICS = 4
    caches_features = True          # f_c depends on the anchor position only

    def __init__(self, model, cfg, codec_state: Optional[dict] = None):
        """``codec_state``: what :meth:`codec_state` returned when the file was written (the
        decoder passes it back). It fixes the grid layout: with ``predict.grid_auto`` the layout
        was sized from the anchor count *at the start of training*, which the decoded model
        (after growing and pruning) no longer has."""
        super().__init__()
        p = cfg.ext["predict"]
        self.pcfg = p
        self.feature_dim = cfg.model.feat_dim
        self.n_offsets = cfg.model.n_offsets
        self._model = [model]
        if codec_state is not None:
            try:
                self.grid_layout = _layout_from_json(codec_state["grid"])
            except (KeyError, TypeError, ValueError, AttributeError) as e:
                raise ValueError(f"bad Spatial Feature Pool state {codec_state!r}: {e}") from None
        else:       # the SFP is its own grid: the entropy grid's `auto` does not size it
            self.grid_layout = grid_options(replace(cfg.entropy.grid, auto=p.grid_auto),
                                            model.n_anchors)
        self.grid = BinaryHashGrid(**self.grid_layout)
        if p.grid_init == "shared":      # one code for every anchor at the start
            self.grid.reset_parameters(shared=True)
        elif p.grid_init != "random":
            raise ValueError(f"predict.grid_init must be 'shared' or 'random', got '{p.grid_init}'")
        xyz = model.xyz.detach()
        if p.box == "extent":
            lo, hi = xyz.min(0).values, xyz.max(0).values
        elif p.box == "contract":
            q = torch.tensor([p.box_quantile, 1.0 - p.box_quantile], dtype=torch.float64)
            lo, hi = torch.quantile(xyz.double(), q, dim=0).float()
        else:
            raise ValueError(f"predict.box must be 'extent' or 'contract', got '{p.box}'")
        margin = 0.1 * (hi - lo).clamp_min(1e-6)
        self.grid.set_bounds(lo - margin, hi + margin)      # the file keeps these bounds
        self.grid.contract = p.box == "contract"      # from the config, at decode too
        self.fusion = nn.Sequential(nn.Linear(self.grid.output_dim, p.fusion_hidden), nn.ReLU(),
                                    nn.Linear(p.fusion_hidden, self.feature_dim))
        if p.fusion_init == "zero":
            out = cast(nn.Linear, self.fusion[2])
            nn.init.zeros_(out.weight)
            nn.init.zeros_(out.bias)
        elif p.fusion_init != "default":
            raise ValueError(f"predict.fusion_init must be 'default' or 'zero', got '{p.fusion_init}'")
        self.use_residual = bool(p.residual) and p.residual_dim > 0
        if p.residual_grow not in RESIDUAL_GROW_RULES:
            raise ValueError(f"predict.residual_grow must be one of {sorted(RESIDUAL_GROW_RULES)}, "
                             f"got '{p.residual_grow}'")
        if p.residual_noise not in ("always", "rate"):
            raise ValueError(f"predict.residual_noise must be 'always' or 'rate', got "
                             f"'{p.residual_noise}'")
        if self.use_residual:
            model.add_per_anchor("residual", torch.zeros(model.n_anchors, p.residual_dim),
                                 RESIDUAL_GROW_RULES[p.residual_grow])
        self._cache: Optional[torch.Tensor] = None

    # ------------------------------------------------------------------- provider contract
    def codec_state(self) -> dict:
        """JSON-able construction state the decoder needs besides the config (the file header
        keeps it): the resolved grid layout (tuples become JSON lists)."""
        return {"grid": dict(self.grid_layout)}

    @classmethod
    def check_codec_state(cls, state, key: str) -> int:
        """A header's state of the SFP: its grid layout; returns the grid's table entries."""
        state = dict_field(state, key)
        unknown_keys(state, ("grid",), key, "entry")
        return check_grid_options(state["grid"], f"{key}.grid") if "grid" in state else 0

    def coded_attributes(self):
        attrs = []
        if self.use_residual:
            attrs.append(CodedAttribute("residual", self.pcfg.residual_dim, 1.0,
                                        noise_phase=self.pcfg.residual_noise == "always"))
        attrs += [CodedAttribute("scaling", 6, 0.001),
                  CodedAttribute("offsets", 3 * self.n_offsets, 0.2, masked=True)]
        return tuple(attrs)

    def coded_values(self, idx):
        if not self.use_residual:
            return {}
        return {"residual": self._model[0].per_anchor["residual"][idx]}

    def predict(self, xyz: torch.Tensor) -> torch.Tensor:
        """[M,3] positions -> [M, 50] predicted features f_c."""
        return self.fusion(self.grid.shared_query(xyz))

    def decoder_features(self, idx, values, xyz):
        if self._cache is not None:
            return self._cache[idx]
        return self.predict(xyz)

    @torch.no_grad()
    def build_cache(self, xyz_all: torch.Tensor) -> None:
        """Precompute f_c of every anchor (decoded models: positions are fixed)."""
        self._cache = self.predict(xyz_all)

    def clear_cache(self) -> None:
        self._cache = None

    def _apply(self, fn, *args, **kwargs):
        """``.to()`` / ``.cuda()`` / ``.cpu()`` move the f_c cache with the parameters."""
        super()._apply(fn, *args, **kwargs)
        if self._cache is not None:
            self._cache = fn(self._cache)
        return self

    def context_grid(self) -> BinaryHashGrid:
        """Its grid, which HAC's entropy model may read as its context
        (``entropy.context = "provider"``, patch ``sfp-context``)."""
        return self.grid

    def rate_bits(self) -> torch.Tensor:
        """The SFP's hash bits, added to the rate loss (paper eq. 8: L_entropy includes the SFP)."""
        return self.grid.hash_bits()

    def param_groups(self, cfg):
        p = cfg.ext["predict"]
        groups = [dict(name="sfp_grid", params=list(self.grid.parameters()),
                       lr_init=p.lr_grid_init, lr_final=p.lr_grid_final),
                  dict(name="sfp_fusion", params=list(self.fusion.parameters()),
                       lr_init=p.lr_fusion_init, lr_final=p.lr_fusion_final)]
        if self.use_residual:
            groups.append(dict(name="residual", params=[self._model[0].per_anchor["residual"]],
                               lr_init=p.lr_residual, lr_final=p.lr_residual))
        return groups
