"""``pgs bench fps``: rendering speed of decoded models against a reference, in one process.

FPS taken by ``pgs compare`` is one pass over the test views per run, measured whenever the run
finished; on a 2-core machine the same decoded file measured at two times gave 2.9 and 5.1 FPS, so
the ratio of two such figures is not a measurement. This bench decodes every file first, then
renders the same views with each model in turn, several rounds, the order rotated every round
(so neither a warm-up nor a slow drift of the machine favours one model), and reports each
model's FPS as the median over rounds and its speed ratio to the first model from the per-round
pairs (median, min and max).

Every model is timed in up to three forms (``Contender.form``), set up outside the timed frames:
``plain`` (:meth:`AnchorModel.decode`; a provider that can cache its per-anchor features,
with its cache: how a decoded model renders), ``baked``
(:mod:`baseline.scaffold.baked`: the view-independent part of every decoder head computed once)
and, for a provider with a cache, ``no cache`` (features recomputed every view). Besides the
ratio to the first contender, each row has its ratio to the first model in the same form (its
``plain`` form where it has no such form), so engines compare like with like, and the largest
difference of its images from its model's ``plain`` form's (:func:`form_image_differences`):
speed beside what it changes in the frames.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence

import torch

from baseline.modelfile import decode_model
from baseline.contracts import feature_cache
from baseline.modelfile import MODEL_FILE
from baseline.pipeline import render_view


@dataclass
class Contender:
    label: str
    model: object
    cache: Optional[bool]        # None: the provider has no cache; True / False: with / without
    form: str = "plain"          # plain | baked | no cache
    baked: object = None         # the BakedDecoder rendered with (form baked)
    model_index: int = 0         # which model (contenders of one model share it)


def resolve_model_file(path: str | Path) -> Path:
    """A ``.pgs`` file, or a run folder holding ``model.pgs`` (what ``pgs compare`` writes)."""
    p = Path(path)
    if p.is_dir():
        p = p / MODEL_FILE
    if not p.is_file():
        raise FileNotFoundError(f"{path}: no such .pgs file (nor a run folder with {MODEL_FILE}; "
                                f"encode it first: pgs encode RUN -o FILE.pgs)")
    return p


def contenders_of(label: str, model, *, model_index: int = 0) -> List[Contender]:
    """The forms to time of one decoded model (see the module doc): plain, baked (when the
    model can be baked), no cache (when its provider has one)."""
    from baseline.scaffold.baked import BakedDecoder

    cached = feature_cache(model) is not None
    if cached:
        _set_cache(model, True)
    out = [Contender(label, model, True if cached else None, "plain", model_index=model_index)]
    baked = BakedDecoder.from_model(model)
    if baked is not None:
        out.append(Contender(f"{label} (baked)", model, out[0].cache, "baked", baked,
                             model_index))
    if cached:
        out.append(Contender(f"{label} (no cache)", model, False, "no cache",
                             model_index=model_index))
    return out


def _set_cache(model, on: Optional[bool]) -> None:
    """Build (on) or drop (off) the model's feature cache, outside the timed frames."""
    if on is None:
        return
    prov = feature_cache(model)
    if on:
        prov.build_cache(model.xyz)
    else:
        prov.clear_cache()


def _prepare(c: Contender) -> None:
    """Put the model in the contender's form (cache, bake), outside the timed frames."""
    _set_cache(c.model, c.cache)
    c.model.baked = c.baked


@torch.no_grad()
def _time_views(c: Contender, cameras, background, backend: str) -> tuple[float, float]:
    """Mean seconds per view (prefilter + Gaussian decoding + rasterization) and mean Gaussians."""
    sync = torch.cuda.synchronize if c.model.xyz.is_cuda else (lambda *a: None)
    total, count = 0.0, 0
    for cam in cameras:
        sync()
        t0 = time.perf_counter()
        res = render_view(c.model, cam, background, phase="decoded", training=False,
                          backend=backend)
        sync()
        total += time.perf_counter() - t0
        count += int(res.gaussians.means.shape[0])
    return total / len(cameras), count / len(cameras)


