"""What a scene looks like to a shared feature field: its camera layout, how far its SfM points
reach beyond where most of them are, and (per trained run) how the SFP's box compares with the
anchors' extent. These are the facts that separate the scenes where Predict-GS keeps more
Gaussians than HAC from those where it does not (`docs/notes/predict-gs-gaussian-count.md`).

    python tools/probes/scene_facts.py SCENE [-r 8] [--runs RUN ...]

One JSON line per scene, then one per run folder (its ``checkpoint.pt``):

* ``view_dir_resultant``: length of the mean unit viewing direction of all views (1: every
  view looks the same way, forward-facing; near 0: views look inward from all sides);
* ``camera_side_resultant``: length of the mean unit vector from the points' median to each
  camera centre (1: every camera on one side of the scene);
* ``sfm_box_over_inner``: per axis, the SfM points' full box over their inner box (the 5-95%
  quantiles); large values mean outliers stretch a bounds-from-points box;
* per run: anchors, and for a run with an SFP (Predict-GS) its normalisation box over the
  anchors' inner 90% box, per axis (how coarse the finest levels are where most anchors lie).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from baseline.data.scene import load_scene


def camera_facts(scene) -> dict:
    cams = scene.train_cameras + scene.test_cameras
    centres = torch.stack([c.center for c in cams]).double().numpy()
    R = torch.stack([c.viewmat[:3, :3] for c in cams]).double()
    dirs = R[:, 2, :].numpy()           # camera +z (the viewing direction) in world: R^T e_z
    pts = scene.points.double().numpy()
    lo, hi = np.quantile(pts, [0.05, 0.95], axis=0)
    side = centres - np.median(pts, axis=0)
    side /= np.linalg.norm(side, axis=1, keepdims=True).clip(1e-12)
    full = pts.max(0) - pts.min(0)
    return {"scene": scene.name, "views": len(cams), "points": len(pts),
            "view_dir_resultant": round(float(np.linalg.norm(dirs.mean(0))), 3),
            "camera_side_resultant": round(float(np.linalg.norm(side.mean(0))), 3),
            "sfm_box_over_inner": np.round(full / np.clip(hi - lo, 1e-12, None), 2).tolist(),
            "extent": round(float(scene.extent), 3)}


def run_facts(run: Path) -> dict:
    ck = run / "checkpoint.pt"
    if not ck.is_file():
        raise SystemExit(f"scene_facts: {ck} not found (a run folder with a checkpoint is needed)")
    state = torch.load(ck, map_location="cpu", weights_only=False)["model"]
    xyz = state["per_anchor.xyz"].double().numpy()
    lo, hi = np.quantile(xyz, [0.05, 0.95], axis=0)
    out = {"run": str(run), "anchors": len(xyz)}
    if "provider.grid.xyz_min" in state:
        box = (state["provider.grid.xyz_max"] - state["provider.grid.xyz_min"]).double().numpy()
        out["sfp_box_over_anchors_inner"] = np.round(box / np.clip(hi - lo, 1e-12, None), 2).tolist()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("-r", "--resolution", type=int, default=-1)
    ap.add_argument("--runs", nargs="*", default=[], type=Path)
    a = ap.parse_args(argv)
    scene = load_scene(a.scene, resolution=a.resolution, prefetch=False, progress=False)
    print(json.dumps(camera_facts(scene)), flush=True)
    for r in a.runs:
        print(json.dumps(run_facts(r)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
