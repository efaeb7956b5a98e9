"""Gaussian census: where a model's rendered Gaussians come from, and whether they are needed.

For each view, a visible anchor offers K candidate Gaussians; a candidate is rendered when its
mask is on and its opacity is above 0 (Scaffold-GS's rule). The census splits that count:

* ``kept_share``: rendered / mask-on candidates (the opacity test's pass rate), and the same
  with the refiner's corrections switched off (``kept_share_coarse``, the Gaussians the
  provider's features alone would draw; equal to ``kept_share`` for a model without refiner),
  with the candidates the corrections add (``revived``) and remove (``removed``);
* ``kept_per_anchor``: visible anchors by how many of their K Gaussians are drawn (0..K);
* ``pattern_equal_nn``: how often a visible anchor's K-slot rendered/not pattern equals its
  nearest visible neighbour's, beside the same for a random visible anchor
  (``pattern_equal_random``; patterns shared by chance), and the mean Hamming distances;
  anchors with every mask off are left out;
* ``by_birth``: the kept share of the initial anchors and of the grown ones (for a training
  whose hooks declare stages, :meth:`~baseline.contracts.TrainingHook.stage_starts`: grown in
  each stage); only for a run folder of a training that kept its anchors' births (a ``.pgs``
  file does not carry them);
* ``sweep``: the test views rendered with the opacity threshold raised (Gaussians per view and
  PSNR at each), so that :func:`psnr_at_gaussians` tells the PSNR a model keeps when its count
  is cut to another model's, i.e. whether its extra Gaussians are dead weight; and
  ``psnr_coarse``: the PSNR with the corrections off.

Counts are summed over the views (shares are of the sums); ``views`` keeps the per-view kept
shares. Everything is measured on the anchors as the codec stores them (a run folder's coded
state, or the decoded file), so the threshold-0 PSNR is the evaluation's.
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from baseline import registry
from baseline.eval.metrics import psnr, to_uint8
from baseline.render import prefilter_anchors, rasterize

DEFAULT_THRESHOLDS = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3)


def _view_anchors(model, cam, coded):
    """(idx [M], values {name: [M,d]}, xyz [M,3]) of the anchors visible from ``cam``, as the
    codec stores them."""
    if coded is not None:
        vis = prefilter_anchors(coded.xyz, coded.values["scaling"][:, :3], cam)
        return coded.index[vis], {k: v[vis] for k, v in coded.values.items()}, coded.xyz[vis]
    if model.fixed_values is None:
        raise ValueError("the census needs a decoded model or a trained run in its adaptive phase")
    scales = torch.exp(model.per_anchor["scaling"][:, :3])
    idx = prefilter_anchors(model.positions(), scales, cam).nonzero()[:, 0]
    return idx, model.coded_values(idx), model.positions(idx)


def _pattern_stats(xyz: np.ndarray, bits: np.ndarray, rng: np.random.Generator) -> dict:
    """Nearest-neighbour vs random-partner agreement of the K-slot patterns ``bits`` [M,K]."""
    from scipy.spatial import cKDTree

    m = len(xyz)
    if m < 2:
        return {"pairs": 0, "equal_nn": 0, "equal_random": 0, "hamming_nn": 0, "hamming_random": 0}
    _, nn = cKDTree(xyz).query(xyz, k=2)
    nn = nn[:, 1]
    other = rng.integers(0, m - 1, size=m)
    other = other + (other >= np.arange(m))          # a random anchor other than itself
    ham_nn = (bits != bits[nn]).sum(1)
    ham_rand = (bits != bits[other]).sum(1)
    return {"pairs": m, "equal_nn": int((ham_nn == 0).sum()), "equal_random": int((ham_rand == 0).sum()),
            "hamming_nn": int(ham_nn.sum()), "hamming_random": int(ham_rand.sum())}


def _birth_buckets(model, cfg) -> Optional[tuple[list[str], torch.Tensor]]:
    """Names and a per-anchor bucket index from the anchors' births; None when unknown."""
    birth = model.per_anchor["birth"] if "birth" in model.per_anchor else None
    if birth is None or model.fixed_values is not None or bool((birth < 0).any()):
        return None
    bucket = (birth > 0).long()
    names = ["initial", "grown"]
    starts = sorted({s for h in (cfg.train.hooks if cfg is not None else ())
                     for s in registry.component_class("hooks", h).stage_starts(cfg)})
    if len(starts) == 1:                # a training of two stages: grown in each
        stage2 = starts[0]
        bucket = torch.where(birth > stage2, torch.full_like(bucket, 2), bucket)
        names = ["initial", f"grown <= it {stage2} (stage 1)", f"grown > it {stage2}"]
    return names, bucket