def _restore(contenders: Sequence[Contender]) -> None:
    """Leave the models as decoded: the feature cache on, not baked."""
    for c in contenders:
        if c.cache is False:
            _set_cache(c.model, True)
        c.model.baked = None


@torch.no_grad()
def form_image_differences(contenders: Sequence[Contender], cameras, background: torch.Tensor,
                           backend: str = "auto", chunk: int = 8) -> List[Optional[float]]:
    """Per contender, the largest absolute difference between its rendered images and its
    model's ``plain`` form's on ``cameras`` (None for a plain contender or a model without
    one): what a faster form changes in the frames. Untimed. The views go ``chunk`` at a time:
    the plain images of a chunk are kept while each other form renders it, so memory does not
    grow with the number of views and each form is set up once per chunk (setting up the
    uncached form drops a feature cache the plain form then rebuilds). NaN if any compared
    pixel is NaN."""
    plain = {c.model_index: i for i, c in enumerate(contenders) if c.form == "plain"}
    others = {mi: [i for i, c in enumerate(contenders) if c.model_index == mi and i != p]
              for mi, p in plain.items()}
    worst: List[Optional[torch.Tensor]] = [None] * len(contenders)
    for ids in others.values():
        for i in ids:
            worst[i] = torch.zeros(())

    def images(c: Contender, cams) -> list:
        _prepare(c)
        return [render_view(c.model, cam, background, phase="decoded",
                            backend=backend).render.image for cam in cams]

    step = max(chunk, 1)
    for s in range(0, len(cameras), step):
        cams = cameras[s:s + step]
        for mi, ids in others.items():
            if not ids:
                continue
            refs = images(contenders[plain[mi]], cams)
            for i in ids:
                for img, ref in zip(images(contenders[i], cams), refs):
                    worst[i] = torch.maximum(worst[i], (img - ref).abs().max().cpu())
    _restore(contenders)
    return [None if w is None else float(w) for w in worst]


def run_fps_bench(contenders: Sequence[Contender], cameras, background: torch.Tensor, *,
                  rounds: int = 5, backend: str = "auto", warmup: bool = True) -> List[dict]:
    """Time every contender on ``cameras``, ``rounds`` times, in an order rotated each round.

    Args:
        contenders: the first is the reference of the ratios.
        cameras: the views (the same for all contenders).
        background: [3] on the models' device.

    Returns:
        One dict per contender: ``label, gaussians_per_view, fps`` (1 / median over rounds of
        the mean time per view), ``fps_min, fps_max`` (over rounds), ``ratio, ratio_min,
        ratio_max`` (per round: reference time / this time, i.e. > 1 = faster than the
        reference; median, min, max), ``form``, ``ratio_form, ratio_form_min, ratio_form_max``
        and ``ref_form`` (the same against the first model's contender in this form, or in
        its plain form), ``seconds`` ([rounds] mean time per view).
    """
    if not contenders:
        raise ValueError("fps bench: no model to time")
    if not cameras:
        raise ValueError("fps bench: the scene has no view to render")
    if rounds < 1:
        raise ValueError(f"fps bench: rounds must be >= 1, got {rounds}")
    n = len(contenders)
    times = [[0.0] * rounds for _ in range(n)]
    gaussians = [0.0] * n
    if warmup:      # compile kernels, fill caches, allocate: one untimed view per contender
        for c in contenders:
            _prepare(c)
            _time_views(c, cameras[:1], background, backend)
    for r in range(rounds):
        for j in range(n):
            i = (j + r) % n
            _prepare(contenders[i])
            times[i][r], gaussians[i] = _time_views(contenders[i], cameras, background, backend)
    _restore(contenders)
    ref_of_form = {}                # form -> the reference model's contender in that form
    for i, c in enumerate(contenders):
        if c.model_index == contenders[0].model_index:
            ref_of_form.setdefault(c.form, i)
    rows = []
    for i, c in enumerate(contenders):
        ratios = [times[0][r] / times[i][r] for r in range(rounds)]
        f = ref_of_form.get(c.form, ref_of_form.get("plain", 0))
        same = [times[f][r] / times[i][r] for r in range(rounds)]
        rows.append(dict(label=c.label, form=c.form, gaussians_per_view=gaussians[i],
                         fps=1.0 / statistics.median(times[i]), fps_min=1.0 / max(times[i]),
                         fps_max=1.0 / min(times[i]), ratio=statistics.median(ratios),
                         ratio_min=min(ratios), ratio_max=max(ratios),
                         ratio_form=statistics.median(same), ratio_form_min=min(same),
                         ratio_form_max=max(same), ref_form=contenders[f].label,
                         seconds=list(times[i])))
    return rows


