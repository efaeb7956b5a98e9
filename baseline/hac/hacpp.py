"""HAC++'s entropy model (``hacpp``): a hyperprior, a channel context and a two-component
mixture for the main coded attribute (docs/method.md section 6; YihangChen-ee/HAC-plus).

* **Hyperprior**: HAC's binary hash grid at the anchor position, then ``Linear(96, 100) ReLU
  Linear(100, n_out)`` giving, in order: for the *main* attribute mean, scale and a mixture
  logit per value (3 d), for every other attribute mean and scale (2 d), then one
  quantization-step adjustment per attribute. For HAC's feat 50 / scaling 6 / offsets 30 that is
  HAC++'s 225 outputs.
* **Channel context** for the main attribute (HAC: feat; a predicting provider: its residual): its d values
  are split into ``n_chunks`` (5) contiguous chunks as evenly as possible (50 -> 5 x 10, 25 ->
  5 x 5, 10 -> 5 x 2; the documented choice for dims HAC++ does not define). Chunk k's network
  sees the already quantized chunks 0..k-1 and the hyperprior's [mean | scale | logit] of the
  main attribute: ``Linear(3 d + sum(chunks < k), 40) LeakyReLU(0.01) Linear(40, 3 size_k)`` ->
  mean, scale, logit of the chunk's values.
* **Likelihood** of the main attribute: ``w_h L(mean_h, scale_h) + w_c L(mean_c, scale_c)``
  with per-value softmax weights over the two logits, each L HAC's quantized Gaussian, floored
  at 1e-6. The other attributes keep HAC's single Gaussian from the hyperprior.
* **Training** runs all chunks in one pass on the values the likelihood is evaluated on (noisy
  in training, teacher forcing); **coding** runs chunk by chunk on the decoded values, vectorised
  over the anchors of a coding chunk (five sequential passes), through the exact path: the
  hyperprior and every chunk network in fixed point (:class:`~baseline.hac.exact.ExactMLP`), the
  mixture range coded by :mod:`baseline.codec.mixture`. Its probabilities are the training
  path's up to the fixed point's ~2^-20 relative perturbation and the coder's 16-bit
  frequencies.

Options: ``grid`` / ``grid_options``, ``context`` ("own"; "provider": the feature provider's
grid, :class:`~baseline.hac.entropy.HashGridContext`), ``hidden`` (100), ``main`` (the main attribute's name,
default the first coded attribute, which providers list first: feat, residual), ``n_chunks``
(5), ``chunk_hidden`` (40), and the base options ``chunk``, ``escape_limit``, ``pipeline``.
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from baseline.codec.container import BitstreamError
from baseline.codec.fields import header_error, int_field, str_field
from baseline.codec.format import MAX_HIDDEN
from baseline.codec.mixture import MixtureStreamDecoder, MixtureStreamEncoder
from baseline.codec.weights import pack_state_dict, round_module_, unpack_state_dict
from baseline.contracts import CodedAttribute
from baseline.hac.entropy import (LIKELIHOOD_FLOOR, SCALE_FLOOR, EntropyModel, HashGridContext,
                                  gaussian_bits)
from baseline.hac.exact import ExactMLP, det_exp, det_tanh
from baseline.hac.hashgrid import FEATURE_BITS, BinaryHashGrid
from baseline.hac.quant import Q_FLOOR, adaptive_q, clamp_halfwidth

# The channel networks' exact inputs: fixed point with 16 fraction bits, |value| <= 2^10 (larger
# values are clamped, alike on both sides). A wider range would cost the exact weights precision
# (ExactMLP keeps every partial sum below 2^52): 2^26 x fan-in 190 leaves ~18 bits per weight.
CTX_FRAC = 16
CTX_BITS = 26
_C_LIMIT = float(2 ** 40)


def chunk_sizes(dims: int, n_chunks: int) -> list[int]:
    """``dims`` split into ``min(n_chunks, dims)`` contiguous chunks, the first ones larger."""
    n = max(1, min(int(n_chunks), int(dims)))
    base, extra = divmod(int(dims), n)
    return [base + (1 if i < extra else 0) for i in range(n)]


def mixture_likelihood(x, q, m1, s1, l1, m2, s2, l2) -> torch.Tensor:
    """``max(w1 L1 + w2 L2, 1e-6)``: L the quantized Gaussians of bin width ``q``, ``w`` the
    softmax of the logits ``l1``, ``l2`` (HAC++'s ``Entropy_gaussian_mix_prob_2``)."""
    w = torch.softmax(torch.stack([l1, l2], dim=-1), dim=-1)
    p = w[..., 0] * _bin_mass(x, m1, s1, q) + w[..., 1] * _bin_mass(x, m2, s2, q)
    return torch.clamp(p, min=LIKELIHOOD_FLOOR)


def _bin_mass(x, mean, scale, q):
    """A quantized Gaussian's mass on the bin of ``x``, not floored (the mixture is)."""
    scale = torch.clamp(scale, min=SCALE_FLOOR)
    return torch.abs(torch.special.ndtr((x + 0.5 * q - mean) / scale)
                     - torch.special.ndtr((x - 0.5 * q - mean) / scale))


class HACPPEntropyModel(HashGridContext, EntropyModel):
    kind = "hacpp"
    SECTION_LABELS = {"grid": "grid", "mlp": "hyperprior", "ctx": "channel_context"}
    HEADER_KEYS = HashGridContext.HEADER_KEYS | {"main", "n_chunks", "chunk_hidden"}

    @classmethod
    def check_header(cls, entry: dict, key: str) -> int:
        entries = super().check_header(entry, key)
        if "main" in entry and str_field(entry["main"], f"{key}.main") not in [
                a[0] for a in entry["attrs"]]:
            raise header_error(f"{key}.main", f"{entry['main']!r:.60} is not a coded attribute")
        if "n_chunks" in entry:
            int_field(entry["n_chunks"], f"{key}.n_chunks", 1, 64)
        if "chunk_hidden" in entry:
            int_field(entry["chunk_hidden"], f"{key}.chunk_hidden", 1, MAX_HIDDEN)
        return entries

    def __init__(self, attrs: Sequence[CodedAttribute], n_masks: int, *,
                 grid: Optional[BinaryHashGrid] = None, grid_options: Optional[dict] = None,
                 hidden: int = 100, main: Optional[str] = None, n_chunks: int = 5,
                 chunk_hidden: int = 40, context: str = "own", **options):
        super().__init__(attrs, n_masks, **options)
        self.main = self.attrs[0].name if main is None else str(main)
        ma = {a.name: a for a in self.attrs}.get(self.main)
        if ma is None:
            raise ValueError(f"hacpp: main attribute '{self.main}' is not coded "
                             f"({[a.name for a in self.attrs]})")
        if ma.masked:
            raise ValueError(f"hacpp: the main attribute '{self.main}' must not be masked")
        self.main_attr = ma
        self._init_grid(grid, grid_options, context)
        self.hidden = int(hidden)
        self.n_chunks = int(n_chunks)
        self.chunk_hidden = int(chunk_hidden)
        self.sizes = chunk_sizes(ma.dims, self.n_chunks)
        d = ma.dims
        self.n_out = sum((3 if a.name == self.main else 2) * a.dims for a in self.attrs) \
            + len(self.attrs)
        self.mlp = nn.Sequential(nn.Linear(self.ctx_grid.output_dim, self.hidden), nn.ReLU(),
                                 nn.Linear(self.hidden, self.n_out))
        offs = np.concatenate([[0], np.cumsum(self.sizes)]).tolist()
        self.offsets = offs
        self.ctx = nn.ModuleList([
            nn.Sequential(nn.Linear(3 * d + offs[k], self.chunk_hidden), nn.LeakyReLU(0.01),
                          nn.Linear(self.chunk_hidden, 3 * self.sizes[k]))
            for k in range(len(self.sizes))])

    # ------------------------------------------------------------------ configuration
    def config(self) -> dict:
        cfg = super().config()
        cfg.update(hidden=self.hidden, **self.grid_config(), main=self.main,
                   n_chunks=self.n_chunks, chunk_hidden=self.chunk_hidden)
        return cfg

    # ------------------------------------------------------------------ hyperprior
    def _split(self, out, exact: bool) -> dict:
        """Per attribute (mean, scale clamped, q [n,1]); the main's raw [mean|scale|logit] too."""
        P, off = {}, 0
        adj_off = self.n_out - len(self.attrs)
        for i, a in enumerate(self.attrs):
            mean = out[:, off:off + a.dims]
            raw_scale = out[:, off + a.dims:off + 2 * a.dims]
            off += 2 * a.dims
            if a.name == self.main:
                logit = out[:, off:off + a.dims]
                off += a.dims
                P["__hyper__"] = (mean, raw_scale, logit)
            adj = out[:, adj_off + i:adj_off + i + 1]
            if exact:
                t = torch.from_numpy(det_tanh(adj.numpy()))
                q = torch.clamp(a.q0 * (1.0 + t), min=a.q0 * Q_FLOOR)
            else:
                q = adaptive_q(a.q0, adj)
            P[a.name] = (mean, torch.clamp(raw_scale, min=SCALE_FLOOR), q)
        return P

    def _exact_context(self):
        """The fixed-point hyperprior and channel networks of one coding pass (built from the
        weights as they are now: after :meth:`serialize` rounded them)."""
        return (ExactMLP(self.mlp, in_bits=FEATURE_BITS, in_frac=FEATURE_BITS),
                [ExactMLP(net, in_bits=CTX_BITS, in_frac=CTX_FRAC) for net in self.ctx])

    def params(self, xyz: torch.Tensor, exact: bool = False, _ctx=None) -> dict:
        """The hyperprior's parameters (the main attribute's are its first component; its
        channel context needs the values: :meth:`main_params`)."""
        if exact:
            with torch.no_grad():
                hyper, nets = _ctx if _ctx is not None else self._exact_context()
                P = self._split(hyper(self.ctx_grid.features_fixed(xyz)), exact=True)
                P["__ctx_nets__"] = nets
                return P
        return self._split(self.mlp(self._features(xyz)), exact=False)

    def _ctx_inputs(self, k: int, prev: torch.Tensor, hyper) -> torch.Tensor:
        return torch.cat([prev[:, :self.offsets[k]], *hyper], dim=-1)

    def main_params(self, hyper, values: torch.Tensor):
        """Chunk networks in one pass (teacher forcing) on ``values`` [n, d]: the second
        component's (mean [n,d], scale [n,d], logit [n,d])."""
        outs = [self.ctx[k](self._ctx_inputs(k, values, hyper)) for k in range(len(self.sizes))]
        means, scales, logits = [], [], []
        for k, o in enumerate(outs):
            m, s, lg = o.split(self.sizes[k], dim=-1)
            means.append(m), scales.append(s), logits.append(lg)
        return (torch.cat(means, -1), torch.clamp(torch.cat(scales, -1), min=SCALE_FLOOR),
                torch.cat(logits, -1))

    # ------------------------------------------------------------------ training
    def train_params(self, xyz: torch.Tensor, rows: torch.Tensor):
        h = self.mlp[1](self.mlp[0](self._features(xyz)))
        last = self.mlp[2]
        adj_off = self.n_out - len(self.attrs)
        adj = F.linear(h, last.weight[adj_off:], last.bias[adj_off:])
        q_all = {a.name: adaptive_q(a.q0, adj[:, i:i + 1]) for i, a in enumerate(self.attrs)}
        P = self._split(last(h[rows]), exact=False)
        P = {k: (v if k.startswith("__") else (v[0], v[1], q_all[k][rows])) for k, v in P.items()}
        return q_all, P

    def _attr_bits(self, a, xs, qs, P):
        """The main attribute's bits come from the two-component mixture."""
        if a.name != self.main:
            return super()._attr_bits(a, xs, qs, P)
        mean, scale, _ = P[a.name]
        hyper = P["__hyper__"]
        m2, s2, l2 = self.main_params(hyper, xs)
        return -torch.log2(mixture_likelihood(xs, qs, mean, scale, hyper[2], m2, s2, l2))

    # ------------------------------------------------------------------ coding
    @staticmethod
    def _fixed(v: torch.Tensor) -> torch.Tensor:
        """float64 values -> fixed-point integers (rounded half to even, clamped): the
        channel networks' exact inputs."""
        lim = float(2 ** CTX_BITS)
        return torch.clamp(torch.round(v * float(2 ** CTX_FRAC)), -lim, lim)

    def _stream_encoder(self, attr):
        if attr.name == self.main:
            return MixtureStreamEncoder(self.escape_limit)
        return super()._stream_encoder(attr)

    def _stream_decoder(self, attr, payload, limit):
        if attr.name == self.main:
            return MixtureStreamDecoder(payload, what=attr.name, escape_limit=limit)
        return super()._stream_decoder(attr, payload, limit)

    def _code_attr(self, a, M, x, msel, coder, encode, emit, x_mean):
        if a.name != self.main:
            return super()._code_attr(a, M, x, msel, coder, encode, emit, x_mean)
        P = M["__P__"]
        mean_h, scale_h, q = P[a.name]                      # float64, q [n,1]
        hyper = P["__hyper__"]
        hyper_fx = [self._fixed(t) for t in hyper]
        n = mean_h.shape[0]
        out = torch.zeros(n, a.dims, dtype=torch.float64)
        nets = P["__ctx_nets__"]
        if encode:
            half = clamp_halfwidth(q, a.q0)
            k_all = torch.round(torch.maximum(torch.minimum(x, x_mean + half), x_mean - half) / q)
        for k, net in enumerate(nets):
            lo, hi = self.offsets[k], self.offsets[k + 1]
            inp = torch.cat([self._fixed(out[:, :lo])] + hyper_fx, dim=-1)
            o = net(inp)                                   # exact float64 [n, 3 size]
            m2, s2, l2 = o.split(self.sizes[k], dim=-1)
            s2 = torch.clamp(s2, min=SCALE_FLOOR)
            qk = q.expand(-1, hi - lo)
            m1 = mean_h[:, lo:hi]
            s1 = scale_h[:, lo:hi]
            c = torch.clamp(torch.round(m1 / qk), -_C_LIMIT, _C_LIMIT)
            l1 = hyper[2][:, lo:hi]
            d = l1 - l2                                    # w1 = 1 / (1 + exp(l2 - l1))
            w1 = 1.0 / (1.0 + torch.from_numpy(det_exp(np.clip(-d.numpy(), -700, 700))))
            args = ((m1 / qk - c).reshape(-1).numpy(), (s1 / qk).reshape(-1).numpy(),
                    (m2 / qk - c).reshape(-1).numpy(), (s2 / qk).reshape(-1).numpy(),
                    w1.reshape(-1).numpy())
            if encode:
                kk = k_all[:, lo:hi]
                if emit:
                    coder.add((kk - c).reshape(-1).numpy().astype(np.int64), *args)
            else:
                sym = coder.decode(*args)
                kk = torch.from_numpy(sym.astype(np.float64)).reshape(n, hi - lo) + c
            out[:, lo:hi] = kk * qk
        return out

    @torch.no_grad()
    def exact_bits(self, xyz, values, gauss_mask=None) -> Dict[str, torch.Tensor]:
        """Per-anchor bits [N] (float64) of every attribute under the coding path's own
        probabilities: the exact hyperprior, the channel networks run chunk by chunk on the
        quantized values the decoder will have, the mixture in float64 (what the range coder
        codes, before its 16-bit frequencies). The training path's bits on the same rounded
        values (``forward(training=False)``) differ only by the fixed point's perturbation."""
        vq = self.quantize_for_coding(xyz, values, gauss_mask)
        xyz = xyz.detach().cpu()
        n = xyz.shape[0]
        ctx = self._exact_context()
        out = {a.name: torch.zeros(n, dtype=torch.float64) for a in self.attrs}
        for s in range(0, n, self.chunk):
            e = min(n, s + self.chunk)
            P = self.params(xyz[s:e], exact=True, _ctx=ctx)
            for a in self.attrs:
                x = vq[a.name][s:e].detach().cpu().double()
                mean, scale, q = P[a.name]
                if a.name != self.main:
                    b = gaussian_bits(x, mean, scale, q)
                    m = self.value_mask(a, gauss_mask[s:e] if gauss_mask is not None else None,
                                        e - s)
                    out[a.name][s:e] = (b * m.double() if m is not None else b).sum(-1)
                    continue
                hyper = P["__hyper__"]
                hyper_fx = [self._fixed(t) for t in hyper]
                for k, net in enumerate(P["__ctx_nets__"]):
                    lo, hi = self.offsets[k], self.offsets[k + 1]
                    o = net(torch.cat([self._fixed(x[:, :lo])] + hyper_fx, dim=-1))
                    m2, s2, l2 = o.split(self.sizes[k], dim=-1)
                    lik = mixture_likelihood(x[:, lo:hi], q, mean[:, lo:hi], scale[:, lo:hi],
                                             hyper[2][:, lo:hi], m2,
                                             torch.clamp(s2, min=SCALE_FLOOR), l2)
                    out[a.name][s:e] += -torch.log2(lik).sum(-1)
        return out

    # ------------------------------------------------------------------ serialisation
    def serialize(self, precision: str = "float32", used_xyz=None) -> Dict[str, bytes]:
        round_module_(self.mlp, precision)
        round_module_(self.ctx, precision)
        sd = self._grid_state()
        sd.update({f"mlp.{k}": v for k, v in self.mlp.state_dict().items()})
        return {**self._grid_sections(used_xyz),
                "mlp": pack_state_dict(sd, precision, keep=("xyz_min", "xyz_max")),
                "ctx": pack_state_dict(self.ctx.state_dict(), precision)}

    def load_serialized(self, blobs: Dict[str, bytes], used_xyz=None) -> None:
        for k in ("mlp", "ctx"):
            if k not in blobs:
                raise BitstreamError(f"entropy model: missing section '{k}'")
        sd = unpack_state_dict(blobs["mlp"], what="entropy model weights")
        cd = unpack_state_dict(blobs["ctx"], what="channel context weights")
        self._load_grid(blobs, sd, used_xyz)
        try:
            self.mlp.load_state_dict({k[4:]: v for k, v in sd.items() if k.startswith("mlp.")})
            self.ctx.load_state_dict(cd)
        except (KeyError, RuntimeError, ValueError) as e:
            raise BitstreamError(f"entropy model weights do not fit the model: {e}") from None


def mixture_bits_reference(x, q, m1, s1, l1, m2, s2, l2) -> torch.Tensor:
    """The mixture's bits written out component by component (tests compare the model's)."""
    w1 = torch.exp(l1) / (torch.exp(l1) + torch.exp(l2))
    c1 = (torch.special.ndtr((x + 0.5 * q - m1) / s1) - torch.special.ndtr((x - 0.5 * q - m1) / s1))
    c2 = (torch.special.ndtr((x + 0.5 * q - m2) / s2) - torch.special.ndtr((x - 0.5 * q - m2) / s2))
    return -torch.log2(torch.clamp(w1 * c1.abs() + (1 - w1) * c2.abs(), min=LIKELIHOOD_FLOOR))