@torch.no_grad()
def census(model, scene, cameras, *, coded=None, cfg=None, backend: str = "auto",
           thresholds: Sequence[float] = DEFAULT_THRESHOLDS, seed: int = 0) -> dict:
    """The census of ``model`` over ``cameras`` (see the module docstring).

    ``coded``: a trained run's :class:`~baseline.pipeline.CodedState` (else ``model`` must be a
    decoded one). ``cfg``: the run's config (births split by stage). Returns a JSON-able dict.
    """
    refiner = model.refiner
    has_refiner = refiner is not None and refiner.active
    baked = model.baked
    if baked is not None:       # the census reads the heads' raw outputs: the plain form
        model.unbake()
    buckets = _birth_buckets(model, cfg)
    rng = np.random.default_rng(seed)
    bg = scene.background.float().to(model.xyz.device)
    thresholds = sorted({float(t) for t in thresholds} | {0.0})
    tot = dict(visible=0, mask_on=0, kept=0, kept_coarse=0, revived=0, removed=0)
    pat = dict(pairs=0, equal_nn=0, equal_random=0, hamming_nn=0, hamming_random=0)
    pat_coarse = dict(pat)
    K = model.n_offsets
    hist = np.zeros(K + 1, np.int64)          # visible anchors by their number of kept Gaussians
    nb = len(buckets[0]) if buckets else 0
    b_on, b_kept = np.zeros(nb, np.int64), np.zeros(nb, np.int64)
    sweep_g = np.zeros(len(thresholds))
    sweep_p: list[list[float]] = [[] for _ in thresholds]
    coarse_p: list[float] = []
    views = []
    try:
        for cam in cameras:
            idx, values, xyz = _view_anchors(model, cam, coded)
            gt = to_uint8(scene.image(cam))
            on = model.gaussian_mask(idx) > 0                               # [M,K]
            kept = (model.raw_heads(cam.center, idx, values, xyz).opacity() > 0) & on
            if has_refiner:
                refiner.active = False
                op0 = model.raw_heads(cam.center, idx, values, xyz).opacity()
                g0 = model.decode(cam.center, idx, values, xyz=xyz)
                out0 = rasterize(g0.means, g0.quats, g0.scales, g0.opacities, g0.colors, cam,
                                 background=bg, backend=backend)
                coarse_p.append(psnr(to_uint8(out0.image), gt))
                refiner.active = True
                kept0 = (op0 > 0) & on
            else:
                kept0 = kept
            n_on, n_kept = int(on.sum()), int(kept.sum())
            tot["visible"] += len(idx)
            tot["mask_on"] += n_on
            tot["kept"] += n_kept
            tot["kept_coarse"] += int(kept0.sum())
            tot["revived"] += int((kept & ~kept0).sum())
            tot["removed"] += int((kept0 & ~kept).sum())
            views.append({"camera": cam.name, "kept_share": n_kept / n_on if n_on else None,
                          "kept_share_coarse": int(kept0.sum()) / n_on if n_on else None})
            valid = on.any(1)
            hist += np.bincount(kept.sum(1).cpu().numpy(), minlength=K + 1)
            pts = xyz[valid].cpu().numpy().astype(np.float64)
            for acc, bits in ((pat, kept), (pat_coarse, kept0)):
                for k, v in _pattern_stats(pts, bits[valid].cpu().numpy(), rng).items():
                    acc[k] += v
            if buckets:
                b = buckets[1][idx].cpu()
                b_on += np.bincount(b.numpy(), weights=on.sum(1).cpu().numpy(), minlength=nb).astype(np.int64)
                b_kept += np.bincount(b.numpy(), weights=kept.sum(1).cpu().numpy(), minlength=nb).astype(np.int64)
            for i, t in enumerate(thresholds):
                g = model.decode(cam.center, idx, values, xyz=xyz, opacity_floor=t)
                out = rasterize(g.means, g.quats, g.scales, g.opacities, g.colors, cam,
                                background=bg, backend=backend)
                sweep_g[i] += g.means.shape[0]
                sweep_p[i].append(psnr(to_uint8(out.image), gt))
    finally:
        if has_refiner:
            refiner.active = True
        if baked is not None:
            model.baked = baked
    n = max(len(cameras), 1)

    def share(a, b):
        return a / b if b else None

    def pattern(acc):
        return {"anchors": acc["pairs"] // n, "equal_nn": share(acc["equal_nn"], acc["pairs"]),
                "equal_random": share(acc["equal_random"], acc["pairs"]),
                "hamming_nn": share(acc["hamming_nn"], acc["pairs"] * K),
                "hamming_random": share(acc["hamming_random"], acc["pairs"] * K)}

    res = {
        "views": len(cameras), "k": K, "refiner": bool(has_refiner),
        "visible_anchors": tot["visible"] / n, "mask_on_share": share(tot["mask_on"], tot["visible"] * K),
        "gaussians": tot["kept"] / n,
        "kept_share": share(tot["kept"], tot["mask_on"]),
        "kept_share_coarse": share(tot["kept_coarse"], tot["mask_on"]),
        "revived_share": share(tot["revived"], tot["mask_on"]),
        "removed_share": share(tot["removed"], tot["mask_on"]),
        "kept_per_anchor": [int(x) for x in hist],
        "pattern": pattern(pat),
        "pattern_coarse": pattern(pat_coarse) if has_refiner else None,
        "by_birth": ({name: {"mask_on": int(b_on[i]), "kept": int(b_kept[i]),
                             "kept_share": share(int(b_kept[i]), int(b_on[i]))}
                      for i, name in enumerate(buckets[0])} if buckets else None),
        "psnr_coarse": float(np.mean(coarse_p)) if coarse_p else None,
        "sweep": [{"threshold": t, "gaussians": float(sweep_g[i] / n),
                   "psnr": float(np.mean(sweep_p[i])) if sweep_p[i] else None}
                  for i, t in enumerate(thresholds)],
        "view_kept_share": views,
    }
    return res


