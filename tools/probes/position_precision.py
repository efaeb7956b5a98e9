"""What the trained-versus-decoded anchor positions cost a finished run's test PSNR.

    python tools/probes/position_precision.py RUN [RUN ...]

A run trained at its float anchor positions (``train.positions = "float"``, or any run
before training semantics 3) renders them, and Predict-GS's SFP queries them, at those floats;
the file stores them at 16 bits over HAC's widened anchor bounds
(``baseline.pipeline.quantized_positions``), so the decoder draws them up to half a 16-bit step
away. HAC's reference code trains on the 16-bit positions themselves (its ``get_anchor``
quantizes them), as this toolkit does by default, so a run trained that way shows no change.
Per run, the test views with every coded attribute rounded as the codec
rounds it, once at the float positions and once at the 16-bit ones (the decoded model), and the
largest and mean position shift in units of the run's voxel size.
"""
from __future__ import annotations

import sys

import torch

from baseline.eval.evaluate import evaluate
from baseline.pipeline import quantized_positions
from baseline.run import load_run


@torch.no_grad()
def position_precision(run: str) -> dict:
    trainer, scene = load_run(run, device="cpu")
    model, ent = trainer.model, trainer.entropy
    stored = model.per_anchor["xyz"].data.clone()
    coded = model.anchor_valid()
    xyz_q = quantized_positions(stored, coded, trainer.cfg.codec.positions)
    idx = torch.arange(model.n_anchors)
    raw = {k: v.detach().clone() for k, v in model.coded_values(idx).items()}
    hard = (model.gaussian_mask(idx).detach() > 0).float()
    rounded = ent.quantize_for_coding(xyz_q, raw, hard)
    shift = (xyz_q - stored)[coded].abs() / float(trainer.voxel_size)
    out = {"run": run, "max_shift_voxels": float(shift.max()), "mean_shift_voxels": float(shift.mean())}
    try:
        model.fixed_values = rounded
        for name, xyz in (("float", stored), ("16-bit", xyz_q)):
            model.per_anchor["xyz"].data.copy_(xyz)
            if hasattr(model.provider, "clear_cache"):
                model.provider.clear_cache()
            r = evaluate(model, scene, scene.test_cameras, phase="decoded",
                         backend=trainer.cfg.train.rasterizer)
            out[f"psnr_{name}"] = r["psnr"]
    finally:
        model.fixed_values = None
        model.per_anchor["xyz"].data.copy_(stored)
    return out


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    print(f"{'run':<60} {'float (dB)':>10} {'16-bit (dB)':>11} {'change':>8} {'max/mean shift (voxels)':>24}")
    for run in argv:
        o = position_precision(run)
        print(f"{o['run'][-60:]:<60} {o['psnr_float']:>10.3f} {o['psnr_16-bit']:>11.3f} "
              f"{o['psnr_16-bit'] - o['psnr_float']:>+8.3f} "
              f"{o['max_shift_voxels']:>12.4f} / {o['mean_shift_voxels']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
