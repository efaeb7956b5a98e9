"""Second layers of the Gaussian heads for every candidate or only for the kept Gaussians.

    python tools/probes/kept_slot_second_layer.py RUN [RUN ...] [--rounds 3] [--views 32] [--threads 1]

A decoded frame runs the cov and color heads' second layers (decoder, plus a refiner's heads
such as Predict-GS's MGRD, summed in the baked form) on all K slots of every visible anchor,
then keeps the Gaussians whose mask is on and opacity > 0 (about a fifth of the candidates on
a trained truck model). The alternative computes them for the kept slots only: group the kept
Gaussians by slot, gather their anchors' hidden rows, one small GEMM per slot, scatter back.
It does ~1/5 of the multiply-adds but moves the gathered rows through memory. A third form
("exact") computes the kept Gaussians' rows in a numba kernel that keeps each output the same
in-order chain of fused multiply-adds that MKL's float32 GEMM computes (from 0, the bias
added last; ``--order`` checks that on this machine), so its values equal the full layer's
bit for bit, with no gather: it shows what an exact kept-only layer costs without SIMD. A
fourth form ("reassociated") lets numba reassociate each output's sum over the hidden units,
which vectorises it, so its values differ from the full layer's in the last bits: it shows
what a kept-only layer costs with SIMD and how far its values move.

Per run (a folder with model.pgs, or a .pgs file) this decodes and bakes the model
(:class:`~baseline.scaffold.baked.BakedDecoder`) and, on its test views, times the four
forms of the cov + color second layers in one process (order reversed every round, a warm-up
round untimed), checks the grouped form gives the same values within 1e-4, says whether the
exact form gives them bit for bit and how far the reassociated form's values are from them.
Prints ms per view of each form, their ratios to the full layer (> 1: the kept-only form is
faster), the candidates and the kept Gaussians per view.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from numba import njit

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


@njit(cache=True, fastmath={"contract"}, error_model="numpy")
def _exact_rows(hid, keep, K, wt, bias, out):  # pragma: no cover - numba
    """out[g, :C] = hid[r] @ wt[s, :, :C] + bias[s, :C] for the kept g = r * K + s: eight
    independent FMA chains per Gaussian, two Gaussians interleaved, in order over the hidden
    units (no reassociation; wt [K, H, 8] zero-padded)."""
    G, H, C = keep.shape[0], hid.shape[1], out.shape[1]
    for g0 in range(0, G, 2):
        g1 = min(g0 + 1, G - 1)
        r0, r1 = keep[g0] // K, keep[g1] // K
        s0, s1 = keep[g0] - r0 * K, keep[g1] - r1 * K
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = np.float32(0.0)
        b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = np.float32(0.0)
        for j in range(H):
            h, q = hid[r0, j], hid[r1, j]
            a0 += h * wt[s0, j, 0]
            a1 += h * wt[s0, j, 1]
            a2 += h * wt[s0, j, 2]
            a3 += h * wt[s0, j, 3]
            a4 += h * wt[s0, j, 4]
            a5 += h * wt[s0, j, 5]
            a6 += h * wt[s0, j, 6]
            a7 += h * wt[s0, j, 7]
            b0 += q * wt[s1, j, 0]
            b1 += q * wt[s1, j, 1]
            b2 += q * wt[s1, j, 2]
            b3 += q * wt[s1, j, 3]
            b4 += q * wt[s1, j, 4]
            b5 += q * wt[s1, j, 5]
            b6 += q * wt[s1, j, 6]
            b7 += q * wt[s1, j, 7]
        t0 = (a0, a1, a2, a3, a4, a5, a6, a7)
        t1 = (b0, b1, b2, b3, b4, b5, b6, b7)
        for c in range(C):
            out[g0, c] = t0[c] + bias[s0, c]
            out[g1, c] = t1[c] + bias[s1, c]


def _kernel_form(baked: BakedDecoder, hid, keep, K, kernel, layout):
    """The kept Gaussians' cov and color pre-activations by a numba ``kernel``; ``layout(W, b,
    width, C)`` turns a second layer's weight [width, K, C] and bias [K, C] into the kernel's
    weight and bias arrays."""
    outs = []
    for attr, C in (("cov", 7), ("color", 3)):
        s = baked.second[attr]
        h = hid[:, s.lo:s.hi].contiguous()
        w, b = layout(s.weight.view(-1, K, C), s.bias.view(K, C), h.shape[1], C)
        out = torch.empty(len(keep), C)
        if len(keep):
            kernel(h.numpy(), keep.numpy(), K, w.numpy(), b.numpy(), out.numpy())
        outs.append(out)
    return tuple(outs)


def _padded_layout(W, b, width, C):
    """[K, width, 8] and [K, 8], zero-padded: the layout of :func:`_exact_rows`."""
    K = b.shape[0]
    wt, bt = torch.zeros(K, width, 8), torch.zeros(K, 8)
    wt[..., :C] = W.permute(1, 0, 2)
    bt[:, :C] = b
    return wt, bt


def exact_form(baked: BakedDecoder, hid, keep, K):
    """The kept Gaussians' cov and color pre-activations by :func:`_exact_rows`."""
    return _kernel_form(baked, hid, keep, K, _exact_rows, _padded_layout)


