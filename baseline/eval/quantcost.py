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
"""
from __future__ import annotations

from typing import Optional

import torch

from baseline.eval.evaluate import evaluate


@torch.no_grad()
def quantization_cost(trainer, scene, cameras=None, *, seed: int = 0,
                      backend: Optional[str] = None) -> list[dict]:
    """Rows ``{"variant", "psnr", "ssim"}`` for the states listed in the module docstring.

    ``trainer``: a loaded run in the adaptive phase (:func:`baseline.run.load_run`).
    """
    if trainer.phase != "adaptive":
        raise ValueError(f"quant-cost needs a run in HAC's adaptive phase (this one ends in "
                         f"'{trainer.phase}': an uncompressed or unfinished run codes nothing)")
    from baseline.pipeline import quantized_positions

    model, ent = trainer.model, trainer.entropy
    cams = cameras if cameras is not None else (scene.test_cameras or scene.train_cameras)
    backend = backend or trainer.cfg.train.rasterizer
    stored = model.per_anchor["xyz"].data.clone()
    xyz_q = quantized_positions(stored, model.anchor_valid(), trainer.cfg.codec.positions,
                                model.position_box)
    idx = torch.arange(model.n_anchors, device=stored.device)
    raw = {k: v.detach().clone() for k, v in model.coded_values(idx).items()}
    hard = (model.gaussian_mask(idx).detach() > 0).float()
    rounded = ent.quantize_for_coding(xyz_q, raw, hard)
    steps = {k: P[2] for k, P in ent.params(xyz_q).items()}
    names = list(raw)
    gen = torch.Generator(device="cpu").manual_seed(seed)

    def noisy(k):
        u = torch.rand(raw[k].shape, generator=gen, dtype=raw[k].dtype).to(raw[k].device)
        return raw[k] + (u - 0.5) * steps[k]

    def run(values_of) -> dict:
        psnr = ssim = 0.0
        for cam in cams:   # one view at a time, so that noise is drawn afresh per view
            model.fixed_values = values_of()
            r = evaluate(model, scene, [cam], phase="decoded", backend=backend)
            psnr, ssim = psnr + r["psnr"], ssim + r["ssim"]
        return {"psnr": psnr / len(cams), "ssim": ssim / len(cams)}

    rows = []
    try:
        model.per_anchor["xyz"].data.copy_(xyz_q)
        rows.append({"variant": "raw", **run(lambda: dict(raw))})
        for k in names:
            rows.append({"variant": f"{k} rounded", **run(lambda k=k: {**raw, k: rounded[k]})})
        rows.append({"variant": "all rounded", **run(lambda: dict(rounded))})
        for k in names:
            rows.append({"variant": f"{k} noise", **run(lambda k=k: {**raw, k: noisy(k)})})
    finally:
        model.fixed_values = None
        model.per_anchor["xyz"].data.copy_(stored)
    return rows


def format_rows(rows: list[dict]) -> str:
    base = rows[0]["psnr"]
    lines = [f"{'values':<22} {'PSNR (dB)':>10} {'vs raw':>8} {'SSIM':>7}", "-" * 50]
    for r in rows:
        lines.append(f"{r['variant']:<22} {r['psnr']:>10.3f} {r['psnr'] - base:>+8.3f} {r['ssim']:>7.4f}")
    lines.append("rounded: as the codec rounds (the file's values); noise: fresh U(-0.5,0.5) Q per "
                 "view, as HAC's training shows the decoder; positions at 16 bits throughout.")
    return "\n".join(lines)
