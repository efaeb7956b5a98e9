"""``pgs bench train``: where a training step's time goes, per stage, for trained runs.

Each run folder is loaded from its checkpoint (a copy in memory: nothing is written), put in
HAC's adaptive phase if it is not there yet, and takes ``warmup`` untimed steps, then ``steps``
timed ones from where it stopped. Stages (:mod:`baseline.timing`) in step order: hooks and
learning rates, the training view and its ground truth, the anchor prefilter, context and rate
(the entropy model on the visible anchors), decoding (feature provider, decoder MLPs, refiner,
the activations), rasterization, losses; the backward pass split at the gradients' arrival
(losses, rasterization, the activations, decoder MLPs + refiner, the rest: feature provider,
context, rate and the leaves); densification statistics, the optimizer, growing and pruning.
Medians over the steps, in ms; with several runs, each run's ratio to the first.

Without a run, ``--anchors N`` builds a synthetic state: the procedural scene with N SfM points
at a small voxel, in the adaptive phase from the first step.
"""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

STAGE_ORDER = [
    "hooks before", "view + ground truth", "prefilter", "context + rate", "decode",
    "provider", "decoder MLPs", "refiner", "rasterize", "losses", "backward", "losses bwd",
    "rasterize bwd", "activations bwd", "decoder MLPs + refiner bwd", "rest bwd",
    "densify statistics", "optimizer", "hooks after (growing, pruning)",
]
NESTED = {"provider", "decoder MLPs", "refiner", "losses bwd", "rasterize bwd",
          "activations bwd", "decoder MLPs + refiner bwd", "rest bwd"}


def _synthetic_trainer(n_anchors: int, threads: int, patches=("cpu",), folder=None):
    """A state of ``n_anchors`` SfM points of the procedural scene (245 x 136, truck's ``-r 4``
    size) in HAC's adaptive phase from the first step; with a method's patches its every stage
    is on from the first step too (its hooks' ``all_on_sets``). One scene per ``folder``:
    several methods share it."""
    from baseline import registry
    from baseline.config import build_config
    from baseline.data.scene import load_scene
    from baseline.data.synthetic import make_scene
    from baseline.train.trainer import Trainer

    d = Path(folder) if folder is not None else Path(tempfile.mkdtemp(prefix="pgs-bench-train-"))
    if not (d / "scene").exists():
        make_scene(d / "scene", n_views=12, width=245, height=136, seed=0, n_points=n_anchors)
    sets = [f"train.threads={threads}", "model.voxel_size=0.001", "entropy.noise_from=0",
            "entropy.context_from=0", "train.log_every=1000"]
    cfg = build_config(list(patches), sets)
    on = [s for h in cfg.train.hooks for s in registry.component_class("hooks", h).all_on_sets(cfg)]
    if on:
        cfg = build_config(list(patches), sets + on)
    run = d / ("run-" + "+".join(patches))
    return Trainer(cfg, load_scene(d / "scene", progress=False), run, progress=False)


def _adaptive(trainer) -> None:
    """Put a loaded run in HAC's adaptive phase (as its hooks would at ``context_from``)."""
    if trainer.phase == "adaptive":
        return
    from baseline.codec.rangecoder import anchor_bounds
    import torch

    lo, hi = anchor_bounds(trainer.model.xyz.detach().cpu().numpy())
    trainer.entropy.set_bounds(torch.from_numpy(lo), torch.from_numpy(hi))
    trainer.phase = "adaptive"
    for h in trainer.hooks:
        if type(h).__name__ == "HACPhases":
            h.context_from = h.noise_from = 0
            if h.coded_positions and trainer.model.position_box is None:
                trainer.model.position_box = (lo, hi)


