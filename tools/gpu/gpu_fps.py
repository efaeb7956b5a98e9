"""Decoded-model FPS on a machine that does not hold the scene (e.g. a GPU node without network
that receives only the repository).

``pgs bench fps`` loads the test views from the scene named in each file's header; such a
machine has the ``.pgs`` files but not the scene. This tool splits the job:

    # here, where the scene is: the test cameras of the files' scene, a few KB
    python tools/gpu/gpu_fps.py export RUN_OR_FILE.pgs -o cams.pt
    # there: the same one-process bench (baseline.bench.fps.run_fps_bench: decode every
    # file, rotate the order every round, median over rounds, ratios to the first file)
    python tools/gpu/gpu_fps.py bench --cams cams.pt --run A.pgs --run B.pgs --device cuda [--scale 1 --scale 4]

``frame`` is ``pgs bench frame`` there: each file's frame split into prefilter, decoding
(plain and baked) and rasterization, ms per view at each scale.

``--scale k`` renders every view at k times its width and height (intrinsics scaled alike): the
same Gaussians at a higher image resolution, e.g. truck models trained at ``-r 4`` timed at the
capture's own size. Those frames are not the trained protocol (the Gaussians were fitted to the
small images); only their cost is measured.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from baseline.camera import Camera  # noqa: E402


def export(src: str, out: str) -> None:
    from baseline.modelfile import decode_model
    from baseline.bench.fps import resolve_model_file
    from baseline.run import load_scene_for

    dec = decode_model(resolve_model_file(src))
    sc = load_scene_for(dec.cfg, dec.scene_path, progress=False)
    cams = list(sc.test_cameras or sc.train_cameras)
    torch.save({"scene": str(dec.scene_path), "background": sc.background.float(),
                "cameras": [dict(viewmat=c.viewmat, fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
                                 width=c.width, height=c.height, near=c.near, far=c.far,
                                 name=c.name, index=c.index) for c in cams]}, out)
    print(f"wrote {len(cams)} cameras ({cams[0].width}x{cams[0].height}) of {dec.scene_path} "
          f"to {out}")


def _load(cams_file: str, runs, device: str):
    """The exported cameras, background and device, and each file decoded once (CPU codec)
    and moved there, labelled by its name (a run folder's model.pgs: the folder's)."""
    from baseline.modelfile import decode_model
    from baseline.device import resolve_device
    from baseline.bench.fps import resolve_model_file

    blob = torch.load(cams_file, weights_only=True)
    cams0 = [Camera(**c) for c in blob["cameras"]]
    dev = resolve_device(device)
    models, seen = [], set()
    for p in runs:
        f = resolve_model_file(p)
        label = f.parent.name if f.stem == "model" else f.stem
        while label in seen:
            label += "'"
        seen.add(label)
        models.append((label, decode_model(f).model.to(dev)))
    return cams0, blob["background"].to(dev), dev, models


def _scaled(cams0, k: int):
    """The cameras at k times their width and height (intrinsics scaled alike)."""
    return [replace(c, fx=c.fx * k, fy=c.fy * k, cx=c.cx * k, cy=c.cy * k,
                    width=c.width * k, height=c.height * k) for c in cams0]


def bench(cams_file: str, runs, device: str, rounds: int, scales, out_json: str | None,
          backend: str = "auto") -> None:
    from baseline.device import device_name
    from baseline.bench.fps import contenders_of, run_fps_bench
    from baseline.render import resolve_backend

    cams0, bg, dev, models = _load(cams_file, runs, device)
    contenders = [c for i, (label, m) in enumerate(models)
                  for c in contenders_of(label, m, model_index=i)]
    used = resolve_backend(backend, contenders[0].model.xyz)
    results = []
    for k in scales:
        cams = _scaled(cams0, k)
        rows = run_fps_bench(contenders, cams, bg, rounds=rounds, backend=backend)
        head = (f"{len(cams)} views at {cams[0].width}x{cams[0].height} (scale {k}), "
                f"{device_name(dev)}, backend {used}, {rounds} rounds")
        print(head)
        print(f"{'model':58s} {'Gauss/view':>10s} {'FPS':>8s} {'ratio':>6s} {'(min-max)':>13s} "
              f"{'same form':>9s} {'(min-max)':>13s}")
        for r in rows:
            print(f"{r['label']:58s} {r['gaussians_per_view']:10.0f} {r['fps']:8.1f} "
                  f"{r['ratio']:6.3f} ({r['ratio_min']:.3f}-{r['ratio_max']:.3f}) "
                  f"{r['ratio_form']:9.3f} ({r['ratio_form_min']:.3f}-{r['ratio_form_max']:.3f})")
        results.append(dict(protocol=head, scale=k, rows=rows))
    if out_json:
        Path(out_json).write_text(json.dumps(results, indent=2))


def frame(cams_file: str, runs, device: str, rounds: int, scales, backend: str = "auto") -> dict:
    """``pgs bench frame`` on exported cameras: each file's frame split into its stages
    (prefilter, decoding, rasterization, and baked decoding), at each scale; printed and
    returned as {scale: {label: stages}}."""
    from baseline.device import device_name
    from baseline.bench.fps import bench_frame_format_model, time_frame_stages

    cams0, bg, dev, models = _load(cams_file, runs, device)
    out = {}
    for k in scales:
        cams = _scaled(cams0, k)
        print(f"{len(cams)} views at {cams[0].width}x{cams[0].height} (scale {k}), "
              f"{device_name(dev)}, {rounds} rounds")
        out[k] = {}
        for label, m in models:
            st = time_frame_stages(m, cams, bg, rounds=rounds, backend=backend)
            out[k][label] = st
            print(bench_frame_format_model(label, st))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write the test cameras of a file's scene")
    e.add_argument("src")
    e.add_argument("-o", "--out", required=True)
    b = sub.add_parser("bench", help="time decoded files on exported cameras")
    b.add_argument("--cams", required=True)
    b.add_argument("--run", action="append", required=True)
    b.add_argument("--device", default="auto")
    b.add_argument("--rounds", type=int, default=10)
    b.add_argument("--scale", type=int, action="append",
                   help="render at k x the trained size (repeatable; default 1)")
    b.add_argument("--json")
    b.add_argument("--backend", default="auto",
                   help="rasterizer (auto: gsplat for CUDA tensors; the files' own setting is "
                        "ignored: the cpu preset pins the numba backend)")
    f = sub.add_parser("frame", help="split decoded files' frames into stages on exported cameras")
    f.add_argument("--cams", required=True)
    f.add_argument("--run", action="append", required=True)
    f.add_argument("--device", default="auto")
    f.add_argument("--rounds", type=int, default=5)
    f.add_argument("--scale", type=int, action="append")
    f.add_argument("--backend", default="auto")
    a = ap.parse_args()
    if a.cmd == "export":
        export(a.src, a.out)
    elif a.cmd == "frame":
        frame(a.cams, a.run, a.device, a.rounds, a.scale or [1], a.backend)
    else:
        bench(a.cams, a.run, a.device, a.rounds, a.scale or [1], a.json, a.backend)


if __name__ == "__main__":
    main()
