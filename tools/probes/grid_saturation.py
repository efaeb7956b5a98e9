"""Where the binarized hash grids' entries stand in a training checkpoint.

    python tools/probes/grid_saturation.py RUN/checkpoint.pt [RUN2/checkpoint.pt ...]

Every binary hash grid of the checkpoint (the entropy model's context grid, and a feature
provider's own grid such as Predict-GS's Spatial Feature Pool) binarizes its float entries with a
straight-through gradient that is zero outside [-1, 1] (HAC's ``STE_binary``): an entry that
leaves that interval keeps its sign for the rest of training. Per grid (all levels together):
the share of entries past +-1 (frozen), the share still exactly at the shared start value
(``predict.grid_init = "shared"`` starts every entry at +init_range, so such an entry was never
read; meaningless for random starts), the share of negative entries (the -1 bits) and the largest
|entry|.
"""
from __future__ import annotations

import inspect
import sys

import torch

from baseline.hac.hashgrid import BinaryHashGrid

# the grids' start value (no config key sets it)
START = float(inspect.signature(BinaryHashGrid).parameters["init_range"].default)


def grid_tables(ck: dict) -> dict[str, list[torch.Tensor]]:
    """grid name -> its tables' float entries, from a checkpoint's model and entropy states."""
    out: dict[str, list[torch.Tensor]] = {}
    for part in ("model", "entropy"):
        for key, value in (ck.get(part) or {}).items():
            if key.endswith(".params") and ".grids." in key:
                name = f"{part}.{key.split('.grids.')[0]}"
                out.setdefault(name, []).append(value.detach().float().flatten())
    return out


def grid_saturation(path: str) -> dict:
    ck = torch.load(path, map_location="cpu", weights_only=False)
    rows = {}
    for name, tables in grid_tables(ck).items():
        x = torch.cat(tables)
        a = x.abs()
        rows[name] = {"entries": int(x.numel()),
                      "frozen": float((a > 1).float().mean()),
                      "at_start": float((x == START).float().mean()),
                      "negative": float((x < 0).float().mean()),
                      "max_abs": float(a.max())}
    return {"iteration": int(ck["iteration"]), "grids": rows}


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    print(f"{'checkpoint':<48} {'it':>6} {'grid':<22} {'entries':>9} {'past +-1':>9} "
          f"{'at start':>9} {'negative':>9} {'max |x|':>8}")
    for path in argv:
        o = grid_saturation(path)
        for name, r in o["grids"].items():
            print(f"{path[-48:]:<48} {o['iteration']:>6} {name:<22} {r['entries']:>9,} "
                  f"{r['frozen']:>9.3%} {r['at_start']:>9.2%} {r['negative']:>9.2%} "
                  f"{r['max_abs']:>8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