def _scene_key(cfg, scene_path: str) -> tuple:
    d = cfg.data
    return (str(Path(scene_path).resolve()), d.resolution, d.images, d.eval, d.test_every,
            d.background)


def bench_files(paths: Sequence[str], *, scene: Optional[str] = None, rounds: int = 5,
                threads: Optional[int] = None, device: str = "cpu",
                max_views: Optional[int] = None) -> dict:
    """Decode each file (or run folder) and time them on the test views of their common scene.

    The scene comes from ``scene`` or from each file's header (``pgs compare`` and ``pgs encode``
    record it); all files must render the same views (scene, resolution, split, background).
    """
    from baseline.render import cpu as cpu_backend

    old_threads, old_cpu_threads = torch.get_num_threads(), cpu_backend._THREADS
    if threads:
        torch.set_num_threads(int(threads))
        cpu_backend.set_num_threads(int(threads))
    try:
        return _bench_files(paths, scene, rounds, device, max_views)
    finally:
        torch.set_num_threads(old_threads)
        cpu_backend.set_num_threads(old_cpu_threads)


def bench_labels(paths) -> List[str]:
    """One label per ``--run`` path: the run folder's name, or the file's stem; where two would
    read the same (``A/model.pgs`` and ``B/model.pgs``), the parent folders that tell them apart
    are kept (``A/model``, ``B/model``); a path given twice gets a prime."""
    parts = []
    for p in paths:
        q = Path(p)
        q = q if q.is_dir() else q.with_suffix("")
        parts.append([x for x in q.absolute().parts if x not in ("", "/")])
    labels = []
    for i, ps in enumerate(parts):
        k = 1
        others = [o for j, o in enumerate(parts) if j != i and o != ps]
        while k < len(ps) and any(o[-k:] == ps[-k:] for o in others):
            k += 1
        labels.append("/".join(ps[-k:]))
    seen, out = set(), []
    for lab in labels:
        while lab in seen:
            lab += "'"
        seen.add(lab)
        out.append(lab)
    return out


def _decode_files(paths, scene, device, max_views):
    """Decode each file (or run folder): ``(decoded [(label, DecodedModel)], cameras,
    background, backend, scene path, device)``; all files must render the same views."""
    from baseline.device import resolve_device
    from baseline.run import load_scene_for

    if not paths:
        raise ValueError("bench: give at least one --run (a .pgs file or a run folder)")
    dev = resolve_device(device)
    decoded, key0 = [], None
    for p in paths:
        f = resolve_model_file(p)
        dec = decode_model(f)
        sp = scene or dec.scene_path
        if not sp:
            raise ValueError(f"{f}: the file does not name its scene; pass --scene PATH")
        key = _scene_key(dec.cfg, sp)
        if key0 is None:
            key0, cfg0, scene_path0 = key, dec.cfg, sp
        elif key != key0:
            raise ValueError(f"bench: models are compared on the same views: {f} renders {key}, "
                             f"the first file {key0}")
        dec.model.to(dev)
        decoded.append(dec)
    decoded = list(zip(bench_labels(paths), decoded))
    sc = load_scene_for(cfg0, scene_path0, progress=False)
    cams = list(sc.test_cameras or sc.train_cameras)
    if max_views:
        cams = cams[:max_views]
    bg = sc.background.float().to(dev)
    split = "test" if sc.test_cameras else "train"
    return decoded, cams, bg, cfg0.train.rasterizer, scene_path0, dev, split


