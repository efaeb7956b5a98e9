"""Where the binarized hash grids' entries stand in a trained run, read and unread.

    python tools/probes/grid_saturation.py RUN [RUN ...]

Every binary hash grid of a run (the entropy model's context grid, and a feature provider's
own grid such as Predict-GS's Spatial Feature Pool) binarizes its float entries with a
straight-through gradient that is zero outside [-1, 1] (HAC's ``STE_binary``): an entry that
leaves that interval keeps its sign for the rest of training. Per grid (all levels together),
from the run's checkpoint: the share of entries the coded anchors read (a nonzero corner weight
at their training positions, ``BinaryHashGrid.used_values``: what the file codes), the share
past +-1 (frozen) among the read and among the unread entries, and the share of -1 bits among
the read ones. An unread entry moves only by the hash-bits rate term, which pushes every entry
toward the majority sign, so frozen unread entries are the rate doing its work; frozen read
entries are capacity the images can no longer move.
"""
from __future__ import annotations

import sys

import numpy as np
import torch

from baseline.run import load_run


@torch.no_grad()
def grid_saturation(run: str) -> dict:
    trainer, _ = load_run(run, device="cpu")
    model = trainer.model
    xyz = model.positions()[model.anchor_valid()]
    grids = {"entropy context": getattr(trainer.entropy, "grid", None),
             "feature provider": getattr(model.provider, "grid", None)}
    rows = {}
    for name, grid in grids.items():
        if grid is None:
            continue
        read = grid.used_values(xyz)
        x = torch.cat([g.params.detach().reshape(-1) for g in grid.grids.values()]).numpy()
        frozen = np.abs(x) > 1
        rows[name] = {"entries": int(x.size), "read": float(read.mean()),
                      "frozen_read": float(frozen[read].mean()) if read.any() else 0.0,
                      "frozen_unread": float(frozen[~read].mean()) if (~read).any() else 0.0,
                      "negative_read": float((x[read] < 0).mean()) if read.any() else 0.0}
    return {"grids": rows}


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    print(f"{'run':<44} {'grid':<17} {'entries':>9} {'read':>8} {'frozen, read':>13} "
          f"{'frozen, unread':>15} {'-1 of read':>11}")
    for run in argv:
        for name, r in grid_saturation(run)["grids"].items():
            print(f"{run.rstrip('/')[-44:]:<44} {name:<17} {r['entries']:>9,} {r['read']:>8.2%} "
                  f"{r['frozen_read']:>13.3%} {r['frozen_unread']:>15.3%} "
                  f"{r['negative_read']:>11.2%}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
