"""Hash-grid benchmark: the numba kernels against the PyTorch path, in one process.

``pgs bench grid [--anchors N] [--threads T]`` (= ``python -m baseline.bench.grid``)

Times one training-path query of HAC's default grid (12 3D levels + 3 x 4 plane levels, 96
outputs) at ``N`` random positions (forward, then forward + backward to the tables), best of a
few repeats after a warm-up, for each backend; ratio = PyTorch time / backend time.
"""
from __future__ import annotations

import argparse
import time
from typing import Dict, List, Optional, Sequence

import torch

from baseline.hac import hashgrid as H


def _best(fn, repeats: int) -> float:
    fn()  # warm-up (compiles the kernels on first use)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run_grid_bench(n_anchors: int = 100_000, threads: Optional[int] = None, repeats: int = 3,
                   seed: int = 0, backends: Sequence[str] = ("torch", "numba")) -> List[Dict]:
    prev_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    grid = H.BinaryHashGrid()
    xyz = torch.rand(n_anchors, 3, generator=g)
    gout = torch.randn(n_anchors, grid.output_dim, generator=g)
    rows = []
    old = H.get_grid_backend()
    try:
        for be in backends:
            H.set_grid_backend(be)

            def fwd():
                with torch.no_grad():
                    grid(xyz)

            def fwd_bwd():
                grid.zero_grad(set_to_none=True)
                (grid(xyz) * gout).sum().backward()

            rows.append(dict(backend=be, n=n_anchors, threads=torch.get_num_threads(),
                             forward_s=_best(fwd, repeats), forward_backward_s=_best(fwd_bwd, repeats)))
    finally:
        H.set_grid_backend(old)
        torch.set_num_threads(prev_threads)
    ref = next((r for r in rows if r["backend"] == "torch"), None)
    for r in rows:
        r["ratio_forward"] = ref["forward_s"] / r["forward_s"] if ref else None
        r["ratio_forward_backward"] = ref["forward_backward_s"] / r["forward_backward_s"] if ref else None
    return rows


def format_grid_bench(rows: Sequence[Dict]) -> str:
    lines = ["hash-grid benchmark (HAC layout, 96 outputs; wall clock, best of 3 after a warm-up; "
             "ratio = torch time / backend time)",
             f"{'anchors':>9} {'backend':>8} {'thr':>4} {'forward':>10} {'fwd+bwd':>10} "
             f"{'x fwd':>7} {'x f+b':>7}"]
    for r in rows:
        lines.append(f"{r['n']:>9} {r['backend']:>8} {r['threads']:>4} {1e3 * r['forward_s']:>8.1f}ms "
                     f"{1e3 * r['forward_backward_s']:>8.1f}ms {r['ratio_forward']:>6.1f}x "
                     f"{r['ratio_forward_backward']:>6.1f}x")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m baseline.bench.grid", description=__doc__)
    ap.add_argument("--anchors", type=int, default=100_000)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    print(format_grid_bench(run_grid_bench(args.anchors, args.threads)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