def _bench_files(paths, scene, rounds, device, max_views) -> dict:
    from baseline.device import device_name
    from baseline.render import resolve_backend

    decoded, cams, bg, backend, scene_path0, dev, split = _decode_files(paths, scene, device,
                                                                        max_views)
    contenders = [c for k, (label, dec) in enumerate(decoded)
                  for c in contenders_of(label, dec.model, model_index=k)]
    rows = run_fps_bench(contenders, cams, bg, rounds=rounds, backend=backend)
    for r, d in zip(rows, form_image_differences(contenders, cams, bg, backend)):
        r["max_image_diff"] = d
    return dict(rows=rows, views=len(cams), split=split,
                rounds=rounds, threads=torch.get_num_threads(), device=device_name(dev),
                backend=resolve_backend(backend, decoded[0][1].model.xyz),
                scene=scene_path0, size=f"{cams[0].width}x{cams[0].height}")


# ------------------------------------------------------------------------------ pgs bench frame
FRAME_STAGES = ("prefilter", "decode", "rasterize")


@torch.no_grad()
def time_frame_stages(model, cameras, background, *, rounds: int = 3,
                      backend: str = "auto") -> dict:
    """Seconds per view of each stage of a decoded frame, the current code against its
    reference form in one process (alternating, the order swapped every round):

    * ``prefilter``: :func:`prefilter_anchors` (closed form) vs its matrix form;
    * ``decode``: :meth:`AnchorModel.decode` (keeps the Gaussians, then activates them) vs
      :func:`decode_all_then_select`;
    * ``rasterize``: the kept Gaussians through the backend (one form; for the frame's share);
    * ``baked``: :class:`~baseline.scaffold.baked.BakedDecoder` decoding vs ``decode`` (a model
      that can be baked only; not part of the frame total: the frame as the model renders);
    * ``refiner``: the refiner's heads alone (view-dependent: run on every visible
      anchor), a share of ``decode``; models with an active refiner only.

    Returns ``{stage: {"new": [rounds] s/view, "ref": [rounds] s/view or None}}``, plus
    ``gaussians`` per view. On every view the two prefilters must choose the same anchors and
    the two decodings keep the same Gaussians at the same positions (else AssertionError).
    """
    from baseline.pipeline import visible_anchors
    from baseline.render import rasterize
    from baseline.render.prefilter import prefilter_anchors, prefilter_anchors_matrix_form
    from baseline.scaffold.model import decode_all_then_select, view_inputs

    sync = torch.cuda.synchronize if model.xyz.is_cuda else (lambda *a: None)

    def timed(fn):
        sync()
        t0 = time.perf_counter()
        out = fn()
        sync()
        return out, time.perf_counter() - t0

    from baseline.scaffold.baked import BakedDecoder

    res = {k: {"new": [0.0] * rounds, "ref": [0.0] * rounds} for k in FRAME_STAGES}
    res["rasterize"]["ref"] = None
    baked = BakedDecoder.from_model(model) if model.fixed_values is not None else None
    if baked is not None:
        res["baked"] = {"new": [0.0] * rounds, "ref": [0.0] * rounds}
    refiner = model.refiner is not None and model.refiner.active
    if refiner:
        res["refiner"] = {"new": [0.0] * rounds, "ref": None}
    n_gauss = 0
    xyz = model.xyz.detach()
    scales = torch.exp(model.per_anchor["scaling"].detach()[:, :3])
    for r in range(-1, rounds):            # round -1: warm-up, untimed
        for cam in cameras:
            forms = ("new", "ref") if r % 2 == 0 else ("ref", "new")
            vis = {}
            for form in forms:
                fn = prefilter_anchors if form == "new" else prefilter_anchors_matrix_form
                vis[form], dt = timed(lambda: fn(xyz, scales, cam))
                if r >= 0:
                    res["prefilter"][form][r] += dt / len(cameras)
            if not torch.equal(vis["new"], vis["ref"]):
                raise AssertionError("bench frame: the two prefilter forms disagree")
            idx = visible_anchors(model, cam)
            g = {}
            for form in forms:
                if form == "new":
                    g[form], dt = timed(lambda: model.decode(cam.center, idx))
                else:
                    g[form], dt = timed(lambda: decode_all_then_select(model, cam.center, idx))
                if r >= 0:
                    res["decode"][form][r] += dt / len(cameras)
            if not (torch.equal(g["new"].anchor_index, g["ref"]["anchor_index"])
                    and torch.allclose(g["new"].means, g["ref"]["means"])):
                raise AssertionError("bench frame: the two decode forms keep different Gaussians")
            gn = g["new"]
            if refiner:          # its heads alone (inside decode): what a refiner adds per view
                vals = model.coded_values(idx)
                vd, dist = view_inputs(model.xyz[idx], cam.center)
                _, dt = timed(lambda: model.refiner(idx, vals, vd, dist))
                if r >= 0:
                    res["refiner"]["new"][r] += dt / len(cameras)
            if baked is not None:
                gb, dt = timed(lambda: baked.decode(cam.center, idx))
                if r >= 0:
                    res["baked"]["new"][r] += dt / len(cameras)
                if not (torch.equal(gb.anchor_index, gn.anchor_index)
                        and torch.allclose(gb.means, gn.means)):
                    raise AssertionError("bench frame: baked decoding keeps other Gaussians")
            _, dt = timed(lambda: rasterize(gn.means, gn.quats, gn.scales, gn.opacities,
                                            gn.colors, cam, background=background,
                                            backend=backend))
            if r >= 0:
                res["rasterize"]["new"][r] += dt / len(cameras)
                n_gauss += int(gn.means.shape[0])
    if baked is not None:            # the baked form's reference: plain decoding, same views
        res["baked"]["ref"] = list(res["decode"]["new"])
    res["gaussians"] = n_gauss / max(1, rounds * len(cameras))
    return res


