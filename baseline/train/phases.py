"""HAC's quantization phases as a training hook (docs/method.md section 3).

it <= noise_from: no quantization; noise_from < it <= context_from: U(-0.5,0.5) * Q0 noise;
at context_from the anchor bounds are recomputed; after it the context model is on (adaptive
steps, rate and mask losses). Milestones scale with ``train.iterations`` like every other.

With ``train.positions = "coded"`` and 16-bit position coding, training draws the anchors at
the 16-bit positions of the same box (HAC's ``get_anchor``): taken from the initial anchors at
the first step (HAC's ``update_anchor_bound`` after the scene is built) and again with the
context's, after which it is the box the encoder stores, so the decoder draws every anchor where
training did. (Trained at the floats, truck's decoded files lost 0.065-0.079 dB to a shift of
up to 0.27 voxels.) HAC floors to its 16-bit levels; this toolkit's codec rounds to the nearest
(half the worst error at the same cost), and training quantizes as the codec does.

The context grid's normalisation box is HAC's ``update_anchor_bound``: the anchors' per-axis
min/max widened outward (x1.2 away from 0, x0.8 toward it; the same widening as the codec's
16-bit positions), taken at the start of iteration ``context_from``, before that iteration's
growing, as HAC does at step 10000. Anchors grown later (until ``update_until``) then still fall
inside the box and read context features (outside it the grid reads zeros).
"""
from __future__ import annotations

import numpy as np
import torch

from baseline import registry
from baseline.codec.rangecoder import anchor_bounds
from baseline.contracts import TrainingHook


def phase_at(it: int, noise_from: int, context_from: int) -> str:
    if it <= noise_from:
        return "none"
    if it <= context_from:
        return "noise"
    return "adaptive"


class HACPhases(TrainingHook):
    name = "hac_phases"

    def __init__(self, trainer):
        self.t = trainer
        at = trainer.cfg.train.at
        self.noise_from = at(trainer.cfg.entropy.noise_from)
        self.context_from = at(trainer.cfg.entropy.context_from)
        self.coded_positions = (trainer.cfg.train.positions == "coded"
                                and trainer.cfg.codec.positions != "lattice")

    def before_step(self, it: int) -> None:
        ph = phase_at(it, self.noise_from, self.context_from)
        if it == 1 and self.coded_positions:
            self.t.model.position_box = anchor_bounds(self.t.model.xyz.detach().cpu().numpy())
        # HAC's moment (step 10000, before its growing), or the first step when the context is
        # on from the start (context_from 0)
        if it == max(self.context_from, 1):
            # context models normalise by the anchor box (others ignore it)
            lo, hi = anchor_bounds(self.t.model.xyz.detach().cpu().numpy())
            self.t.entropy.set_bounds(torch.from_numpy(lo), torch.from_numpy(hi))
            if self.coded_positions:
                self.t.model.position_box = (lo, hi)
        self.t.phase = ph

    def state_dict(self):
        box = self.t.model.position_box
        return None if box is None else {"position_box": [b.tolist() for b in box]}

    def load_state_dict(self, state: dict) -> None:
        box = state.get("position_box")
        if box is not None:
            self.t.model.position_box = tuple(np.asarray(b, dtype=np.float32) for b in box)


registry.register("hooks", "hac_phases", HACPhases)