@njit(cache=True, fastmath=True, error_model="numpy")
def _reassociated_rows(hid, keep, K, w, bias, out):  # pragma: no cover - numba
    """out[g, c] = hid[r] . w[s, c] + bias[s, c] for the kept g = r * K + s, each dot product
    summed in whatever order LLVM vectorises it (w [K, C, H])."""
    G, H, C = keep.shape[0], hid.shape[1], out.shape[1]
    for g in range(G):
        r = keep[g] // K
        s = keep[g] - r * K
        for c in range(C):
            acc = np.float32(0.0)
            for j in range(H):
                acc += hid[r, j] * w[s, c, j]
            out[g, c] = acc + bias[s, c]


def reassociated_form(baked: BakedDecoder, hid, keep, K):
    """The kept Gaussians' cov and color pre-activations by :func:`_reassociated_rows`."""
    return _kernel_form(baked, hid, keep, K, _reassociated_rows,
                        lambda W, b, width, C: (W.permute(1, 2, 0).contiguous(), b.contiguous()))


def gemm_order() -> str:
    """Whether this machine's float32 addmm computes each output as an in-order FMA chain from
    0 with the bias added last (checked against a float64 emulation of that chain, whose
    products are exact, on a 200 x 70 product with 32 hidden units)."""
    g = torch.Generator().manual_seed(0)
    X = torch.relu(torch.randn(200, 32, generator=g))
    W, b = torch.randn(70, 32, generator=g) * 0.3, torch.randn(70, generator=g)
    full = torch.addmm(b, X, W.t()).numpy()
    Xd, Wd = X.double().numpy(), W.double().numpy()
    acc = np.zeros((200, 70), np.float32)
    for j in range(32):          # acc = round32(acc + x * w): one rounding per step, as an FMA
        acc = (acc.astype(np.float64) + Xd[:, j:j + 1] * Wd[:, j][None, :]).astype(np.float32)
    chain = acc + b.numpy()[None, :]
    same = int((chain == full).sum())
    return f"addmm vs in-order FMA chain, bias last: {same} of {full.size} outputs equal"


FORMS = {"all": full_form, "kept": kept_form, "exact": exact_form,
         "reassociated": reassociated_form}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--views", type=int, default=32)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--order", action="store_true",
                    help="first check how this machine's GEMM sums (see gemm_order)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.order:
        print(gemm_order())
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
            forms_all = tuple(FORMS)
            t = {f: [0.0] * a.rounds for f in forms_all}
            exact_equal, reassoc_diff = True, 0.0
            for r in range(-1, a.rounds):
                forms = forms_all if r % 2 == 0 else forms_all[::-1]
                for hid, keep in inputs:
                    res = {}
                    for f in forms:
                        t0 = time.perf_counter()
                        res[f] = FORMS[f](baked, hid, keep, K)
                        if r >= 0:
                            t[f][r] += (time.perf_counter() - t0) / len(inputs)
                    for x, y in zip(res["all"], res["kept"]):
                        if not torch.allclose(x, y, rtol=1e-4, atol=1e-4):
                            raise AssertionError(f"{label}: the two forms disagree")
                    exact_equal &= all(torch.equal(x, y) for x, y in zip(res["all"], res["exact"]))
                    reassoc_diff = max([reassoc_diff] + [float((x - y).abs().max()) for x, y
                                                         in zip(res["all"], res["reassociated"])
                                                         if len(x)])
        cand = statistics.mean(h.shape[0] * K for h, _ in inputs)
        kept = statistics.mean(len(k) for _, k in inputs)
        ta, tk = statistics.median(t["all"]), statistics.median(t["kept"])
        te = statistics.median(t["exact"])
        tr = statistics.median(t["reassociated"])
        print(f"{label}: all candidates {ta * 1e3:.1f} ms, kept only {tk * 1e3:.1f} ms, "
              f"ratio {ta / tk:.2f}x (rounds {min(t['all']) * 1e3:.1f}-{max(t['all']) * 1e3:.1f}"
              f" / {min(t['kept']) * 1e3:.1f}-{max(t['kept']) * 1e3:.1f}); candidates "
              f"{cand:,.0f}, kept {kept:,.0f} ({kept / cand:.1%}) per view; exact kept-only "
              f"kernel {te * 1e3:.1f} ms ({ta / te:.2f}x), "
              f"{'bit-equal to' if exact_equal else 'NOT bit-equal to'} the full layer; "
              f"reassociated kernel {tr * 1e3:.1f} ms ({ta / tr:.2f}x), values within "
              f"{reassoc_diff:.2g} of the full layer's")


if __name__ == "__main__":
    main()