def bench_frame_files(paths: Sequence[str], *, scene: Optional[str] = None, rounds: int = 3,
                      threads: Optional[int] = None, device: str = "cpu",
                      max_views: Optional[int] = None) -> dict:
    """``pgs bench frame``: :func:`time_frame_stages` for each decoded file (cache as decoded)."""
    from baseline.device import device_name
    from baseline.render import cpu as cpu_backend
    from baseline.render import resolve_backend

    if rounds < 1:
        raise ValueError(f"frame bench: rounds must be >= 1, got {rounds}")
    old_threads, old_cpu_threads = torch.get_num_threads(), cpu_backend._THREADS
    if threads:
        torch.set_num_threads(int(threads))
        cpu_backend.set_num_threads(int(threads))
    try:
        decoded, cams, bg, backend, scene_path0, dev, split = _decode_files(paths, scene, device,
                                                                            max_views)
        models = [dict(label=label, stages=time_frame_stages(dec.model, cams, bg, rounds=rounds,
                                                             backend=backend))
                  for label, dec in decoded]
        return dict(models=models, views=len(cams), split=split, rounds=rounds,
                    threads=torch.get_num_threads(), device=device_name(dev),
                    backend=resolve_backend(backend, decoded[0][1].model.xyz),
                    scene=scene_path0, size=f"{cams[0].width}x{cams[0].height}")
    finally:
        torch.set_num_threads(old_threads)
        cpu_backend.set_num_threads(old_cpu_threads)


def format_frame_bench(res: dict) -> str:
    lines = [f"frame bench: {res['views']} {res['split']} views of {res['scene']} at "
             f"{res['size']}, {res['rounds']} rounds, {res['threads']} thread(s), "
             f"{res['device']}, backend {res['backend']}"]
    for m in res["models"]:
        lines += ["", bench_frame_format_model(m["label"], m["stages"])]
    lines.append("ms/view: median over rounds of the mean over views; reference form: the same "
                 "stage written the way it was before (prefilter with [N,3,3] covariances, "
                 "decode activating all M*K candidates before selecting), run alternately in "
                 "this process and checked equal; x ref = reference time / this time (> 1: "
                 "faster); baked dec: decoding with the view-independent head terms "
                 "precomputed (baseline/scaffold/baked.py) against decode, not in the frame "
                 "total; refiner: the refiner's heads alone, part of decode.")
    return "\n".join(lines)


