"""Where a trained model's quantization loss comes from: ``pgs quant-cost RUN``.

A run in HAC's adaptive phase is rendered on the test views with its coded attributes
(feat or residual, scaling, offsets) in several states, everything else equal:

* ``raw``: the trained values, nothing quantized;
* ``<attr> rounded``: one attribute rounded as the codec rounds it (the file's values), the
  others raw; ``all rounded``: every attribute, i.e. the model the file decodes to (its PSNR is
  the run's pre-encode PSNR);
* ``<attr> noise``: one attribute with fresh ``U(-0.5, 0.5) Q`` noise per view, the others raw:
  what HAC's training shows the decoder.

A large gap between an attribute's ``noise`` and ``rounded`` rows means the decoder learned to
use information below the quantization step (noise dithers it; rounding deletes it): train with
``--patch quant-ste``. Positions are the 16-bit ones the codec stores, in every row.

:func:`value_ablation` (``pgs quant-cost RUN --ablate``) asks what each attribute's coded
values buy, starting from the model the file decodes to (``as coded``) and replacing one
attribute at a time:

* ``<attr> at context mean``: every value set to the entropy model's mean for it, on the
  value's own quantization grid (``round(mean / Q) Q``): what the context alone predicts, the
  values that cost the fewest bits;
* ``<attr> zero``: every value 0 (for a residual: the refiner still runs, on a zero input);
* ``<attr> shuffled``: the coded anchors' values permuted among them (right statistics, wrong
  anchor).

The gap between ``as coded`` and ``at context mean`` is what the anchor-specific part of the
bits buys; with it come, per attribute, the share of the coded values' variance the context
mean explains (R^2) and their spread in quantization steps.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Optional

import torch

from baseline.eval.evaluate import evaluate


def _coded_state(trainer):
    """The adaptive-phase model's 16-bit positions, its raw values, Gaussian masks and coded
    values, and the entropy model's parameters at those positions."""
    if trainer.phase != "adaptive":
        raise ValueError(f"quant-cost needs a run in HAC's adaptive phase (this one ends in "
                         f"'{trainer.phase}': an uncompressed or unfinished run codes nothing)")
    from baseline.pipeline import quantized_positions

    model, ent = trainer.model, trainer.entropy
    stored = model.per_anchor["xyz"].data.clone()
    xyz_q = quantized_positions(stored, model.anchor_valid(), trainer.cfg.codec.positions,
                                model.position_box)
    idx = torch.arange(model.n_anchors, device=stored.device)
    raw = {k: v.detach().clone() for k, v in model.coded_values(idx).items()}
    hard = (model.gaussian_mask(idx).detach() > 0).float()
    rounded = ent.quantize_for_coding(xyz_q, raw, hard)
    return xyz_q, raw, hard, rounded, ent.params(xyz_q)


@contextmanager
def _as_decoded(trainer, scene, cams, backend, xyz_q):
    """Yield ``run(values_of)``: mean PSNR / SSIM over ``cams`` of the model at the stored
    positions ``xyz_q`` with its coded values set to ``values_of()``, called afresh per view (so
    noise is drawn per view), set as a decoded model sets them
    (:meth:`AnchorModel.set_fixed_values`: the prefilter then reads the scalings the values
    hold). The model is restored on exit."""
    model = trainer.model
    kept = {k: model.per_anchor[k].data for k in ("scaling", "offsets")}
    xyz = model.per_anchor["xyz"].data.clone()

    def run(values_of) -> dict:
        psnr = ssim = 0.0
        for cam in cams:
            model.set_fixed_values(values_of())
            r = evaluate(model, scene, [cam], phase="decoded", backend=backend)
            psnr, ssim = psnr + r["psnr"], ssim + r["ssim"]
        return {"psnr": psnr / len(cams), "ssim": ssim / len(cams)}

    try:
        model.per_anchor["xyz"].data.copy_(xyz_q)
        yield run
    finally:
        model.fixed_values = None
        model.per_anchor["xyz"].data.copy_(xyz)
        for k, t in kept.items():
            model.per_anchor[k].data = t


@torch.no_grad()
def quantization_cost(trainer, scene, cameras=None, *, seed: int = 0,
                      backend: Optional[str] = None) -> list[dict]:
    """Rows ``{"variant", "psnr", "ssim"}`` for the states listed in the module docstring.

    ``trainer``: a loaded run in the adaptive phase (:func:`baseline.run.load_run`).
    """
    cams = cameras if cameras is not None else (scene.test_cameras or scene.train_cameras)
    xyz_q, raw, _, rounded, params = _coded_state(trainer)
    steps = {k: P[2] for k, P in params.items()}
    names = list(raw)
    gen = torch.Generator(device="cpu").manual_seed(seed)

    def noisy(k):
        u = torch.rand(raw[k].shape, generator=gen, dtype=raw[k].dtype).to(raw[k].device)
        return raw[k] + (u - 0.5) * steps[k]

    rows = []
    with _as_decoded(trainer, scene, cams, backend or trainer.cfg.train.rasterizer, xyz_q) as run:
        rows.append({"variant": "raw", **run(lambda: dict(raw))})
        for k in names:
            rows.append({"variant": f"{k} rounded", **run(lambda k=k: {**raw, k: rounded[k]})})
        rows.append({"variant": "all rounded", **run(lambda: dict(rounded))})
        for k in names:
            rows.append({"variant": f"{k} noise", **run(lambda k=k: {**raw, k: noisy(k)})})
    return rows


