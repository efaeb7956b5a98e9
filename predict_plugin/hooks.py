"""Prediction-tailored progressive training (paper section 3.3) as a training hook set.

Stage 1 (it <= residual_from): SFP only, residual branch off. Stage 2: MGRD + residual on.
The training view is rendered at the scaled intrinsics and the ground truth bilinearly resized
by the schedule's factor (the trainer does both from ``trainer.render_scale``). Milestones (T,
the stage switch) scale with ``train.iterations`` like every other milestone.
"""
from __future__ import annotations

from baseline.contracts import TrainingHook

from predict_plugin.schedule import downsample_scale


class PredictStages(TrainingHook):
    name = "predict_stages"

    def __init__(self, trainer):
        self.t = trainer
        p = trainer.cfg.ext["predict"]
        at = trainer.cfg.train.at
        self.p = p
        self.residual_from = at(p.residual_from)
        self.T = max(1, at(p.T))

    def residual_on(self, it: int) -> bool:
        return bool(self.p.residual) and it > self.residual_from

    @classmethod
    def stage_starts(cls, cfg) -> list[int]:
        """Stage 2 (the residual branch) starts after ``predict.residual_from``."""
        p = cfg.ext["predict"]
        return [cfg.train.at(p.residual_from)] if p.residual else []

    @classmethod
    def all_on_sets(cls, cfg) -> list[str]:
        return ["predict.residual_from=0", "predict.schedule=none", "predict.d_s=1.0"]

    def restore(self, it: int) -> None:
        """After a checkpoint of iteration ``it`` is loaded: the refiner is on exactly when it
        was on in that iteration (a loaded run is evaluated, rendered, exported or encoded
        without a step; before this hook a loaded stage-2 run rendered without its MGRD)."""
        ref = self.t.model.refiner
        if ref is not None:
            ref.active = self.residual_on(it)

    def before_step(self, it: int) -> None:
        ref = self.t.model.refiner
        if ref is not None:
            ref.active = self.residual_on(it)
        self.t.render_scale = downsample_scale(it, self.p.schedule, self.p.d_s, self.p.d_e, self.T,
                                               stage2_from=self.residual_from)