def bench_frame_format_model(label: str, st: dict) -> str:
    """One model's table of :func:`time_frame_stages` results ``st``."""
    lines = [f"{label}  ({st['gaussians']:,.0f} Gaussians/view)",
             f"{'stage':<10}  {'ms/view':>8}  {'reference form':>14}  {'x ref':>6}  "
             f"{'x ref range':>11}", "-" * 57]
    tot_new = tot_ref = 0.0
    for k in FRAME_STAGES:
        new = statistics.median(st[k]["new"])
        ref = None if st[k]["ref"] is None else statistics.median(st[k]["ref"])
        tot_new += new
        tot_ref += new if ref is None else ref
        if ref is None:
            lines.append(f"{k:<10}  {1000 * new:>8.1f}  {'-':>14}  {'-':>6}  {'':>11}")
            continue
        ratios = [a / b for a, b in zip(st[k]["ref"], st[k]["new"])]
        lines.append(f"{k:<10}  {1000 * new:>8.1f}  {1000 * ref:>14.1f}  "
                     f"{statistics.median(ratios):>6.2f}  "
                     f"{min(ratios):>5.2f}-{max(ratios):<5.2f}")
    lines.append(f"{'frame':<10}  {1000 * tot_new:>8.1f}  {1000 * tot_ref:>14.1f}  "
                 f"{tot_ref / tot_new:>6.2f}")
    if "baked" in st:
        b, d = st["baked"]["new"], st["baked"]["ref"]
        ratios = [x / y for x, y in zip(d, b)]
        lines.append(f"{'baked dec':<10}  {1000 * statistics.median(b):>8.1f}  "
                     f"{1000 * statistics.median(d):>14.1f}  "
                     f"{statistics.median(ratios):>6.2f}  "
                     f"{min(ratios):>5.2f}-{max(ratios):<5.2f}  (reference: decode)")
    if "refiner" in st:
        lines.append(f"{'refiner':<10}  {1000 * statistics.median(st['refiner']['new']):>8.1f}  "
                     f"{'-':>14}  {'-':>6}  {'':>11}  (its heads alone, part of decode)")
    return "\n".join(lines)


def format_fps_bench(res: dict) -> str:
    rows = res["rows"]
    w = max(12, max(len(r["label"]) for r in rows))
    lines = [f"fps bench: {res['views']} {res['split']} views of {res['scene']} at {res['size']}, "
             f"{res['rounds']} rounds (order rotated), {res['threads']} thread(s), "
             f"{res['device']}, backend {res['backend']}",
             f"{'model':<{w}}  {'Gaussians/view':>14}  {'FPS':>7}  {'FPS range':>15}  "
             f"{'x ref':>6}  {'x ref range':>13}  {'x same form':>11}  {'range':>13}  "
             f"{'max |img - plain|':>17}",
             "-" * (w + 112)]
    for i, r in enumerate(rows):
        ref = "ref" if i == 0 else f"{r['ratio']:.3f}"
        rng = "" if i == 0 else f"{r['ratio_min']:.3f}-{r['ratio_max']:.3f}"
        same = r.get("ratio_form")
        if same is None or r.get("ref_form") == r["label"]:
            sf, sr = "ref", ""
        else:
            sf, sr = f"{same:.3f}", f"{r['ratio_form_min']:.3f}-{r['ratio_form_max']:.3f}"
        d = r.get("max_image_diff")
        dd = "-" if d is None else f"{d:.2g}"
        lines.append(f"{r['label']:<{w}}  {r['gaussians_per_view']:>14,.0f}  {r['fps']:>7.2f}  "
                     f"{r['fps_min']:>7.2f}-{r['fps_max']:<7.2f}  {ref:>6}  {rng:>13}  "
                     f"{sf:>11}  {sr:>13}  {dd:>17}")
    lines.append("FPS = 1 / median over rounds of the mean time per view (prefilter + Gaussian "
                 "decoding + rasterization); x ref = reference time / this time per round "
                 "(> 1: faster), median and range over rounds; x same form: the same against "
                 "the first model in this row's form (plain: decode as decoded, f_c cache on; "
                 "baked: view-independent head terms precomputed; no cache: f_c recomputed), "
                 "or its plain form; max |img - plain|: the largest difference of this form's "
                 "images from its model's plain form's over the views (untimed; - for plain).")
    return "\n".join(lines)
