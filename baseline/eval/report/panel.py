"""Pictures of where the methods differ, for the comparison report.

For a test view and a rate point, from each method's decoded ``.pgs`` file:

* its render and its per-pixel error against the ground truth (mean absolute error over RGB on
  uint8 images, in 0..255 grey levels; one colour scale for every method of the panel);
* its bit map: each anchor's coded bits (:func:`baseline.modelfile.coded_bits_per_anchor`:
  its coded attributes' information content under the file's own probabilities) added at the
  pixel its centre projects to, for the anchors that pass the prefilter of this view and land
  in the image (one colour scale, in bits per pixel). The map's total is those anchors' bits:
  per-anchor bits only. The sections no pixel owns (positions, masks, hash grids, networks,
  header: "shared") are given beside it with the file's total (:func:`file_bit_split`), since
  two methods can split a file very differently between the two.

Written per view and rate point: the single images at the view's size (``gt.png``,
``<method>-render.png``, ``<method>-error.png``, ``<method>-bits.png``, and the arrays as
``.npy``; the error and bit maps each with its colour bar and unit) and one matplotlib panel
with colour bars (``panel.png``) that the report embeds.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import torch

from baseline.fileio import atomic_path


def project_pixels(xyz: torch.Tensor, cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates (x, y) [N] of points ``xyz`` [N,3] and whether each lies in front of
    the near plane (the rasterizer's pinhole convention: pixel centres at integer + 0.5)."""
    vm = cam.viewmat.to(torch.float64)
    p = xyz.double() @ vm[:3, :3].T + vm[:3, 3]
    z = p[:, 2]
    front = z > cam.near
    zs = torch.where(front, z, torch.ones_like(z))
    u = cam.fx * p[:, 0] / zs + cam.cx
    v = cam.fy * p[:, 1] / zs + cam.cy
    return u.numpy(), v.numpy(), front.numpy()