def psnr_at_gaussians(sweep: list[dict], target: float) -> Optional[float]:
    """PSNR of a census sweep interpolated (linearly in the Gaussian count) at ``target``
    Gaussians per view; None when ``target`` is outside the swept counts."""
    pts = sorted((s["gaussians"], s["psnr"]) for s in sweep if s.get("psnr") is not None)
    if not pts or target < pts[0][0] or target > pts[-1][0]:
        return None
    g = np.array([p[0] for p in pts])
    p = np.array([p[1] for p in pts])
    return float(np.interp(target, g, p))


def census_of(target: str, thresholds: Optional[Sequence[float]] = None,
              device: Optional[str] = None) -> dict:
    """The census of a run folder (its coded state; births when kept) or a ``.pgs`` file, on
    its scene's test views (training views when it has none)."""
    from baseline.run import Renderable

    r = Renderable(target, device=device)
    if r.phase not in ("decoded", "adaptive"):
        raise ValueError(f"{target}: the census needs a finished training (phase 'adaptive') "
                         f"or a .pgs file, not a run in phase '{r.phase}'")
    cams = r.scene.test_cameras or r.scene.train_cameras
    res = census(r.model, r.scene, cams, coded=r.coded, cfg=r.cfg,
                 backend=r.cfg.train.rasterizer, thresholds=thresholds or DEFAULT_THRESHOLDS)
    res["target"] = str(target)
    return res


