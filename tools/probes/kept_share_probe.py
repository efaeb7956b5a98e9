"""The kept share (opacity > 0 of the mask-on candidate Gaussians) of a training's first steps,
on fixed test views: where a method's Gaussian count is decided.

    python tools/probes/kept_share_probe.py SCENE -r 4 --patch cpu [--patch predict-gs ...]
        [--set section.key=value ...] [--steps 0 10 25 50 100 200 300] [--views 8]
    python tools/probes/kept_share_probe.py SCENE -r 4 --patch cpu --init-seeds 4

One JSON line per measured step: kept share, Gaussians per view, the share of visible anchors
by their number of kept Gaussians, anchors, seconds since the start. ``--init-seeds N``
measures only the initialisation (no step) of HAC (the given patches) and of the same with
``predict-gs`` for seeds 0..N-1. A training folder is made under a temporary directory and
removed. Run it with one thread per core (OMP_NUM_THREADS=1, taskset) beside other work.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time

import torch

from baseline.config import build_config
from baseline.data.scene import load_scene
from baseline.pipeline import visible_anchors
from baseline.train.trainer import Trainer


def kept(model, cams) -> dict:
    on_t = kept_t = 0
    per = torch.zeros(model.n_offsets + 1)
    with torch.no_grad():
        for cam in cams:
            idx = visible_anchors(model, cam)
            op = model.raw_heads(cam.center, idx).opacity()
            on = model.gaussian_mask(idx) > 0
            k = (op > 0) & on
            on_t += int(on.sum())
            kept_t += int(k.sum())
            per += torch.bincount(k.sum(1), minlength=model.n_offsets + 1).float()
    return dict(kept_share=round(kept_t / max(on_t, 1), 4), gaussians=round(kept_t / len(cams)),
                per_anchor=[round(x, 3) for x in (per / per.sum().clamp_min(1)).tolist()])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("-r", "--resolution", type=int, default=-1)
    ap.add_argument("--patch", action="append", default=[])
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--steps", type=int, nargs="+", default=[0, 10, 25, 50, 100, 200, 300])
    ap.add_argument("--views", type=int, default=8, help="the first N test views")
    ap.add_argument("--init-seeds", type=int, default=0)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    scene = load_scene(a.scene, resolution=a.resolution, progress=False)
    cams = (scene.test_cameras or scene.train_cameras)[:a.views]
    with tempfile.TemporaryDirectory(prefix="pgs-probe-") as tmp:
        if a.init_seeds:
            for seed in range(a.init_seeds):
                for patches in (a.patch, a.patch + ["predict-gs"]):
                    cfg = build_config(patches, [f"train.seed={seed}"] + a.set)
                    cfg.train.threads = 1
                    t = Trainer(cfg, scene, f"{tmp}/{seed}-{len(patches)}", progress=False)
                    print(json.dumps(dict(seed=seed, patches=patches, **kept(t.model, cams))),
                          flush=True)
            return 0
        cfg = build_config(a.patch, a.set)
        cfg.train.threads = 1
        t = Trainer(cfg, scene, f"{tmp}/run", progress=False)
        t0 = time.time()
        for it in sorted(set(a.steps)):
            if it:
                t.train(until=it)
            print(json.dumps(dict(it=it, **kept(t.model, cams), anchors=t.model.n_anchors,
                                  s=round(time.time() - t0))), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