@torch.no_grad()
def bit_map(dec, cam, bits: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(map [H,W] float64, shown [N] bool)``: the coded bits of the anchors the view shows
    (prefilter-visible, centre inside the image) summed at their centre pixels."""
    from baseline.pipeline import visible_anchors

    model = dec.model
    vis = torch.zeros(model.n_anchors, dtype=torch.bool)
    vis[visible_anchors(model, cam).cpu()] = True
    u, v, front = project_pixels(model.xyz.detach().cpu(), cam)
    px, py = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    shown = (vis.numpy() & front & (px >= 0) & (px < cam.width) & (py >= 0)
             & (py < cam.height))
    out = np.zeros((cam.height, cam.width), np.float64)
    np.add.at(out, (py[shown], px[shown]), bits.numpy()[shown])
    return out, shown


def _png(path: Path, img: np.ndarray) -> None:
    from baseline.data.images import write_png_atomic

    write_png_atomic(path, img)


@torch.no_grad()
def view_panel(entries: list[tuple[str, Path]], scene, view: int, out_dir: Path,
               title: str = "") -> dict:
    """One panel for test view ``view`` from decoded files ``[(label, path)]``; returns
    ``{"panel": path, "images": {...}, "bits_shown": {label: total}, "error_vmax": ...}``."""
    from baseline.modelfile import coded_bits_per_anchor, decode_model
    from baseline.eval.metrics import to_uint8
    from baseline.pipeline import render_view

    cams = scene.test_cameras or scene.train_cameras
    cam = cams[view]
    out_dir.mkdir(parents=True, exist_ok=True)
    gt = to_uint8(scene.image(cam))
    _png(out_dir / "gt.png", gt)
    np.save(out_dir / "gt.npy", gt)
    rows, images = [], {"gt": str(out_dir / "gt.png")}
    bg = scene.background.float()
    for label, path in entries:
        dec = decode_model(path)
        dec.model.to("cpu")
        img = to_uint8(render_view(dec.model, cam, bg, phase="decoded", backend="cpu").render.image)
        err = np.abs(img.astype(np.float64) - gt.astype(np.float64)).mean(axis=2)
        per_anchor = coded_bits_per_anchor(dec)
        bmap, shown = bit_map(dec, cam, per_anchor)
        safe = "".join(c if c.isalnum() or c in "+-_." else "_" for c in label)
        _png(out_dir / f"{safe}-render.png", img)
        np.save(out_dir / f"{safe}-error.npy", err)
        np.save(out_dir / f"{safe}-bits.npy", bmap)
        images[label] = {k: str(out_dir / f"{safe}-{k}.png") for k in ("render", "error", "bits")}
        rows.append((label, img, err, bmap, int(shown.sum()),
                     file_bit_split(path, per_anchor)))
    evmax = max((float(np.percentile(r[2], 99.5)) for r in rows), default=1.0) or 1.0
    bvmax = max((float(np.percentile(r[3][r[3] > 0], 99)) if (r[3] > 0).any() else 0.0
                 for r in rows), default=1.0) or 1.0
    for label, img, err, bmap, _, _ in rows:
        _scaled_png(Path(images[label]["error"]), err, evmax, "inferno",
                    "|render - GT| (grey levels)")
        _scaled_png(Path(images[label]["bits"]), bmap, bvmax, "viridis",
                    "per-anchor coded bits per pixel")
    panel = out_dir / "panel.png"
    _draw(panel, gt, rows, evmax, bvmax, title or f"view {view} ({cam.name})")
    return {"panel": str(panel), "images": images, "view": view, "camera": cam.name,
            "bits_shown": {r[0]: float(r[3].sum()) for r in rows},
            "anchors_shown": {r[0]: r[4] for r in rows},
            "file_bits": {r[0]: r[5] for r in rows},
            "error_vmax": evmax, "bits_vmax": bvmax}


def file_bit_split(path: Path, per_anchor_bits: torch.Tensor) -> dict:
    """What a bit map shows of its file: ``per_anchor`` (the coded attributes' bits of every
    anchor, the map's currency), ``shared`` (everything else: positions, masks, hash grids,
    networks, header; no pixel to put them on) and ``file`` (bytes x 8)."""
    total = 8 * Path(path).stat().st_size
    per = float(per_anchor_bits.sum())
    return {"file": total, "per_anchor": per, "shared": total - per}


def _scaled_png(path: Path, values: np.ndarray, vmax: float, cmap: str, label: str) -> None:
    """A single map as a PNG at about its own size, with its colour bar and unit (the arrays
    themselves are beside it as ``.npy``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    h, w = values.shape
    dpi = 100
    fig = Figure(figsize=(max(w, 160) / dpi + 1.3, max(h, 120) / dpi + 0.3), dpi=dpi,
                 layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.set_xticks([])
    ax.set_yticks([])
    im = ax.imshow(values, cmap=cmap, vmin=0, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.9, label=label)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight", pad_inches=0.05)


def _draw(path: Path, gt, rows, evmax: float, bvmax: float, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    h, w = gt.shape[:2]
    n = len(rows)
    cw = 3.2
    fig = Figure(figsize=(cw * (n + 1) + 1.0, cw * h / w * 3 + 1.2), dpi=110,
                 layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, n + 1, squeeze=False)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0][0].imshow(gt)
    axes[0][0].set_title("ground truth", fontsize=9)
    axes[1][0].axis("off")
    axes[2][0].axis("off")
    im_e = im_b = None
    for j, (label, img, err, bmap, shown, split) in enumerate(rows, start=1):
        axes[0][j].imshow(img)
        axes[0][j].set_title(label, fontsize=9)
        im_e = axes[1][j].imshow(err, cmap="inferno", vmin=0, vmax=evmax)
        axes[1][j].set_title(f"|error| mean {err.mean():.2f}", fontsize=8)
        im_b = axes[2][j].imshow(bmap, cmap="viridis", vmin=0, vmax=bvmax,
                                 interpolation="nearest")
        kib = 8 * 1024
        axes[2][j].set_title(f"here: {bmap.sum() / kib:.1f} KiB of per-anchor bits, {shown} anchors\n"
                             f"file {split['file'] / kib:.0f} KiB = per-anchor "
                             f"{split['per_anchor'] / kib:.0f} + shared {split['shared'] / kib:.0f} "
                             f"({100 * split['shared'] / split['file']:.0f}%)", fontsize=7)
    if im_e is not None:
        fig.colorbar(im_e, ax=list(axes[1][1:]), shrink=0.9,
                     label="|render - GT| (grey levels)")
        fig.colorbar(im_b, ax=list(axes[2][1:]), shrink=0.9,
                     label="per-anchor coded bits per pixel")
    fig.suptitle(title, fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def write_panels(results: dict, out_dir: str | Path, views: Optional[list[int]] = None) -> list:
    """Panels of ``results`` (a comparison's) into ``out_dir/panels``: for each rate point
    (the first seed of each lambda) and each view in ``views`` (test-view indices; default
    ``[0]``), every method whose ``model.pgs`` is present. Returns the panels' records; runs
    reported from archived records (no model file) are left out and named."""
    from baseline.eval.report.names import label, method_names, runs_of
    from baseline.run import load_scene_for

    views = [0] if views is None else list(views)
    if not views or not results.get("runs"):
        return []
    lams = sorted({r["lmbda"] for r in results["runs"]})
    out, scene = [], None
    for lm in lams:
        entries, missing = [], []
        for m in method_names(results):
            rs = [r for r in runs_of(results, m) if r["lmbda"] == lm]
            if not rs:
                continue
            r = rs[0]                                   # the lowest seed
            f = Path(r["run_dir"]) / "model.pgs"
            (entries if f.exists() else missing).append((label(results, m), f))
        if not entries:
            continue
        if scene is None:
            from baseline.modelfile import decode_model

            cfg = decode_model(entries[0][1]).cfg
            scene = load_scene_for(cfg, results["scene"], progress=False)
        n_views = len(scene.test_cameras or scene.train_cameras)
        for v in views:
            if not 0 <= v < n_views:
                raise ValueError(f"panel view {v} out of range: the scene has {n_views} "
                                 f"test views")
            d = Path(out_dir) / "panels" / f"l{lm:g}-v{v}"
            rec = view_panel(entries, scene, v, d, title=f"lambda {lm:g}, test view {v}")
            rec.update(lmbda=lm, missing=[m for m, _ in missing])
            out.append(rec)
    return out
