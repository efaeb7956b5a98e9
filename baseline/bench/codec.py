"""Codec benchmark: encode / decode time and throughput of the entropy-coding path.

``pgs bench codec [--anchors N] [--threads T] [--run RUN]...``
(= ``python -m baseline.bench.codec``, which also takes ``--model hac|hacpp|factorized``;
``pgs bench codec`` runs ``hac`` and ``hacpp`` side by side, or ``--model M`` repeated)

Measures, for a synthetic payload shaped like an average Mip-NeRF360 HAC model (feat 50,
scaling 6 post-exp, offsets 30 gated by 10 Gaussian masks about half on): the hash-grid context
+ MLP (exact path), range coding of all attributes, and the hash-grid / mask Bernoulli streams;
then the decoder doing the same from the bytes. The HAC model is at random initialisation except
for the output biases of its scale head, set to the payload's per-attribute spread (a random
head predicts negative scales, i.e. the 1e-9 floor, which makes sizes meaningless; the timing is
the same either way).

Two implementations run in the same process on the same payload, and the report gives their
ratio: ``reference`` is the plain PyTorch coding loop (hash-grid corners and weights as PyTorch
tensors, the context model and the range coder one after the other), ``fast`` the default
(numba kernel for the exact grid features, the next chunk's model computed while the range coder
codes the current one). Both produce the same bytes; decoding is checked bit-exact. The context
model's share (the exact grid + MLP pass over all anchors) is timed on its own.
``--run RUN`` adds a real trained run: its whole ``.pgs`` file encoded and decoded.
Reference figures (HAC paper, A100, average Mip-NeRF360 model): encode 6.96 s, decode 18.72 s.
"""
from __future__ import annotations

import argparse
import time
from typing import Dict, List, Sequence

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
        main = getattr(model, "main", None)          # HAC++: mean, scale, logit for the main
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
            off += (3 if a.name == main else 2) * a.dims


VARIANTS = ("reference", "fast")


def run_codec_bench(n_anchors: int = 500_000, model: str = "hac", threads: int = 0,
                    seed: int = 0, repeats: int = 1,
                    variants: Sequence[str] = VARIANTS) -> List[Dict]:
    """Encode + decode a synthetic payload with each variant; rows with times in seconds and
    ratios to the ``reference`` variant (when run).

    ``threads`` sets torch's thread count for the run (restored afterwards)."""
    prev = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        rows = _run_codec_bench(n_anchors, model, seed, repeats, variants)
    finally:
        torch.set_num_threads(prev)
    ref = next((r for r in rows if r["variant"] == "reference"), None)
    for r in rows:
        r["x_enc"] = ref["encode_s"] / r["encode_s"] if ref else None
        r["x_dec"] = ref["decode_s"] / r["decode_s"] if ref else None
    return rows


def _variant(name: str):
    """Context manager setting the grid backend / pipelining of a variant."""
    from contextlib import contextmanager

    from baseline.hac import hashgrid as H

    if name not in VARIANTS:
        raise ValueError(f"unknown codec bench variant {name!r}; choose from {VARIANTS}")

    @contextmanager
    def ctx():
        old = H.get_grid_backend()
        H.set_grid_backend("torch" if name == "reference" else "auto")
        try:
            yield name != "reference"           # pipeline on/off
        finally:
            H.set_grid_backend(old)
    return ctx()


