"""Anchor growing and pruning (Scaffold-GS, with HAC's schedule), as a training hook set.

Choices where the reference code has quirks (each is a config flag and is tested):
  * Level skip: the reference stops trying levels 1-2 of a growing step when level 0 added no
    anchor. We try every level by default (``densify.reference_level_skip = false``): a level-0
    miss says nothing about coarser cells, and skipping them only slows growth on sparse scenes.
  * Scaling clamp on prune: the reference clamps the last three log-scales of every anchor to
    <= 0.05 whenever it adjusts anchors. We keep it (``densify.prune_clamp_log_scaling = 0.05``;
    a negative value turns it off): it only bounds Gaussians larger than ~1 scene unit.
  * Growth statistics are gradients w.r.t. NDC coordinates (as the reference's
    ``viewspace_points``): the rasterizer reports pixel-space gradients, multiplied here by W/2
    and H/2.
"""
from __future__ import annotations

import torch

from baseline import registry
from baseline.contracts import TrainingHook
from baseline.device import uniform


MIN_INTERVAL = 10


def _unique_rows(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.unique(a, dim=0, return_inverse=True)`` for integer rows ``a`` [C, D].

    Same result (unique rows in lexicographic order, inverse [C]), computed on one packed int64
    key per row: torch's ``dim=0`` path sorts whole rows and was the largest single cost of a
    growing step on truck (the 1-D sort of packed keys is several times faster). Each column is
    offset by its minimum and given ``63 // D`` bits, most significant first, so the order of the
    keys is the lexicographic order of the rows; spans that do not fit fall back to torch.
    """
    C, D = a.shape
    if C == 0 or D == 0:
        return torch.unique(a, dim=0, return_inverse=True)
    bits = 63 // D
    lo = a.min(0).values
    b = a - lo
    if int(b.max()) >= (1 << bits):
        return torch.unique(a, dim=0, return_inverse=True)
    key = b[:, 0].clone()
    for d in range(1, D):
        key = (key << bits) | b[:, d]
    uk, inv = torch.unique(key, sorted=True, return_inverse=True)
    mask = (1 << bits) - 1
    rows = torch.stack([(uk >> (bits * (D - 1 - d))) & mask for d in range(D)], 1)
    return rows + lo, inv


def grow_anchors(model, grads: torch.Tensor, eligible: torch.Tensor, cfg, voxel_size: float,
                 optimizer=None, generator: torch.Generator | None = None, rand=None) -> int:
    """One Scaffold-GS growing step.

    Args:
        grads: [N*K] mean NDC gradient norm per neural Gaussian.
        eligible: [N*K] bool, Gaussians with enough statistics (count > interval * st * 0.5).
        rand: optional ``rand(n) -> [n]`` uniform draws (tests pass a fixed one).
    Returns:
        number of anchors added.
    """
    K = model.n_offsets
    N0 = model.n_anchors
    with torch.no_grad():
        xyz0 = model.positions().detach()     # HAC's get_anchor: the 16-bit positions
        scaling = torch.exp(model.per_anchor["scaling"].detach())
        offsets = model.per_anchor["offsets"].detach()
        all_xyz = (xyz0[:, None, :] + offsets * scaling[:, None, :3]).reshape(-1, 3)
    added = 0
    m = cfg.model
    for level in range(m.update_depth):
        thr = cfg.densify.grad_threshold * float((m.update_hierarchy_factor // 2) ** level)
        cand = (grads >= thr) & eligible
        keep_p = 0.5 ** (level + 1)
        u = (rand(N0 * K) if rand is not None else uniform(N0 * K, generator, grads.device)).to(grads.device)
        cand = cand & (u > keep_p)
        factor = m.update_init_factor // (m.update_hierarchy_factor ** level)
        size = voxel_size * factor
        if size <= 0:
            continue
        n_new = 0
        if cand.any():
            sel = cand.nonzero()[:, 0]
            cells = torch.round(all_xyz[sel].double() / size).long()          # [C,3]
            uniq, inverse = _unique_rows(cells)                                # [U,3], [C]
            # the stored (lattice) positions: HAC reads its floored 16-bit ones, which put an
            # anchor on a cell boundary in the lower cell (docs/deviations.md)
            existing = torch.round(model.xyz.detach().double() / size).long()   # [N,3], repeats ok
            both, inv_both = _unique_rows(torch.cat([existing, uniq], 0))
            occupied = torch.zeros(len(both), dtype=torch.bool, device=both.device)
            occupied[inv_both[: len(existing)]] = True
            free = ~occupied[inv_both[len(existing):]]                         # [U]
            if free.any():
                remap = torch.full((len(uniq),), -1, dtype=torch.long, device=uniq.device)
                remap[free] = torch.arange(int(free.sum()), device=uniq.device)
                new_inv = remap[inverse]
                ok = new_inv >= 0
                parent = sel[ok] // K
                # on the voxel lattice, the expression of anchors.voxelize and of the lattice
                # position coder (the same bits as uniq * size for power-of-two factors)
                new_xyz = ((uniq[free] * factor).double() * voxel_size).float()
                n_new = len(new_xyz)
                new_scaling = torch.full((n_new, 6), float(torch.log(torch.tensor(size))),
                                         device=new_xyz.device)
                model.append_anchors(new_xyz, new_scaling, parent, new_inv[ok], optimizer)
        added += n_new
        if n_new == 0 and level == 0 and cfg.densify.reference_level_skip:
            break
    return added


class TrainingCollapsed(ValueError):
    """Every anchor was about to be pruned: no Gaussian kept an opacity above zero in the views
    that saw it, so nothing would receive a gradient again. Training stops; the last
    checkpoint is kept."""


class ScaffoldDensify(TrainingHook):
    """Growing statistics after backward, grow + prune every ``update_interval`` iterations."""

    name = "scaffold_densify"

    def __init__(self, trainer):
        self.t = trainer
        cfg = trainer.cfg
        at = cfg.train.at
        d = cfg.densify
        self.stat_from = at(d.stat_from)
        self.update_from = at(d.update_from)
        self.update_until = at(d.update_until)
        # Scaled with the run like every milestone, but never below MIN_INTERVAL iterations: the
        # visibility counts that gate growing (> interval*st/2) and pruning (> interval*st) need
        # a few views to mean anything.
        self.interval = max(MIN_INTERVAL, at(d.update_interval))
        self.skip = (at(d.skip_from), at(d.skip_until))
        self.grow_count = self.interval * d.success_threshold * 0.5
        self.prune_count = self.interval * d.success_threshold
        self.reset(trainer.model.n_anchors, trainer.model.n_offsets)
        # anchors added and removed since the start of training (the log's "grown" / "pruned":
        # what a net anchor count cannot tell apart)
        self.grown = 0
        self.pruned = 0

    def reset(self, N, K):
        dev = self.t.model.xyz.device
        self.opacity_accum = torch.zeros(N, device=dev)
        self.anchor_demon = torch.zeros(N, device=dev)
        self.grad_accum = torch.zeros(N * K, device=dev)
        self.grad_denom = torch.zeros(N * K, device=dev)

    _STATS = ("opacity_accum", "anchor_demon", "grad_accum", "grad_denom")
    _COUNTS = ("grown", "pruned")

    def state_dict(self):
        return ({k: getattr(self, k) for k in self._STATS}
                | {k: torch.tensor(getattr(self, k)) for k in self._COUNTS})

    def load_state_dict(self, s):
        dev = self.t.model.xyz.device
        for k in self._STATS:
            setattr(self, k, s[k].to(dev, copy=True))
        for k in self._COUNTS:   # checkpoints written before the counts were kept: 0
            setattr(self, k, int(s[k]) if k in s else 0)

    def log_fields(self) -> dict[str, int | float]:
        return {k: getattr(self, k) for k in self._COUNTS}

    # -------------------------------------------------------------------------------- hooks
    def after_backward(self, it: int, ctx) -> None:
        if not (self.stat_from < it < self.update_until):
            return
        if self.t.cfg.densify.reference_skip_update and self.adjusts(it):
            # The reference's order: it grows and prunes before its optimizer step, replacing
            # every per-anchor parameter by a new tensor without a gradient, so at each
            # adjustment Adam leaves the anchors' values (and moments) as they are and updates
            # only the networks. Dropping their gradients here, before this step, does the same.
            for p in self.t.model.per_anchor.values():
                p.grad = None
        g, out, cam = ctx["gaussians"], ctx["render"], ctx["camera"]
        K = self.t.model.n_offsets
        with torch.no_grad():
            vis = g.visible
            op = g.opacity_all.detach().clamp_min(0).sum(dim=1)
            self.opacity_accum[vis] += op
            self.anchor_demon[vis] += 1
            if out.means2d.grad is None:
                return
            grad = out.means2d.grad
            gn = torch.sqrt((grad[:, 0] * cam.width * 0.5) ** 2 + (grad[:, 1] * cam.height * 0.5) ** 2)
            vis_idx = vis.nonzero()[:, 0]
            flat = (vis_idx[:, None] * K + torch.arange(K, device=vis_idx.device)[None, :]).reshape(-1)  # [M*K]
            kept = flat[g.selection]                                             # [G]
            upd = out.radii > 0
            self.grad_accum.index_add_(0, kept[upd], gn[upd])
            self.grad_denom.index_add_(0, kept[upd], torch.ones(int(upd.sum()), device=gn.device))

    def adjusts(self, it: int) -> bool:
        """Whether iteration ``it`` grows and prunes (after its optimizer step)."""
        return (it % self.interval == 0 and self.update_from < it < self.update_until
                and not self.skip[0] <= it < self.skip[1])

    def after_step(self, it: int) -> None:
        if it % self.interval != 0:
            return
        if it >= self.update_until and self.t.cfg.densify.clamp_scaling_to_end:
            self.clamp_scaling()
            return
        if self.adjusts(it):
            self.adjust(it)

    def clamp_scaling(self) -> None:
        """The reference's clamp of the scale multipliers: log-scaling[:, 3:] <= c (c < 0: off)."""
        c = self.t.cfg.densify.prune_clamp_log_scaling
        if c >= 0:
            with torch.no_grad():
                s = self.t.model.per_anchor["scaling"]
                s[:, 3:] = s[:, 3:].clamp(max=c)

    def adjust(self, it: int = 0) -> None:
        """Grow, then prune (at iteration ``it``, named in errors)."""
        t = self.t
        model = t.model
        K = model.n_offsets
        cfg = t.cfg
        N0 = model.n_anchors
        grads = self.grad_accum / self.grad_denom.clamp_min(1)
        eligible = self.grad_denom > self.grow_count
        grads = torch.where(eligible, grads, torch.zeros_like(grads))
        added = grow_anchors(model, grads, eligible, cfg, t.voxel_size, t.optimizer, t.generator)
        # reset statistics of the Gaussians that were eligible; zero stats for new anchors
        self.grad_denom[eligible] = 0
        self.grad_accum[eligible] = 0
        dev = self.grad_accum.device
        pad = torch.zeros(added * K, device=dev)
        self.grad_denom = torch.cat([self.grad_denom, pad])
        self.grad_accum = torch.cat([self.grad_accum, pad])
        prune = (self.opacity_accum < cfg.densify.min_opacity * self.anchor_demon)
        counted = self.anchor_demon > self.prune_count
        prune = prune & counted
        self.opacity_accum[counted] = 0
        self.anchor_demon[counted] = 0
        self.opacity_accum = torch.cat([self.opacity_accum, torch.zeros(added, device=dev)])
        self.anchor_demon = torch.cat([self.anchor_demon, torch.zeros(added, device=dev)])
        prune = torch.cat([prune, torch.zeros(added, dtype=torch.bool, device=dev)])
        n_pruned = int(prune.sum())
        if n_pruned and n_pruned == model.n_anchors:
            # an empty model is an absorbing state (no Gaussian, no gradient): say so here,
            # not with a shape error in the next render
            raise TrainingCollapsed(
                f"training collapsed at iteration {it}: every anchor "
                f"({n_pruned}) would be pruned, as no Gaussian of any anchor kept an opacity "
                f"above zero in the views that saw it; the last checkpoint is kept")
        if n_pruned:
            keep = ~prune
            model.keep_anchors(keep, t.optimizer)
            self.opacity_accum = self.opacity_accum[keep]
            self.anchor_demon = self.anchor_demon[keep]
            keepk = keep[:, None].expand(-1, K).reshape(-1)
            self.grad_accum = self.grad_accum[keepk]
            self.grad_denom = self.grad_denom[keepk]
        self.clamp_scaling()
        self.grown += added
        self.pruned += n_pruned
        t.on_anchors_changed(N0, model.n_anchors)


registry.register("hooks", "scaffold_densify", ScaffoldDensify)
