"""HAC's quantization phases as a training hook (SPEC.md section 3).

it <= noise_from: no quantization; noise_from < it <= context_from: U(-0.5,0.5) * Q0 noise;
at context_from the anchor bounds are recomputed; after it the context model is on (adaptive
steps, rate and mask losses). Milestones scale with ``train.iterations`` like every other.
"""
from __future__ import annotations

from baseline import registry


def phase_at(it: int, noise_from: int, context_from: int) -> str:
    if it <= noise_from:
        return "none"
    if it <= context_from:
        return "noise"
    return "adaptive"


class HACPhases:
    name = "hac_phases"

    def __init__(self, trainer):
        self.t = trainer
        at = trainer.cfg.train.at
        self.noise_from = at(trainer.cfg.entropy.noise_from)
        self.context_from = at(trainer.cfg.entropy.context_from)

    def before_step(self, it: int) -> None:
        ph = phase_at(it, self.noise_from, self.context_from)
        if ph == "adaptive" and self.t.phase != "adaptive":
            ent = self.t.entropy
            if hasattr(ent, "set_bounds"):     # context models normalise by the anchor box
                xyz = self.t.model.xyz.detach()
                ent.set_bounds(xyz.min(0).values, xyz.max(0).values)
        self.t.phase = ph


registry.register("hooks", "hac_phases", HACPhases)
