"""Codec benchmark: encode / decode time and throughput of the entropy-coding path.

``python -m baseline.codec.bench [--anchors N] [--model hac|factorized] [--threads T]``

Measures, for a synthetic payload shaped like an average Mip-NeRF360 HAC model (feat 50,
scaling 6 post-exp, offsets 30 gated by 10 Gaussian masks about half on): the hash-grid context
+ MLP (exact path), range coding of all attributes, and the hash-grid / mask Bernoulli streams;
then the decoder doing the same from the bytes. The HAC model is at random initialisation except
for the output biases of its scale head, set to the payload's per-attribute spread (a random
head predicts negative scales, i.e. the 1e-9 floor, which makes sizes meaningless; the timing is
the same either way). Reference (HAC paper, A100, average Mip-NeRF360): encode 6.96 s, decode
18.72 s.
"""
from __future__ import annotations

import argparse
import time
from typing import Dict, List

import numpy as np
import torch

from baseline.contracts import scaffold_coded_attributes
from baseline.codec.rangecoder import decode_bernoulli, encode_bernoulli


def synthetic_payload(n: int, n_offsets: int = 10, seed: int = 0):
    """Positions, attribute values and Gaussian masks with realistic-ish statistics."""
    g = torch.Generator().manual_seed(seed)
    # anchors on a few noisy surfaces in a 20 m box
    xyz = torch.rand(n, 3, generator=g) * 20 - 10
    xyz[:, 2] = torch.sin(xyz[:, 0] * 0.3) * 2 + 0.05 * torch.randn(n, generator=g)
    feat = torch.randn(n, 50, generator=g) * torch.linspace(0.5, 4.0, 50)
    scaling = torch.exp(torch.randn(n, 6, generator=g) * 0.5 - 4.0)
    offsets = torch.randn(n, 3 * n_offsets, generator=g) * 0.6
    mask = (torch.rand(n, n_offsets, generator=g) < 0.5).float()
    return xyz, {"feat": feat, "scaling": scaling, "offsets": offsets}, mask


def _calibrate(model, values, mask) -> None:
    """Set the HAC head's scale biases to the data spread (see module docstring)."""
    with torch.no_grad():
        last = model.mlp[-1]
        off = 0
        for a in model.attrs:
            x = values[a.name]
            if a.masked:
                m = mask.repeat_interleave(a.dims // model.n_masks, dim=1).bool()
                std = torch.stack([x[:, j][m[:, j]].std() for j in range(a.dims)])
                mu = torch.stack([x[:, j][m[:, j]].mean() for j in range(a.dims)])
            else:
                std, mu = x.std(0), x.mean(0)
            last.bias[off:off + a.dims] = mu
            last.bias[off + a.dims:off + 2 * a.dims] = std
            off += 2 * a.dims


def run_codec_bench(n_anchors: int = 500_000, model: str = "hac", threads: int = 0,
                    seed: int = 0, repeats: int = 1) -> List[Dict]:
    """Encode + decode a synthetic payload; one result row per repeat (times in seconds).

    ``threads`` sets torch's thread count for the run (restored afterwards)."""
    prev = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        return _run_codec_bench(n_anchors, model, seed, repeats)
    finally:
        torch.set_num_threads(prev)


def _run_codec_bench(n_anchors: int, model: str, seed: int, repeats: int) -> List[Dict]:
    import baseline.hac  # noqa: F401  (registers the entropy models)
    from baseline import registry

    torch.manual_seed(seed)
    attrs = scaffold_coded_attributes()
    cls = registry.get("entropy_model", model)
    em = cls(attrs, 10)
    xyz, values, mask = synthetic_payload(n_anchors, seed=seed)
    if model == "hac":
        lo, hi = xyz.min(0).values, xyz.max(0).values
        em.set_bounds(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
        _calibrate(em, values, mask)
    else:
        em.fit_(values, mask)
    n_symbols = int(n_anchors * 56 + mask.sum().item() * 3)
    rows = []
    for r in range(repeats):
        t0 = time.perf_counter()
        side = em.serialize("float32")
        mask_blob = encode_bernoulli(mask.numpy().astype(np.uint8))
        blobs, vq = em.compress(xyz, values, mask, return_values=True)
        t_enc = time.perf_counter() - t0

        dm = cls(attrs, 10)
        t0 = time.perf_counter()
        dm.load_serialized(side)
        dmask = torch.from_numpy(decode_bernoulli(mask_blob, expected_n=mask.numel()).reshape(mask.shape)).float()
        dec = dm.decompress(xyz, blobs, dmask)
        t_dec = time.perf_counter() - t0
        ok = all(torch.equal(dec[k], vq[k]) for k in dec)
        size = {k: len(v) for k, v in blobs.items()}
        size.update({f"em.{k}": len(v) for k, v in side.items()}, masks=len(mask_blob))
        rows.append(dict(model=model, anchors=n_anchors, symbols=n_symbols, threads=torch.get_num_threads(),
                         encode_s=t_enc, decode_s=t_dec, exact=ok, bytes=size,
                         total_mb=sum(size.values()) / 2 ** 20,
                         enc_msym_s=n_symbols / t_enc / 1e6, dec_msym_s=n_symbols / t_dec / 1e6))
    return rows


def format_codec_bench(rows: List[Dict]) -> str:
    lines = [f"{'model':<11}{'anchors':>9}{'symbols':>11}{'thr':>4}{'enc s':>8}{'dec s':>8}"
             f"{'enc Msym/s':>11}{'dec Msym/s':>11}{'MB':>8}  exact"]
    for r in rows:
        lines.append(f"{r['model']:<11}{r['anchors']:>9}{r['symbols']:>11}{r['threads']:>4}"
                     f"{r['encode_s']:>8.2f}{r['decode_s']:>8.2f}{r['enc_msym_s']:>11.2f}"
                     f"{r['dec_msym_s']:>11.2f}{r['total_mb']:>8.2f}  {r['exact']}")
        lines.append("    bytes: " + ", ".join(f"{k} {v}" for k, v in r["bytes"].items()))
    lines.append("reference: HAC on an A100, average Mip-NeRF360 model: encode 6.96 s, decode 18.72 s")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--anchors", type=int, default=500_000)
    ap.add_argument("--model", default="hac", choices=["hac", "factorized"])
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    ap.add_argument("--repeats", type=int, default=1)
    a = ap.parse_args(argv)
    print(format_codec_bench(run_codec_bench(a.anchors, a.model, a.threads, repeats=a.repeats)))


if __name__ == "__main__":
    main()