@torch.no_grad()
def value_ablation(trainer, scene, cameras=None, *, seed: int = 0,
                   backend: Optional[str] = None) -> dict:
    """What each coded attribute's values buy (module docstring): ``{"rows": [{"variant",
    "psnr", "ssim"}], "stats": [{"attribute", "coded_values", "mean_step", "raw_std",
    "share_within_half_step_of_zero", "r2_context_mean", "rms_steps_from_mean",
    "share_at_mean"}]}``.

    The statistics are over the values the file codes (the coded anchors' values, without the
    offsets of masked-off Gaussians): the mean adaptive step Q, the trained (raw) values' standard
    deviation and share within half a step of zero (those round to 0), R^2 of the context mean
    as a predictor of the coded value, the root mean square of (value - mean) / Q, and the share
    of values that equal the context mean on their grid (those cost the fewest bits and carry no
    anchor-specific information).
    """
    model, ent = trainer.model, trainer.entropy
    cams = cameras if cameras is not None else (scene.test_cameras or scene.train_cameras)
    xyz_q, raw, hard, rounded, params = _coded_state(trainer)
    valid = model.anchor_valid()
    n = int(valid.shape[0])
    coded = {}
    for a in ent.attrs:
        m = ent.value_mask(a, hard, n, device=valid.device)
        m = valid[:, None].expand(n, a.dims) if m is None else (m & valid[:, None])
        coded[a.name] = m
    at_mean, zero, shuffled, stats = {}, {}, {}, []
    gen = torch.Generator(device="cpu").manual_seed(seed)
    rows = torch.nonzero(valid).squeeze(1).cpu()
    perm = rows[torch.randperm(len(rows), generator=gen)]   # each coded anchor gets another's values
    for k, x in rounded.items():
        mean, _, q = (t.detach().to(x.device) for t in params[k])
        q = q.expand_as(mean).to(torch.float64)
        on_grid = (torch.round(mean.to(torch.float64) / q) * q).to(x.dtype)
        m = coded[k].to(x.device)
        at_mean[k] = torch.where(m, on_grid, x)
        zero[k] = torch.where(m, torch.zeros_like(x), x)
        sh = x.clone()
        sh[rows.to(x.device)] = x[perm.to(x.device)]
        shuffled[k] = torch.where(m, sh, x)
        xv = x[m].to(torch.float64)                 # the coded values
        mv = mean[m].to(torch.float64)              # their context means
        qv = q[m]                                   # their steps
        tv = raw[k].to(x.device)[m].to(torch.float64)   # the trained values they round
        var = ((xv - xv.mean()) ** 2).sum()
        stats.append({
            "attribute": k, "coded_values": int(m.sum()),
            "mean_step": float(qv.mean()) if xv.numel() else 0.0,
            "raw_std": float(tv.std()) if xv.numel() > 1 else 0.0,
            "share_within_half_step_of_zero": float(((tv / qv).abs() < 0.5).double().mean())
            if xv.numel() else 0.0,
            "r2_context_mean": float(1.0 - ((xv - mv) ** 2).sum() / var) if var > 0 else 0.0,
            "rms_steps_from_mean": float((((xv - mv) / qv) ** 2).mean().sqrt()) if xv.numel() else 0.0,
            "share_at_mean": float((x[m] == on_grid[m]).double().mean()) if xv.numel() else 0.0})
    out = []
    with _as_decoded(trainer, scene, cams, backend or trainer.cfg.train.rasterizer, xyz_q) as run:
        out.append({"variant": "as coded", **run(lambda: dict(rounded))})
        for label, alt in (("at context mean", at_mean), ("zero", zero), ("shuffled", shuffled)):
            for k in rounded:
                out.append({"variant": f"{k} {label}", **run(lambda k=k, alt=alt: {**rounded, k: alt[k]})})
    return {"rows": out, "stats": stats}


def format_ablation(result: dict) -> str:
    rows, stats = result["rows"], result["stats"]
    base = rows[0]["psnr"]
    lines = [f"{'values':<30} {'PSNR (dB)':>10} {'vs coded':>9} {'SSIM':>7}", "-" * 59]
    for r in rows:
        lines.append(f"{r['variant']:<30} {r['psnr']:>10.3f} {r['psnr'] - base:>+9.3f} {r['ssim']:>7.4f}")
    lines.append("")
    lines.append(f"{'attribute':<12} {'coded values':>13} {'mean step Q':>12} {'raw std':>8} "
                 f"{'|raw| < Q/2':>12} {'R^2 of context mean':>20} {'rms (x-mean)/Q':>15} "
                 f"{'at the mean':>12}")
    for st in stats:
        lines.append(f"{st['attribute']:<12} {st['coded_values']:>13,} {st['mean_step']:>12.4g} "
                     f"{st['raw_std']:>8.4g} {st['share_within_half_step_of_zero']:>11.1%} "
                     f"{st['r2_context_mean']:>20.3f} {st['rms_steps_from_mean']:>15.3f} "
                     f"{st['share_at_mean']:>11.1%}")
    lines.append("one attribute replaced at a time in the decoded model: by the entropy model's mean "
                 "on its grid (what the context alone predicts), by 0, or by another coded anchor's "
                 "values.")
    return "\n".join(lines)


def format_rows(rows: list[dict]) -> str:
    base = rows[0]["psnr"]
    lines = [f"{'values':<22} {'PSNR (dB)':>10} {'vs raw':>8} {'SSIM':>7}", "-" * 50]
    for r in rows:
        lines.append(f"{r['variant']:<22} {r['psnr']:>10.3f} {r['psnr'] - base:>+8.3f} {r['ssim']:>7.4f}")
    lines.append("rounded: as the codec rounds (the file's values); noise: fresh U(-0.5,0.5) Q per "
                 "view, as HAC's training shows the decoder; positions at 16 bits throughout.")
    return "\n".join(lines)