def bench_trainer(trainer, steps: int = 10, warmup: int = 2, label: str = "") -> dict:
    """Time ``steps`` steps of ``trainer`` (after ``warmup`` untimed ones): per-step stage times
    and wall times in seconds."""
    from baseline import timing
    from baseline.timing import StageTimer

    _adaptive(trainer)
    it = trainer.iteration
    for _ in range(warmup):
        it += 1
        trainer.step(it)
    per_step, walls = [], []
    for _ in range(steps):
        it += 1
        t = StageTimer()
        with timing.timing(t):
            t0 = timing.now()
            trainer.step(it)
            walls.append(timing.now() - t0)
        per_step.append(dict(t.times))
    stages = {k: [s.get(k, 0.0) for s in per_step] for k in
              dict.fromkeys(k for s in per_step for k in s)}
    return {"label": label, "anchors": trainer.model.n_anchors, "iteration": trainer.iteration,
            "steps": steps, "stages": stages, "wall": walls,
            "gaussians": None}


def run_train_bench(runs: list[str], steps: int = 10, threads: int = 1, warmup: int = 2,
                    anchors: Optional[int] = None, methods: Sequence[str] = (),
                    clock: str = "wall") -> dict:
    """Bench each run folder, or without runs a synthetic state of ``anchors`` points for HAC
    and for each of ``methods`` (patches joined by '+', as ``--vs`` takes them), in one process.

    ``clock``: "wall" (``time.perf_counter``) or "cpu" (the process's CPU time,
    ``time.process_time``: at one thread, what the step itself costs, whatever else shares the
    core; it leaves out waits, so it is no wall-time figure)."""
    from baseline import timing
    from baseline.eval.report import method_label
    from baseline.train.trainer import set_threads

    if clock not in ("wall", "cpu"):
        raise ValueError(f"clock must be 'wall' or 'cpu', got {clock!r}")
    n = set_threads(threads)
    results = []
    with timing.clock(time.process_time if clock == "cpu" else time.perf_counter):
        if not runs:
            folder = Path(tempfile.mkdtemp(prefix="pgs-bench-train-"))
            for m in ("",) + tuple(methods):
                patches = ("cpu",) + tuple(p for p in m.split("+") if p)
                tr = _synthetic_trainer(anchors or 100_000, threads, patches, folder)
                results.append(bench_trainer(tr, steps, warmup, method_label(m or "baseline")))
        for r in runs:
            from baseline.run import load_run

            tr, _ = load_run(r, device="cpu")
            set_threads(threads)
            results.append(bench_trainer(tr, steps, warmup, Path(r).name))
    return {"threads": n, "steps": steps, "warmup": warmup, "runs": results, "clock": clock,
            "synthetic": not runs}


def format_train_bench(res: dict) -> str:
    runs = res["runs"]
    med = [{k: statistics.median(v) * 1e3 for k, v in r["stages"].items()} for r in runs]
    walls = [statistics.median(r["wall"]) * 1e3 for r in runs]
    head = ["stage (ms per step, median)"] + [r["label"] for r in runs] + (
        [f"{r['label']} / {runs[0]['label']}" for r in runs[1:]])
    names = [k for k in STAGE_ORDER if any(k in m for m in med)]
    names += sorted({k for m in med for k in m} - set(names))
    rows = []
    for k in names:
        vals = [m.get(k) for m in med]
        ratio = [(f"{v / vals[0]:.2f}x" if v is not None and vals[0] else "-") for v in vals[1:]]
        rows.append([("  " if k in NESTED else "") + k] + [("-" if v is None else f"{v:.1f}")
                                                           for v in vals] + ratio)
    rows.append(["step"] + [f"{w:.1f}" for w in walls]
                + [f"{w / walls[0]:.2f}x" for w in walls[1:]])
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    fmt = lambda r: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)  # noqa: E731
                              for i, (c, w) in enumerate(zip(r, widths)))
    clock = ("process CPU time" if res.get("clock") == "cpu" else "wall time")
    synthetic = " (synthetic states)" if res.get("synthetic") else ""
    lines = [f"training step{synthetic}, {res['threads']} thread(s), {res['steps']} timed steps after "
             f"{res['warmup']} untimed, {clock} (medians; indented rows are parts of the row "
             f"above)",
             "runs: " + "; ".join(f"{r['label']}: {r['anchors']} anchors" + (
                 "" if res.get("synthetic") else
                 f" from iteration {r['iteration'] - r['steps'] - res['warmup']}")
                 for r in runs), fmt(head), fmt(["-" * w for w in widths])]
    lines += [fmt(r) for r in rows]
    return "\n".join(lines)
