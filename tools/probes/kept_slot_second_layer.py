"""Second layers of the Gaussian heads for every candidate or only for the kept Gaussians.

    python tools/probes/kept_slot_second_layer.py RUN [RUN ...] [--rounds 3] [--views 32] [--threads 1]

A decoded frame runs the cov and color heads' second layers (decoder, plus a refiner's heads
such as Predict-GS's MGRD, summed in the baked form) on all K slots of every visible anchor,
then keeps the Gaussians whose mask is on and opacity > 0 (about a fifth of the candidates on
a trained truck model). The alternative computes them for the kept slots only: group the kept
Gaussians by slot, gather their anchors' hidden rows, one small GEMM per slot, scatter back.
It does ~1/5 of the multiply-adds but moves the gathered rows through memory.

Per run (a folder with model.pgs, or a .pgs file) this decodes and bakes the model
(:class:`~baseline.scaffold.baked.BakedDecoder`) and, on its test views, times both forms
of the cov + color second layers in one process (order swapped every round, a warm-up round
untimed) and checks they give the same values. Prints ms per view of each form, their ratio
(> 1: the kept-only form is faster), the candidates and the kept Gaussians per view.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from baseline.bench.fps import _decode_files
from baseline.pipeline import visible_anchors
from baseline.scaffold.baked import BakedDecoder


def full_form(baked: BakedDecoder, hid, keep, K):
    M = hid.shape[0]
    return (baked._second("cov", hid).reshape(M * K, 7)[keep],
            baked._second("color", hid).reshape(M * K, 3)[keep])


def kept_form(baked: BakedDecoder, hid, keep, K):
    """The kept Gaussians' cov [G,7] and color [G,3] pre-activations, slot by slot (of the
    variants tried, the fastest here: gathering per slot straight from ``hid`` and writing
    into the output in place beat gathering all kept rows first and permuting after)."""
    row = torch.div(keep, K, rounding_mode="floor")
    slot = keep - row * K
    order = torch.argsort(slot, stable=True)
    counts = torch.bincount(slot, minlength=K).tolist()
    rows = row[order]
    outs = []
    for attr, C in (("cov", 7), ("color", 3)):
        s = baked.second[attr]
        h = hid[:, s.lo:s.hi]
        W = s.weight.view(-1, K, C)                  # [width, K, C]
        b = s.bias.view(K, C)
        out = torch.empty(len(keep), C)
        start = 0
        for k, c in enumerate(counts):
            if c:
                out[order[start:start + c]] = torch.addmm(b[k], h[rows[start:start + c]],
                                                          W[:, k, :])
                start += c
        outs.append(out)
    return tuple(outs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--views", type=int, default=32)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    decoded, cams, _, _, _, _, split = _decode_files(a.runs, None, "cpu", a.views)
    print(f"{len(cams)} {split} views, {a.rounds} rounds, {a.threads} thread(s); ms per view "
          f"of the cov + color second layers")
    for label, dec in decoded:
        model = dec.model
        baked = BakedDecoder.from_model(model)
        K = baked.n_offsets
        inputs = []
        with torch.no_grad():
            for cam in cams:
                idx = visible_anchors(model, cam)
                _, hid = baked.hidden(cam.center, idx)
                keep = baked.kept(hid, idx)[1].nonzero()[:, 0]
                inputs.append((hid, keep))
            t = {"all": [0.0] * a.rounds, "kept": [0.0] * a.rounds}
            for r in range(-1, a.rounds):
                forms = ("all", "kept") if r % 2 == 0 else ("kept", "all")
                for hid, keep in inputs:
                    res = {}
                    for f in forms:
                        fn = full_form if f == "all" else kept_form
                        t0 = time.perf_counter()
                        res[f] = fn(baked, hid, keep, K)
                        if r >= 0:
                            t[f][r] += (time.perf_counter() - t0) / len(inputs)
                    for x, y in zip(res["all"], res["kept"]):
                        if not torch.allclose(x, y, rtol=1e-4, atol=1e-4):
                            raise AssertionError(f"{label}: the two forms disagree")
        cand = statistics.mean(h.shape[0] * K for h, _ in inputs)
        kept = statistics.mean(len(k) for _, k in inputs)
        ta, tk = statistics.median(t["all"]), statistics.median(t["kept"])
        print(f"{label}: all candidates {ta * 1e3:.1f} ms, kept only {tk * 1e3:.1f} ms, "
              f"ratio {ta / tk:.2f}x (rounds {min(t['all']) * 1e3:.1f}-{max(t['all']) * 1e3:.1f}"
              f" / {min(t['kept']) * 1e3:.1f}-{max(t['kept']) * 1e3:.1f}); candidates "
              f"{cand:,.0f}, kept {kept:,.0f} ({kept / cand:.1%}) per view")


if __name__ == "__main__":
    main()
