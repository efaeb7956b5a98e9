"""Evaluation of a trained or decoded model on the test views: metrics on uint8 images, FPS.

With an output folder the views are written as 3DGS's ``render.py`` and ``metrics.py`` lay out
``test/ours_<iterations>/``: ``renders/`` and ``gt/`` (PNG, one name per view) and
``per_view.json`` (``{"ours_<iterations>": {"PSNR": {name: dB}, "SSIM": {...}, "LPIPS": {...},
"SSIM_skimage": {...}}}``, LPIPS where measured), so the field's scripts read them as they are.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from baseline.data.images import write_png_atomic
from baseline.eval.metrics import SSIM_CONVENTION, psnr, ssim, ssim_skimage, to_uint8
from baseline.pipeline import render_view


def alive_breakdown(visible: int, mask_on: int, kept: int, views: int, k: int) -> dict:
    """Where the Gaussians per view come from, summed over ``views``: ``visible_anchors_mean``
    (anchors in the view frustum, per view), ``mask_on_fraction`` (of their ``k`` candidate
    Gaussians each, those whose mask is on) and ``opacity_kept_fraction`` (of those, the ones
    with opacity > 0, i.e. rasterized), so that kept per view = visible x k x mask_on x opacity_kept.
    """
    cand = visible * k
    return {"visible_anchors_mean": visible / views if views else 0.0,
            "mask_on_fraction": mask_on / cand if cand else None,
            "opacity_kept_fraction": kept / mask_on if mask_on else None}


def view_file_names(cameras) -> list[str]:
    """One PNG name per view: its image's name (``Path(name).stem + ".png"``) where those are
    unique among ``cameras``, else the view's index (``00000.png``, as 3DGS names them)."""
    stems = [Path(c.name).stem for c in cameras]
    if all(stems) and len(set(stems)) == len(stems):
        return [f"{s}.png" for s in stems]
    return [f"{i:05d}.png" for i in range(len(cameras))]


def method_key(iterations: int) -> str:
    """The key 3DGS's ``per_view.json`` files a model under: ``ours_<iterations>``."""
    return f"ours_{int(iterations)}"


@torch.no_grad()
def evaluate(model, scene, cameras, *, phase: str, entropy=None, backend: str = "auto",
             coded=None, render_dir: Optional[Path] = None,
             lpips_fn=None, fps_skip: int = 5, iterations: int | None = None) -> dict:
    """Render ``cameras`` and report PSNR / SSIM (/ LPIPS) on uint8 images and FPS.

    FPS = 1 / mean(prefilter + decode + render time), the first ``fps_skip`` frames skipped
    (docs/method.md section 2); on a GPU each frame is timed to the end of its work. The model renders
    where it lives (``model.to(device)`` first). ``coded``: a trained model in the adaptive phase
    rendered as the codec stores it (:func:`baseline.pipeline.coded_state`).

    ``render_dir``: write ``renders/``, ``gt/`` and ``per_view.json`` there (module doc), the
    views keyed by :func:`view_file_names` under :func:`method_key` of ``iterations`` (default:
    ``model.iteration``). "ssim" is the field's SSIM (:func:`baseline.eval.metrics.ssim`,
    ``ssim_convention``), "ssim_skimage" scikit-image's.
    """
    bg = scene.background.float().to(model.xyz.device)
    sync = (torch.cuda.synchronize if model.xyz.is_cuda else (lambda *a: None))
    ps, ss, sk, lp, times, counts = [], [], [], [], [], []
    names = view_file_names(cameras)
    n_vis = n_on = 0                     # visible anchors, mask-on Gaussians among their candidates
    from baseline.memory import allocating

    dev = str(model.xyz.device)
    for i, cam in enumerate(cameras):
        t0 = time.perf_counter()
        with allocating(f"rendering view {cam.name} ({cam.width} x {cam.height}, "
                        f"{model.n_anchors} anchors)", device=dev):
            res = render_view(model, cam, bg, phase=phase, training=False, entropy=entropy,
                              backend=backend, coded=coded)
        img = res.render.image
        sync()                           # CUDA work is asynchronous: time it to the end
        times.append(time.perf_counter() - t0)
        counts.append(int(res.gaussians.means.shape[0]))
        vis = torch.nonzero(res.gaussians.visible).squeeze(1)   # after the timing: not part of it
        n_vis += len(vis)
        n_on += int((model.gaussian_mask(vis) > 0).sum())
        a = to_uint8(img)
        b = to_uint8(scene.image(cam))
        ps.append(psnr(a, b))
        ss.append(ssim(a, b))
        sk.append(ssim_skimage(a, b))
        if lpips_fn is not None:
            lp.append(float(lpips_fn(a, b)))
        if render_dir is not None:
            write_png_atomic(Path(render_dir) / "renders" / names[i], a)
            write_png_atomic(Path(render_dir) / "gt" / names[i], b)
    if render_dir is not None:
        from baseline.fileio import write_text_atomic

        it = int(getattr(model, "iteration", 0) or 0) if iterations is None else iterations
        per = {"PSNR": dict(zip(names, ps)), "SSIM": dict(zip(names, ss))}
        if lp:
            per["LPIPS"] = dict(zip(names, lp))
        per["SSIM_skimage"] = dict(zip(names, sk))
        write_text_atomic(Path(render_dir) / "per_view.json",
                          json.dumps({method_key(it): per}, indent=2))
    t = times[fps_skip:] if len(times) > fps_skip else times
    out = {
        "psnr": float(np.mean(ps)) if ps else float("nan"),
        "ssim": float(np.mean(ss)) if ss else float("nan"),
        "ssim_skimage": float(np.mean(sk)) if sk else float("nan"),
        "ssim_convention": SSIM_CONVENTION,
        "lpips": float(np.mean(lp)) if lp else None,
        "fps": float(1.0 / np.mean(t)) if t else float("nan"),
        "n_views": len(cameras),
        "gaussians_mean": float(np.mean(counts)) if counts else 0.0,
        "anchors": int(model.n_anchors),
        **alive_breakdown(n_vis, n_on, int(sum(counts)), len(cameras), model.n_offsets),
    }
    return out
