"""Rasterizer benchmark: every available backend, side by side, in one process.

    python -m baseline.bench.raster [--threads N] [--repeats R] [--sizes 50000x320x240,...]

(``pgs bench raster`` calls :func:`run_raster_bench` and :func:`format_raster_bench`.)

Scene: a fixed-seed random cloud in front of a pinhole camera (60 deg horizontal fov): depths
uniform in [2, 8], positions uniform over the (10 % enlarged) frustum, random rotations,
per-axis scales chosen so that the projected standard deviation is log-uniform in [0.6, 5]
pixels (each Gaussian covers a few to tens of pixels), opacities uniform in [0.05, 0.95],
random RGB colours, black background.

Measured per backend and size (wall clock, after one excluded warm-up run):
    forward:          ``rasterize(...)`` under ``torch.no_grad()``
    forward+backward: ``rasterize(...)`` with inputs requiring grad, then
                      ``(image * w).sum().backward()`` (w a fixed random weight image)
Both are the best (minimum) of ``repeats`` runs, the usual choice on a machine other processes
share (the medians are in the rows too). "pairs" is ``tile_pairs * 256``: the number of
(Gaussian, 16x16 tile) intersections of the opacity-aware boxes times the pixels in a tile,
i.e. the nominal Gaussian-pixel evaluations a tile rasterizer does (the same count for every
backend, so pairs/s compares backends directly; the CPU backend actually evaluates fewer, only
the pixels of each tile inside a Gaussian's box, and stops early per tile). Ratios are
reference time / backend time.

Threads: the reference runs on torch's intra-op pool with ``threads`` threads. The CPU backend
runs its numba kernels on ``threads`` threads while torch's pool (which only does glue there)
is set to ``cpu_torch_threads`` (default 1): torch's OpenMP workers spin for milliseconds after
every parallel torch op and take the cores from the kernels that follow (measured 20-40 %
slower with both at 2 threads on 2 cores; ``OMP_WAIT_POLICY=PASSIVE`` in the environment also
avoids it). Pass ``cpu_torch_threads=None`` to time it with torch at ``threads`` as well.

The reference backend is pure PyTorch and slow: it is run with ``reference_repeats`` (default
2) repeats after a warm-up on a small scene, and skipped (with the reason printed, and no
ratio for that row) when the size has more than ``reference_max_pairs`` tile pairs.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from typing import Iterable, Optional, Sequence

import torch

from baseline.camera import Camera
from baseline.device import machine_name

DEFAULT_SIZES = ((50_000, 320, 240), (200_000, 640, 480))


def make_scene(n: int, width: int, height: int, seed: int = 0, device="cpu",
               dtype=torch.float32):
    """A fixed-seed random scene in front of the camera.

    Returns:
        (means [n, 3], quats [n, 4], scales [n, 3], opacities [n], colors [n, 3]) and a
        :class:`Camera` of ``width`` x ``height`` at the origin looking down +z.
    """
    g = torch.Generator().manual_seed(seed)
    fx = 0.5 * width / math.tan(math.radians(30.0))
    z = torch.rand(n, generator=g, dtype=torch.float64) * 6.0 + 2.0
    x = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * z * (0.55 * width / fx)
    y = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * z * (0.55 * height / fx)
    means = torch.stack([x, y, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    sigma_px = 0.6 * torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64)
                               * math.log(5.0 / 0.6))
    scales = sigma_px * z[:, None] / fx
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    cam = Camera(viewmat=torch.eye(4), fx=fx, fy=fx, cx=width / 2, cy=height / 2,
                 width=width, height=height)
    tensors = tuple(t.to(device=device, dtype=dtype) for t in
                    (means, quats, scales, opacities, colors))
    return tensors, cam


def count_tile_pairs(tensors, camera) -> int:
    """Number of (Gaussian, tile) intersections of the opacity-aware boxes."""
    from baseline.render.reference import project_reference

    with torch.no_grad():
        means, quats, scales, opacities, _ = (t.detach().cpu().double() for t in tensors)
        proj = project_reference(means, quats, scales, opacities, camera)
        r = proj.rect
        return int(((r[:, 2] - r[:, 0]).clamp(min=0) * (r[:, 3] - r[:, 1]).clamp(min=0)).sum())


def available_backends() -> list[str]:
    """Backends that can run here: always cpu and reference, gsplat with CUDA + gsplat."""
    from baseline.render.gsplat_backend import gsplat_available

    names = ["cpu", "reference"]
    if torch.cuda.is_available() and gsplat_available():
        names.insert(1, "gsplat")
    return names


def _sync(device) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def _time_backend(backend: str, tensors, camera, repeats: int, weight, warmup=True):
    from baseline.render import rasterize

    device = tensors[0].device

    def fwd():
        with torch.no_grad():
            rasterize(*tensors, camera, backend=backend)
        _sync(device)

    def fwd_bwd():
        leaves = [t.detach().clone().requires_grad_(True) for t in tensors]
        out = rasterize(*leaves, camera, backend=backend)
        (out.image * weight).sum().backward()
        _sync(device)

    if warmup:
        fwd_bwd()
    t_fwd, t_fb = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fwd()
        t_fwd.append(time.perf_counter() - t0)
    for _ in range(repeats):
        t0 = time.perf_counter()
        fwd_bwd()
        t_fb.append(time.perf_counter() - t0)
    return min(t_fwd), min(t_fb), statistics.median(t_fwd), statistics.median(t_fb)


def run_raster_bench(sizes: Iterable[Sequence[int]] = DEFAULT_SIZES,
                     backends: Optional[Sequence[str]] = None, threads: Optional[int] = None,
                     repeats: int = 3, reference_repeats: int = 2,
                     reference_max_pairs: Optional[int] = 2_000_000, seed: int = 0,
                     progress: bool = False, cpu_torch_threads: Optional[int] = 1
                     ) -> list[dict]:
    """Time forward and forward+backward of each backend on random scenes.

    Args:
        sizes: (n_gaussians, width, height) triples.
        backends: names to run (default: :func:`available_backends`).
        threads: CPU threads for torch and the CPU kernels during the run (default: the
            current ``torch.get_num_threads()``); restored afterwards.
        repeats: timed runs per measurement (best reported, median kept); reference_repeats
            for the reference backend.
        reference_max_pairs: skip the reference where the scene has more tile pairs (None: never
            skip).
        seed: scene seed. progress: print a line per measurement as it finishes.
        cpu_torch_threads: torch's thread count while the CPU backend is timed (None: same
            as ``threads``; see the module docstring).
    Returns:
        One dict per (size, backend) with keys ``n, width, height, backend, threads,
        torch_threads, device, repeats, tile_pairs, pairs, forward_s, forward_backward_s`` (best of the repeats),
        ``forward_median_s, forward_backward_median_s, pairs_per_s`` (pairs / best
        forward+backward time), ``ratio_forward, ratio_forward_backward`` (reference best /
        backend best; None without a reference time) and ``skipped`` (None, or why the backend
        was not run; its times are then None).
    """
    from baseline.render import cpu as cpu_backend

    names = list(backends) if backends is not None else available_backends()
    old_torch_threads = torch.get_num_threads()
    old_cpu_threads = cpu_backend._THREADS
    n_threads = int(threads) if threads is not None else old_torch_threads
    torch.set_num_threads(n_threads)
    cpu_backend.set_num_threads(n_threads)
    rows: list[dict] = []
    # named once; a gsplat row asked for on a machine without CUDA says so (it is skipped)
    machine = {"cpu": machine_name(torch.device("cpu")),
               "cuda": machine_name(torch.device("cuda")) if torch.cuda.is_available()
               else "cuda (none here)"}
    try:
        ref_warm = False
        for n, width, height in sizes:
            base, cam = make_scene(int(n), int(width), int(height), seed=seed)
            tile_pairs = count_tile_pairs(base, cam)
            wg = torch.Generator().manual_seed(seed + 1)
            weight_cpu = torch.rand(int(height), int(width), 3, generator=wg)
            size_rows = []
            for name in names:
                torch_threads = n_threads
                if name == "cpu" and cpu_torch_threads is not None:
                    torch_threads = int(cpu_torch_threads)
                row = dict(n=int(n), width=int(width), height=int(height), backend=name,
                           threads=n_threads, torch_threads=torch_threads, device="cpu",
                           repeats=repeats,
                           tile_pairs=tile_pairs, pairs=tile_pairs * 256, forward_s=None,
                           forward_backward_s=None, forward_median_s=None,
                           forward_backward_median_s=None, pairs_per_s=None,
                           ratio_forward=None, ratio_forward_backward=None, skipped=None)
                device = "cuda" if name == "gsplat" else "cpu"
                row["device"] = machine[device]
                if name == "gsplat" and not torch.cuda.is_available():
                    row["skipped"] = "no CUDA device"
                elif name == "reference" and reference_max_pairs is not None \
                        and tile_pairs > reference_max_pairs:
                    row["skipped"] = (f"{tile_pairs:,} tile pairs > reference_max_pairs "
                                      f"{reference_max_pairs:,}")
                else:
                    tensors = tuple(t.to(device) for t in base)
                    weight = weight_cpu.to(device)
                    reps = repeats
                    warm = True
                    if name == "reference":
                        reps = reference_repeats
                        warm = False
                        if not ref_warm:  # warm up on a small scene instead of a full run
                            small, small_cam = make_scene(2000, 64, 48, seed=seed)
                            _time_backend("reference", small, small_cam, 1,
                                          torch.ones(48, 64, 3))
                            ref_warm = True
                    row["repeats"] = reps
                    torch.set_num_threads(torch_threads)
                    try:
                        t_f, t_fb, m_f, m_fb = _time_backend(name, tensors, cam, reps, weight,
                                                             warm)
                    except (ImportError, RuntimeError, ValueError) as e:
                        row["skipped"] = f"failed: {e}"
                    else:
                        row["forward_s"] = t_f
                        row["forward_backward_s"] = t_fb
                        row["forward_median_s"] = m_f
                        row["forward_backward_median_s"] = m_fb
                        row["pairs_per_s"] = row["pairs"] / t_fb
                    finally:
                        torch.set_num_threads(n_threads)
                if progress:
                    print(format_raster_bench([row], header=False), flush=True)
                size_rows.append(row)
            ref = next((r for r in size_rows if r["backend"] == "reference"
                        and r["forward_s"] is not None), None)
            if ref is not None:
                for r in size_rows:
                    if r["forward_s"] is not None:
                        r["ratio_forward"] = ref["forward_s"] / r["forward_s"]
                        r["ratio_forward_backward"] = (ref["forward_backward_s"]
                                                       / r["forward_backward_s"])
            rows.extend(size_rows)
    finally:
        torch.set_num_threads(old_torch_threads)
        cpu_backend.set_num_threads(old_cpu_threads)
    return rows


def _thr(r: dict) -> str:
    """Threads column: the backend's threads, '/t' with torch's count where it differs."""
    t = r.get("torch_threads", r["threads"])
    return str(r["threads"]) if t == r["threads"] else f"{r['threads']}/{t}"


def _fmt_time(t: Optional[float]) -> str:
    if t is None:
        return "-"
    return f"{t * 1e3:.1f} ms" if t < 10 else f"{t:.1f} s"


def format_raster_bench(rows: Sequence[dict], header: bool = True) -> str:
    """A plain-text table of :func:`run_raster_bench` rows."""
    lines = []
    if header:
        lines.append("rasterizer benchmark (wall clock, best of 'rep' runs after a warm-up; "
                     "pairs = tile pairs x 256; ratio = reference time / backend time;")
        lines.append("thr = threads, 'n/t': the CPU kernels on n threads with torch's own pool "
                     "at t)")
        lines.append(f"{'gaussians':>9} {'image':>9} {'backend':>9} {'thr':>5} {'rep':>3} "
                     f"{'forward':>10} {'fwd+bwd':>10} {'Mpairs/s':>9} {'x ref fwd':>9} "
                     f"{'x ref f+b':>9}")
    for r in rows:
        size = f"{r['width']}x{r['height']}"
        if r["skipped"]:
            lines.append(f"{r['n']:>9} {size:>9} {r['backend']:>9} {_thr(r):>5} "
                         f"{'':>3} skipped ({r['skipped']})")
            continue
        mps = "-" if r["pairs_per_s"] is None else f"{r['pairs_per_s'] / 1e6:.1f}"
        rf = "-" if r["ratio_forward"] is None else f"{r['ratio_forward']:.1f}x"
        rfb = "-" if r["ratio_forward_backward"] is None else \
            f"{r['ratio_forward_backward']:.1f}x"
        lines.append(f"{r['n']:>9} {size:>9} {r['backend']:>9} {_thr(r):>5} "
                     f"{r['repeats']:>3} {_fmt_time(r['forward_s']):>10} "
                     f"{_fmt_time(r['forward_backward_s']):>10} {mps:>9} {rf:>9} {rfb:>9}")
    return "\n".join(lines)


def _loadavg() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:  # not available on this platform
        return "n/a"


def _parse_sizes(text: str):
    sizes = []
    for part in text.split(","):
        n, w, h = part.lower().split("x")
        sizes.append((int(n), int(w), int(h)))
    return tuple(sizes)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m baseline.bench.raster",
                                 description="Time the rasterizer backends side by side.")
    ap.add_argument("--sizes", type=_parse_sizes, default=DEFAULT_SIZES,
                    help="comma-separated NxWxH, default 50000x320x240,200000x640x480")
    ap.add_argument("--backends", default=None, help="comma-separated backend names")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: torch's)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--reference-repeats", type=int, default=2)
    ap.add_argument("--reference-max-pairs", type=int, default=2_000_000,
                    help="skip the reference above this many tile pairs (-1: never skip)")
    ap.add_argument("--cpu-torch-threads", type=int, default=1,
                    help="torch threads while the CPU backend is timed (-1: same as --threads)")
    args = ap.parse_args(argv)
    backends = args.backends.split(",") if args.backends else None
    max_pairs = None if args.reference_max_pairs < 0 else args.reference_max_pairs
    threads = args.threads if args.threads is not None else torch.get_num_threads()
    tt_note = ("torch at the same count" if args.cpu_torch_threads < 0 else
               f"torch's own pool at {args.cpu_torch_threads} while the CPU backend runs")
    print(f"threads: {threads} (reference: torch; CPU backend: numba kernels, {tt_note}); "
          f"backends: {', '.join(backends or available_backends())}", flush=True)
    print(f"machine: {os.cpu_count()} CPU cores, load average {_loadavg()} before the run "
          "(other processes compete for the cores)", flush=True)
    from baseline.render.cpu import kernels

    kernels()  # compile / load the CPU kernels before timing (announced if compiling)
    cpu_tt = None if args.cpu_torch_threads < 0 else args.cpu_torch_threads
    rows = run_raster_bench(args.sizes, backends, threads, args.repeats,
                            args.reference_repeats, max_pairs, progress=False,
                            cpu_torch_threads=cpu_tt)
    print(format_raster_bench(rows))


if __name__ == "__main__":
    main()