def _hist_parts(hist: list[int]) -> list[float]:
    h = np.asarray(hist, np.float64)
    t = max(h.sum(), 1.0)
    return [h[0] / t, h[1:4].sum() / t, h[4:8].sum() / t, h[8:].sum() / t]


def format_census(results: list[dict]) -> str:
    """A plain-text table of censuses (one column each); with two or more, the PSNR each keeps
    when cut to the first one's Gaussians per view."""
    def pct(x):
        return "-" if x is None else f"{100 * x:.1f}%"

    def num(x, f="{:.3f}"):
        return "-" if x is None else f.format(x)

    rows = [("views", lambda r: str(r["views"])),
            ("visible anchors / view", lambda r: f"{r['visible_anchors']:.0f}"),
            ("masks on (of visible x K)", lambda r: pct(r["mask_on_share"])),
            ("Gaussians / view", lambda r: f"{r['gaussians']:.0f}"),
            ("kept share (opacity > 0 of mask-on)", lambda r: pct(r["kept_share"])),
            ("  corrections off", lambda r: pct(r["kept_share_coarse"]) if r["refiner"] else "-"),
            ("  revived / removed by corrections", lambda r: (f"{pct(r['revived_share'])} / "
                                                          f"{pct(r['removed_share'])}") if r["refiner"] else "-"),
            ("visible anchors drawing 0 / 1-3 / 4-7 / 8+ Gaussians", lambda r: " / ".join(
                pct(x) for x in _hist_parts(r["kept_per_anchor"]))),
            ("K-slot pattern = nearest neighbour's", lambda r: pct(r["pattern"]["equal_nn"])),
            ("  = a random anchor's", lambda r: pct(r["pattern"]["equal_random"])),
            ("  Hamming nn / random", lambda r: f"{pct(r['pattern']['hamming_nn'])} / "
                                                f"{pct(r['pattern']['hamming_random'])}"),
            ("  corrections off: = nn / = random", lambda r: (
                f"{pct(r['pattern_coarse']['equal_nn'])} / {pct(r['pattern_coarse']['equal_random'])}")
                if r["pattern_coarse"] else "-"),
            ("PSNR (threshold 0)", lambda r: num(r["sweep"][0]["psnr"])),
            ("PSNR, corrections off", lambda r: num(r["psnr_coarse"]))]
    names = set()
    for r in results:
        names |= set((r.get("by_birth") or {}).keys())
    for name in sorted(names, key=lambda s: (s != "initial", s)):
        rows.append((f"kept share, {name} anchors",
                     lambda r, name=name: (f"{pct(r['by_birth'][name]['kept_share'])} of "
                                           f"{r['by_birth'][name]['mask_on']}") if r.get("by_birth") and name in r["by_birth"] else "-"))
    for i, s in enumerate(results[0]["sweep"]):
        t = s["threshold"]
        rows.append((f"threshold {t:g}: Gaussians / PSNR",
                     lambda r, t=t: next((f"{x['gaussians']:.0f} / {num(x['psnr'])}"
                                          for x in r["sweep"] if x["threshold"] == t), "-")))
    if len(results) > 1:
        ref = results[0]["gaussians"]
        rows.append((f"PSNR cut to {ref:.0f} Gaussians / view",
                     lambda r: num(psnr_at_gaussians(r["sweep"], ref))))
    head = ["", *[r.get("label", r.get("target", "?")) for r in results]]
    table = [head] + [[name, *[fn(r) for r in results]] for name, fn in rows]
    w = [max(len(str(row[i])) for row in table) for i in range(len(head))]
    return "\n".join("  ".join(str(c).ljust(w[i]) for i, c in enumerate(row)) for row in table)
