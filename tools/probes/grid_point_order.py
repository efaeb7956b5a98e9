"""What bounds a hash-grid pass on the CPU: the order of the points, or the arithmetic.

    python tools/probes/grid_point_order.py RUN [RUN ...] [--views 4] [--repeats 5]

A training step queries each binary hash grid of a run (the entropy model's context grid, and
a feature provider's own grid such as Predict-GS's Spatial Feature Pool) at the anchors a view
sees, and scatters the gradient back into the tables. If the pass waited on table rows missed
in the caches, reading the points in a spatially coherent order (Morton order of their
normalised positions: neighbours share corners at every level) would be faster than the order
the model keeps them in, and a random order slower. If it is bound by the arithmetic per
corner (the cell, hash and weights, then the weighted sum), the three orders take the same
time.

Per run (its checkpoint; one thread), on ``--views`` training views spread over the cameras,
for each grid: the visible anchors' forward pass (the numba kernel the training step runs, the
float parameters read as their binarization where the grid binarizes) and forward + backward
(gradient to the tables, a fixed random output gradient), in the model's order, Morton order
and a random order, medians over ``--repeats`` of the process CPU time; and the forward's
split into the corners' cells, hashes and weights alone (a kernel that computes them and
discards them) and the rest (reading the rows and the weighted sums). The forward's values in
any order are checked to equal the model order's, permuted, bit for bit (each point's value
depends on that point alone). Prints ms per view and ns per point and level.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from numba import njit

from baseline.hac import _grid_kernels as K
from baseline.hac.hashgrid import _float_meta
from baseline.pipeline import visible_anchors
from baseline.run import load_run


@njit(cache=False, error_model="numpy")
def _corners_only(u, res, rows, offsets, kinds, strides):
    """The forward's corner rows and weights for every point and level, summed into a number
    that is returned so the work cannot be dropped; no table is read."""
    n, dim = u.shape
    sink = np.float64(0.0)
    for l in range(res.shape[0]):
        r = res[l]
        kind = kinds[l]
        nr = rows[l]
        off = offsets[l]
        sy = strides[l, 1]
        for i in range(n):
            if not K._inside(u, i, dim):
                continue
            if dim == 3:
                ix, w, wn = K._level3(u[i, 0], u[i, 1], u[i, 2], r, kind, nr, sy, strides[l, 2])
                sink += np.float64(ix[0] + ix[7] + off) + w[3] + wn
            else:
                ix2, w2, wn2 = K._level2(u[i, 0], u[i, 1], r, kind, nr, sy)
                sink += np.float64(ix2[0] + ix2[3] + off) + w2[1] + wn2
    return sink


def morton_order(u: torch.Tensor, bits: int = 10) -> torch.Tensor:
    """Indices that sort points ``u`` [N, 3] in [0, 1] by their Morton (Z-order) code."""
    q = (u.clamp(0, 1) * ((1 << bits) - 1)).to(torch.int64)
    code = torch.zeros(len(u), dtype=torch.int64)
    for b in range(bits):
        for d in range(q.shape[1]):
            code |= ((q[:, d] >> b) & 1) << (q.shape[1] * b + d)
    return torch.argsort(code)


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return 1e3 * statistics.median(times)


def _grids(trainer) -> dict:
    out = {}
    ent = getattr(trainer.entropy, "ctx_grid", None) if trainer.entropy is not None else None
    if ent is not None:
        out["entropy context"] = ent
    prov = getattr(trainer.model.provider, "grid", None)
    if prov is not None and prov is not ent:
        out["feature provider"] = prov
    return out


def probe_run(run: str, views: int = 4, repeats: int = 5, seed: int = 0) -> list:
    torch.set_num_threads(1)
    trainer, _ = load_run(run, device="cpu")
    model = trainer.model
    xyz = model.positions().detach()
    cams = trainer.scene.train_cameras
    picks = np.linspace(0, len(cams) - 1, views).round().astype(int)
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for name, grid in _grids(trainer).items():
        for ci in picks:
            idx = visible_anchors(model, cams[ci])
            x = xyz[idx]
            u = grid.normalize(x)
            gout = torch.randn(len(x), grid.output_dim, generator=gen)
            orders = {"model": None, "Morton": morton_order(u),
                      "random": torch.randperm(len(x), generator=gen)}
            with torch.no_grad():
                ref = grid(x)
            row = {"run": run, "grid": name, "view": int(ci), "points": int(len(x)),
                   "levels": sum(g.n_levels for g in grid.grids.values())}
            for oname, p in orders.items():
                xx, gg = (x, gout) if p is None else (x[p], gout[p])
                with torch.no_grad():
                    out = grid(xx)
                same = torch.equal(out, ref if p is None else ref[p])
                if not same:
                    raise AssertionError(f"{name}: the {oname} order changed a forward value")

                def fwd(xx=xx):
                    with torch.no_grad():
                        grid(xx)

                def fwd_bwd(xx=xx, gg=gg):
                    grid.zero_grad(set_to_none=True)
                    grid(xx).backward(gg)

                row[oname] = (_median_ms(fwd, repeats), _median_ms(fwd_bwd, repeats))
            corners = 0.0
            for k, g in grid.grids.items():
                uk = u[:, list(grid._axes[k])].contiguous().numpy()
                meta = _float_meta(g)
                corners += _median_ms(lambda uk=uk, meta=meta: _corners_only(uk, *meta), repeats)
            row["corners only"] = corners
            rows.append(row)
    return rows


def format_rows(rows: list) -> str:
    lines = ["ms per view (process CPU time, one thread); ns per point and level in brackets",
             f"{'grid':<17} {'view':>4} {'points':>7} | {'forward: model':>16} {'Morton':>7} "
             f"{'random':>7} | {'fwd+bwd: model':>15} {'Morton':>7} {'random':>7} | "
             f"{'corners only':>13} {'rows + sums':>12}"]
    for r in rows:
        pl = r["points"] * r["levels"] / 1e6       # point-levels, millions: ms / pl = ns each
        f, fb = r["model"]
        corners = r["corners only"]
        lines.append(
            f"{r['grid']:<17} {r['view']:>4} {r['points']:>7} | {f:>7.1f} ({f / pl:>4.1f}) "
            f"{r['Morton'][0]:>7.1f} {r['random'][0]:>7.1f} | {fb:>6.1f} ({fb / pl:>4.1f}) "
            f"{r['Morton'][1]:>7.1f} {r['random'][1]:>7.1f} | {corners:>5.1f} ({corners / pl:>4.1f}) "
            f"{f - corners:>5.1f} ({(f - corners) / pl:>4.1f})")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)
    for run in a.runs:
        print(run)
        print(format_rows(probe_run(run, a.views, a.repeats)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