def _run_codec_bench(n_anchors: int, model: str, seed: int, repeats: int,
                     variants: Sequence[str]) -> List[Dict]:
    import baseline.hac  # noqa: F401  (registers the entropy models)
    from baseline import registry

    torch.manual_seed(seed)
    attrs = scaffold_coded_attributes()
    cls = registry.get("entropy_model", model)
    em = cls(attrs, 10)
    xyz, values, mask = synthetic_payload(n_anchors, seed=seed)
    if model in ("hac", "hacpp"):
        lo, hi = xyz.min(0).values, xyz.max(0).values
        em.set_bounds(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
        _calibrate(em, values, mask)
    else:
        em.fit_(values, mask)
    n_symbols = int(n_anchors * 56 + mask.sum().item() * 3)
    side = em.serialize("float32")       # rounds the weights to the stored precision once
    with _variant("fast"):                # compile / load the kernels outside the timings
        em.params(xyz[:8], exact=True)
    rows = []
    blobs_of = {}
    for r in range(repeats):
        for name in variants:
            with _variant(name) as pipelined:
                em.pipeline = pipelined
                t0 = time.perf_counter()
                side = em.serialize("float32")
                mask_blob = encode_bernoulli(mask.numpy().astype(np.uint8))
                blobs, vq = em.compress(xyz, values, mask, return_values=True)
                t_enc = time.perf_counter() - t0

                dm = cls(attrs, 10, pipeline=pipelined)
                t0 = time.perf_counter()
                dm.load_serialized(side)
                dmask = torch.from_numpy(decode_bernoulli(mask_blob, expected_n=mask.numel())
                                         .reshape(mask.shape)).float()
                dec = dm.decompress(xyz, blobs, dmask)
                t_dec = time.perf_counter() - t0

                t0 = time.perf_counter()
                ctx = em._exact_context()
                for s in range(0, n_anchors, em.chunk):
                    em.params(xyz[s:s + em.chunk], exact=True, _ctx=ctx)
                t_model = time.perf_counter() - t0
            ok = all(torch.equal(dec[k], vq[k]) for k in dec)
            same = all(blobs_of.setdefault(k, v) == v for k, v in blobs.items())
            size = {k: len(v) for k, v in blobs.items()}
            size.update({f"em.{k}": len(v) for k, v in side.items()}, masks=len(mask_blob))
            rows.append(dict(variant=name, model=model, anchors=n_anchors, symbols=n_symbols,
                             threads=torch.get_num_threads(), encode_s=t_enc, decode_s=t_dec,
                             model_s=t_model, exact=ok and same, bytes=size,
                             total_mb=sum(size.values()) / 2 ** 20,
                             enc_msym_s=n_symbols / t_enc / 1e6, dec_msym_s=n_symbols / t_dec / 1e6))
    return rows


def run_model_codec_bench(run_dir: str) -> Dict:
    """Encode a trained run folder to a temporary ``.pgs`` and decode it: times, size, exactness."""
    import tempfile
    from pathlib import Path

    from baseline.modelfile import decode_model, encode_model
    from baseline.run import load_run

    trainer, _ = load_run(run_dir, device="cpu")       # the codec runs on the CPU
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.pgs"
        st = encode_model(trainer.cfg, trainer.model, trainer.entropy, path)
        dec = decode_model(path)
        ok = all(torch.equal(dec.model.fixed_values[k], v) for k, v in st["values"].items())
    n = st["anchors"]
    K = trainer.model.n_offsets
    n_symbols = 0
    for a in trainer.model.coded_attributes():
        n_symbols += (int(dec.model.gaussian_mask().detach().sum()) * (a.dims // K) if a.masked
                      else n * a.dims)
    return dict(variant="run", model=str(run_dir), anchors=n, symbols=n_symbols,
                threads=torch.get_num_threads(), encode_s=st["encode_s"], decode_s=dec.decode_s,
                model_s=None, exact=ok, bytes={"file": st["bytes"]}, total_mb=st["bytes"] / 2 ** 20,
                enc_msym_s=n_symbols / st["encode_s"] / 1e6,
                dec_msym_s=n_symbols / dec.decode_s / 1e6, x_enc=None, x_dec=None)


def format_codec_bench(rows: List[Dict]) -> str:
    lines = ["codec benchmark (whole encode / decode wall clock; x = reference time / this time)",
             f"{'variant':<10}{'model':<11}{'anchors':>9}{'symbols':>11}{'thr':>4}{'enc s':>8}"
             f"{'dec s':>8}{'model s':>8}{'x enc':>7}{'x dec':>7}{'enc Msym/s':>11}"
             f"{'dec Msym/s':>11}{'MB':>8}  exact"]

    def f(v, fmt):
        return format(v, fmt) if v is not None else "-"

    for r in rows:
        model = r["model"] if len(r["model"]) <= 10 else "run"
        lines.append(f"{r['variant']:<10}{model:<11}{r['anchors']:>9}{r['symbols']:>11}"
                     f"{r['threads']:>4}{r['encode_s']:>8.2f}{r['decode_s']:>8.2f}"
                     f"{f(r['model_s'], '>8.2f'):>8}{f(r['x_enc'], '>6.2f'):>6}x"
                     f"{f(r['x_dec'], '>6.2f'):>6}x{r['enc_msym_s']:>11.2f}{r['dec_msym_s']:>11.2f}"
                     f"{r['total_mb']:>8.2f}  {r['exact']}")
        if r["variant"] == "run":
            lines.append(f"    run: {r['model']}")
        lines.append("    bytes: " + ", ".join(f"{k} {v}" for k, v in r["bytes"].items()))
    lines.append("paper figures: HAC on an A100, average Mip-NeRF360 model (~500k anchors): "
                 "encode 6.96 s, decode 18.72 s")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--anchors", type=int, default=500_000)
    ap.add_argument("--model", default="hac", choices=["hac", "hacpp", "factorized"])
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--run", action="append", default=[], help="also a trained run folder")
    a = ap.parse_args(argv)
    rows = run_codec_bench(a.anchors, a.model, a.threads, repeats=a.repeats)
    rows += [run_model_codec_bench(r) for r in a.run]
    print(format_codec_bench(rows))


if __name__ == "__main__":
    main()
