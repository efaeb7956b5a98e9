"""Entropy models of the coded per-anchor attributes, behind one CompressAI-like interface.

One module of about 650 lines: both registered models and the probability code that training
(rate) and coding (compress / decompress) share, kept side by side so the two paths cannot part.

Registered as ``entropy_model`` components (see :mod:`baseline.hac`):

* ``hac``        — HAC's hash-grid context model (docs/method.md section 3): a :class:`BinaryHashGrid` queried at
  the anchor position, then ``Linear(96, 100) ReLU Linear(100, sum(2 d) + n_attrs)`` giving per
  attribute a mean and a scale per value (scale clamped >= 1e-9, no activation, as HAC) and
  one quantization-step adjustment per anchor (``Q = q0 (1 + tanh(adj))``). For the baseline
  attributes feat 50 / scaling 6 / offsets 30 that is 175 outputs, in HAC's order
  ``[mean_feat, scale_feat, mean_scaling, scale_scaling, mean_offsets, scale_offsets,
  adj_feat, adj_scaling, adj_offsets]``.
* ``factorized`` — no context: a learned Gaussian per channel (mean, log-scale), fixed Q = q0.

Interface (``EntropyModel(attrs: Sequence[CodedAttribute], n_masks: int, **options)``)::

    params(xyz [N,3], exact=False) -> {name: (mean [N,d], scale [N,d], q [N,1])}
        THE probability function. exact=False: differentiable float path (training, estimates).
        exact=True: the bit-reproducible float64 CPU path that compress and decompress share.
    forward(xyz, values {name: [N,d]}, gauss_mask [N,K] or None, training=True, adaptive_q=True)
        -> (values_hat {name: [N,d]}, bits {name: [N]} per-anchor bits, masked values excluded)
        training: x + U(-.5,.5) Q; else straight-through rounding (clamped to mean +- 15000 Q).
        bits = -log2 max(|Phi((x+Q/2-mu)/s) - Phi((x-Q/2-mu)/s)|, 1e-6); in training a
        masked attribute's bits are weighted by the float gauss_mask (its straight-through
        gradient reaches the mask logits, as in HAC), otherwise by the boolean mask.
    hash_bits() -> scalar tensor (0 for factorized)
    quantize_for_coding(xyz, values, gauss_mask) -> {name: [N,d] float32}  what decode returns
    compress(xyz, values, gauss_mask, return_values=False) -> {name: bytes} (, values)
    decompress(xyz, blobs, gauss_mask, n) -> {name: [N,d] float32}
    serialize(precision) -> {name: bytes};  load_serialized(blobs);  config() -> dict

Exact decoding. Coding uses ``params(exact=True)`` on both sides: hash-grid features with
integer interpolation weights rounded to 2^-20, the context MLP in fixed point held in float64
(every matmul partial sum is an integer below 2^53, hence exact in any order), and a tanh made of
correctly rounded operations (:mod:`baseline.hac.exact`). Nothing depends on thread count,
BLAS, SIMD or chunking, so the decoder reproduces the encoder's (mean, scale, Q) bit for bit;
rounding to a coarse grid is unnecessary. The values are coded as integer symbols
``s = round(x / Q) - round(mu / Q)`` with a quantized Gaussian of mean ``mu/Q - round(mu/Q)`` and
std ``scale/Q`` (constriction's leaky quantizer, range coder); the decoder returns
``(s + round(mu/Q)) * Q``, bit-identical to the encoder's quantized value. Weights must be at the
stored precision before coding: :meth:`serialize` rounds them in place.
Options common to both models: ``chunk`` (anchors per coding chunk, 32768), ``escape_limit``
(|symbol - round(mu/Q)| beyond which a value is stored raw, 16383), ``pipeline`` (compute the
next chunk's model in a worker thread while the range coder runs, True).
Remaining assumption: constriction's quantizer (compiled Rust) evaluates the Gaussian CDF the
same way on both machines; it is single-threaded and deterministic for identical inputs.
"""
from __future__ import annotations

import math
import struct
from concurrent.futures import ThreadPoolExecutor
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from baseline import registry
from baseline.codec.container import BitstreamError
from baseline.codec.fields import bool_field, header_error, int_field, unknown_keys
from baseline.codec.format import MAX_CHUNK, MAX_ESCAPE, MAX_HIDDEN
from baseline.contracts import CodedAttribute
from baseline.codec.rangecoder import (DEFAULT_ESCAPE_LIMIT, GaussianStreamDecoder,
                                       GaussianStreamEncoder)
from baseline.codec.weights import pack_state_dict, round_module_, unpack_state_dict
from baseline.hac.exact import ExactMLP, det_exp, det_tanh
from baseline.hac.hashgrid import FEATURE_BITS, BinaryHashGrid
from baseline.hac.layout import check_grid_options, grid_options
from baseline.hac.quant import (Q_FLOOR, adaptive_q, clamp_halfwidth, noise_quantize, ste_round,
                                ste_round_q)

LIKELIHOOD_FLOOR = 1e-6
SCALE_FLOOR = 1e-9
_C_LIMIT = float(2 ** 40)  # |round(mu / Q)| cap (keeps symbols integral in float64)
# Attribute stream: anchors per coding chunk, escape limit, then the Gaussian stream.
_BLOB_HDR = struct.Struct("<II")

Params = Dict[str, Tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


def gaussian_likelihood(x: torch.Tensor, mean: torch.Tensor, scale: torch.Tensor, q) -> torch.Tensor:
    """``max(|Phi((x + q/2 - mean)/scale) - Phi((x - q/2 - mean)/scale)|, 1e-6)``."""
    scale = torch.clamp(scale, min=SCALE_FLOOR)
    upper = torch.special.ndtr((x + 0.5 * q - mean) / scale)
    lower = torch.special.ndtr((x - 0.5 * q - mean) / scale)
    return torch.clamp(torch.abs(upper - lower), min=LIKELIHOOD_FLOOR)


def gaussian_bits(x, mean, scale, q) -> torch.Tensor:
    return -torch.log2(gaussian_likelihood(x, mean, scale, q))


class EntropyModel(nn.Module):
    """Base class: attribute bookkeeping, training forward, and the shared coding loop
    (implements :class:`baseline.contracts.EntropyModel`)."""

    kind = "base"
    SECTION_LABELS: dict = {}
    TRAINING_SEMANTICS = 1
    # the fields of its header entry (:meth:`config`, plus the coding options)
    HEADER_KEYS = frozenset({"kind", "n_masks", "attrs", "chunk", "escape_limit", "pipeline"})

    @classmethod
    def build(cls, cfg, attrs: Sequence[CodedAttribute], n_masks: int, n_anchors: int):
        """The model a training config selects (``cfg.entropy``), its head sized from ``attrs``."""
        return cls(attrs, n_masks)

    @classmethod
    def check_header(cls, entry: dict, key: str) -> int:
        """Check the options of a file header's entry of this model (kind, masks and attributes
        are checked by the header); returns the hash-grid entries it makes the decoder build."""
        unknown_keys(entry, cls.HEADER_KEYS, key)
        if "chunk" in entry:
            int_field(entry["chunk"], f"{key}.chunk", 1, MAX_CHUNK)
        if "escape_limit" in entry:
            int_field(entry["escape_limit"], f"{key}.escape_limit", 1, MAX_ESCAPE)
        if "pipeline" in entry:
            bool_field(entry["pipeline"], f"{key}.pipeline")
        return 0

    def __init__(self, attrs: Sequence[CodedAttribute], n_masks: int, *, chunk: int = 32768,
                 escape_limit: int = DEFAULT_ESCAPE_LIMIT, pipeline: bool = True):
        super().__init__()
        attrs = tuple(attrs)
        if not attrs:
            raise ValueError("an entropy model needs at least one coded attribute")
        names = [a.name for a in attrs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate coded attribute names: {names}")
        self.n_masks = int(n_masks)
        for a in attrs:
            if a.dims <= 0 or not (a.q0 > 0 and math.isfinite(a.q0)):
                raise ValueError(f"invalid coded attribute {a}")
            if a.masked and (self.n_masks <= 0 or a.dims % self.n_masks):
                raise ValueError(f"masked attribute '{a.name}' has {a.dims} dims, not a multiple "
                                 f"of n_masks={self.n_masks}")
        self.attrs = attrs
        self.chunk = int(chunk)
        self.escape_limit = int(escape_limit)
        if not 0 < self.escape_limit <= MAX_ESCAPE:
            raise ValueError(f"escape_limit must be in [1, {MAX_ESCAPE}], got {escape_limit}")
        if not 0 < self.chunk <= MAX_CHUNK:
            raise ValueError(f"chunk must be in [1, {MAX_CHUNK}], got {chunk}")
        self.pipeline = bool(pipeline)

    # ----------------------------------------------------------- to override
    def params(self, xyz: torch.Tensor, exact: bool = False, _ctx=None) -> Params:
        raise NotImplementedError

    def train_params(self, xyz: torch.Tensor, rows: torch.Tensor):
        """Training-path parameters when bits are needed on ``rows`` [S] only.

        Returns ``(q_all, P_rows)``: the quantization step of every anchor per attribute
        ({name: [N,1]}, it quantizes all of them) and (mean [S,d], scale [S,d], q [S,1]) of the
        rows. Default: from :meth:`params`; models override it to skip work on the other rows.
        """
        P = self.params(xyz)
        return ({a.name: P[a.name][2] for a in self.attrs},
                {a.name: tuple(t[rows] for t in P[a.name]) for a in self.attrs})

    def _exact_context(self):
        """Precomputed state shared by all chunks of one exact pass (e.g. the fixed-point MLP)."""
        return None

    def hash_bits(self) -> torch.Tensor:
        return torch.zeros(())

    def set_bounds(self, xyz_min, xyz_max) -> None:
        """The anchors' box; a model without a positional context ignores it."""

    def config(self) -> dict:
        return {"kind": self.kind, "n_masks": self.n_masks,
                "attrs": [[a.name, a.dims, a.q0, a.masked] for a in self.attrs]}

    # ---------------------------------------------------------------- helpers
    def value_mask(self, attr: CodedAttribute, gauss_mask: Optional[torch.Tensor], n: int,
                   device=None) -> Optional[torch.Tensor]:
        """[n, d] bool of the values that are coded (None: all of them)."""
        if not attr.masked or gauss_mask is None:
            return None
        m = torch.as_tensor(gauss_mask, device=device)
        if m.ndim == 3 and m.shape[-1] == 1:
            m = m[..., 0]
        if m.shape != (n, self.n_masks):
            raise ValueError(f"gauss_mask must be [{n}, {self.n_masks}], got {tuple(m.shape)}")
        per = attr.dims // self.n_masks
        return (m > 0.5).repeat_interleave(per, dim=1) if m.is_floating_point() else \
            m.bool().repeat_interleave(per, dim=1)

    def value_weights(self, attr: CodedAttribute, gauss_mask: Optional[torch.Tensor],
                      n: int) -> Optional[torch.Tensor]:
        """[n, d] float weights of the values' bits in the training rate (None: all 1).

        HAC (``generate_neural_gaussians``) multiplies the offsets' bits by the Gaussian mask as
        the straight-through float it is in training (forward 0/1, backward the sigmoid's
        gradient), so the offsets' rate pushes every sampled Gaussian's mask logit toward "off"
        in proportion to its offsets' bits. A float ``gauss_mask`` is used as it is (its
        gradient kept); a boolean one gives 0/1 weights. The codec uses :meth:`value_mask`.
        """
        if not attr.masked or gauss_mask is None:
            return None
        m = gauss_mask
        if not torch.is_tensor(m):
            m = torch.as_tensor(m)
        if m.ndim == 3 and m.shape[-1] == 1:
            m = m[..., 0]
        if m.shape != (n, self.n_masks):
            raise ValueError(f"gauss_mask must be [{n}, {self.n_masks}], got {tuple(m.shape)}")
        if not m.is_floating_point():
            m = m.float()
        return m.repeat_interleave(attr.dims // self.n_masks, dim=1)

    def _check_values(self, values, n):
        for a in self.attrs:
            if a.name not in values:
                raise KeyError(f"missing coded attribute '{a.name}'")
            v = values[a.name]
            if v.shape != (n, a.dims):
                raise ValueError(f"attribute '{a.name}' must be [{n}, {a.dims}], got {tuple(v.shape)}")

    # --------------------------------------------------------------- training
    def forward(self, xyz: torch.Tensor, values: Dict[str, torch.Tensor],
                gauss_mask: Optional[torch.Tensor] = None, training: bool = True,
                adaptive_q: bool = True, rate_rows: Optional[torch.Tensor] = None,
                decoder_quant: str = "noise", bit_weights: Optional[dict] = None):
        """Quantized values and per-anchor bits per attribute (see module docstring).

        ``adaptive_q=False`` uses the base step q0 (HAC's phase 3001..10000).
        ``rate_rows`` ([S] indices or [N] bool): bits are computed for these anchors only and
        returned as [S] (the rate loss uses a ~5% sample; the likelihood of the other 95% would
        be computed and thrown away). Default: all anchors, [N].
        ``decoder_quant`` (training only): the returned values, which the decoder sees, are
        ``x + U(-.5,.5) Q`` ("noise", HAC) or the rounded values of evaluation with a
        straight-through gradient ("ste", :func:`baseline.hac.quant.ste_round_q`); the bits are
        estimated on the noisy values either way.
        ``bit_weights`` {name: [N, d] float}: weigh those attributes' bits by these instead of
        the Gaussian mask (a mask-training strategy's choice, e.g. anchor masks).
        """
        if decoder_quant not in ("noise", "ste"):
            raise ValueError(f"decoder_quant must be 'noise' or 'ste', got {decoder_quant!r}")
        n = xyz.shape[0]
        self._check_values(values, n)
        if rate_rows is not None and rate_rows.dtype == torch.bool:
            rate_rows = rate_rows.nonzero()[:, 0]
        if rate_rows is None:
            P = self.params(xyz)
            q_all = {a.name: P[a.name][2] for a in self.attrs}
        else:
            q_all, P = self.train_params(xyz, rate_rows)
        values_hat, bits = {}, {}
        for a in self.attrs:
            x = values[a.name]
            mean, scale, _ = P[a.name]
            q = q_all[a.name]
            if not adaptive_q:
                q = torch.full_like(q, a.q0)
            x_hat = noise_quantize(x, q) if training else ste_round(x, q, q0=a.q0)
            # training: the float straight-through mask weighs the bits (its gradient trains
            # the masks, as HAC's rate does); evaluation: the codec's boolean mask
            if bit_weights is not None and bit_weights.get(a.name) is not None:
                m = bit_weights[a.name]
            else:
                m = (self.value_weights(a, gauss_mask, n) if training
                     else self.value_mask(a, gauss_mask, n, device=x.device))
            if rate_rows is not None:
                b = self._attr_bits(a, x_hat[rate_rows], q[rate_rows], P)
                m = m[rate_rows] if m is not None else None
            else:
                b = self._attr_bits(a, x_hat, q, P)
            if m is not None:
                b = b * m.to(b.dtype)
            if training and decoder_quant == "ste":
                x_hat = ste_round_q(x, q, q0=a.q0)
            values_hat[a.name] = x_hat
            bits[a.name] = b.sum(dim=-1)
        return values_hat, bits

    def _attr_bits(self, a: CodedAttribute, xs: torch.Tensor, qs: torch.Tensor, P: dict) -> torch.Tensor:
        """Estimated bits [S, d] of quantized values ``xs`` with steps ``qs``; ``P`` holds the
        rows' parameters (``P[name] = (mean, scale, q)``). A subclass with another likelihood
        for some attribute overrides this."""
        mean, scale, _ = P[a.name]
        return gaussian_bits(xs, mean, scale, qs)

    @torch.no_grad()
    def estimate_bits(self, xyz, values, gauss_mask=None) -> Dict[str, float]:
        """Total estimated bits per attribute with rounding (no noise)."""
        _, bits = self.forward(xyz, values, gauss_mask, training=False)
        return {k: float(v.sum()) for k, v in bits.items()}

    # ----------------------------------------------------------------- coding
    def _coding_pass(self, xyz, values=None, gauss_mask=None, blobs=None, encode=True, emit=True):
        """The one coding loop: encode (``emit=False``: only quantize) or decode, chunk by chunk."""
        n = int(xyz.shape[0])
        out_device = xyz.device
        xyz_cpu = xyz.detach().cpu()
        masks = {a.name: self.value_mask(a, gauss_mask, n) for a in self.attrs}
        masks = {k: (m.cpu() if m is not None else None) for k, m in masks.items()}
        if encode:
            self._check_values(values, n)
            xs = {a.name: values[a.name].detach().cpu() for a in self.attrs}  # float64 per chunk
            x_means = {}
            for a in self.attrs:
                x, m = xs[a.name], masks[a.name]
                if not torch.isfinite(x).all():
                    raise ValueError(f"attribute '{a.name}' holds non-finite values")
                sel = (x[m] if m is not None else x).to(torch.float64)
                x_means[a.name] = sel.mean() if sel.numel() else torch.zeros((), dtype=torch.float64)
                del sel
            coders = {a.name: self._stream_encoder(a) for a in self.attrs}
            chunk = self.chunk
        else:
            coders, chunks = {}, set()
            for a in self.attrs:
                if a.name not in blobs:
                    raise BitstreamError(f"missing coded section '{a.name}'")
                blob = bytes(blobs[a.name])
                if len(blob) < _BLOB_HDR.size:
                    raise BitstreamError(f"{a.name}: truncated attribute stream")
                ch, limit = _BLOB_HDR.unpack_from(blob)
                chunks.add(ch)
                if not 0 < limit <= MAX_ESCAPE:
                    raise BitstreamError(f"{a.name}: invalid escape limit {limit}")
                coders[a.name] = self._stream_decoder(a, blob[_BLOB_HDR.size:], limit)
            chunk = chunks.pop()
            if chunks or not 0 < chunk <= MAX_CHUNK:
                raise BitstreamError("attribute streams disagree on (or hold an invalid) chunk size")
        # k * Q is computed in float64 and stored as float32 (a deterministic cast)
        outs = {a.name: torch.zeros(n, a.dims, dtype=torch.float32) for a in self.attrs}
        ctx = self._exact_context()

        def model(s, e):
            """Coding distribution of anchors s..e: per attribute (c, mu_s, sd_s, q) [n, d]
            (the exact params under ``"__P__"`` for attributes coded their own way)."""
            P = self.params(xyz_cpu[s:e], exact=True, _ctx=ctx)
            res = {"__P__": P}
            for a in self.attrs:
                mean, scale, q = P[a.name]
                q = q.expand(-1, a.dims)
                c = torch.clamp(torch.round(mean / q), -_C_LIMIT, _C_LIMIT)
                res[a.name] = (c, mean / q - c, scale / q, q)
            return res

        # the decoder follows the encoder's chunking (stored in each attribute stream)
        bounds = [(s, min(n, s + chunk)) for s in range(0, n, chunk)]
        # The (torch, GIL-releasing) model of chunk i+1 is computed in a worker thread while the
        # main thread range-codes chunk i (constriction holds the GIL). Exactness does not depend
        # on it: the model is bit-reproducible under any threading.
        pool = ThreadPoolExecutor(max_workers=1) if (self.pipeline and len(bounds) > 1) else None
        try:
            fut = pool.submit(model, *bounds[0]) if (pool and bounds) else None
            for i, (s, e) in enumerate(bounds):
                if pool:
                    M = fut.result()
                    if i + 1 < len(bounds):
                        fut = pool.submit(model, *bounds[i + 1])
                else:
                    M = model(s, e)
                for a in self.attrs:
                    m = masks[a.name]
                    msel = m[s:e] if m is not None else None
                    x = xs[a.name][s:e].to(torch.float64) if encode else None
                    outs[a.name][s:e] = self._code_attr(
                        a, M, x, msel, coders[a.name], encode, emit,
                        x_means[a.name] if encode else None)
        finally:
            if pool:
                pool.shutdown(wait=True, cancel_futures=True)
        values_q = {k: v.to(device=out_device, dtype=torch.float32) for k, v in outs.items()}
        if encode:
            return {a.name: _BLOB_HDR.pack(chunk, self.escape_limit) + coders[a.name].finish()
                    for a in self.attrs}, values_q
        for a in self.attrs:
            coders[a.name].check_done()
        return values_q

    # ------------------------------------------------- per-attribute coding (overridable)
    def _stream_encoder(self, attr: CodedAttribute):
        return GaussianStreamEncoder(self.escape_limit)

    def _stream_decoder(self, attr: CodedAttribute, payload: bytes, limit: int):
        return GaussianStreamDecoder(payload, what=attr.name, escape_limit=limit)

    def _code_attr(self, a: CodedAttribute, M: dict, x, msel, coder, encode: bool, emit: bool,
                   x_mean):
        """Code (or decode) attribute ``a`` of one anchor chunk: ``M`` the chunk's model
        (:meth:`_coding_pass`), ``x`` [n, d] float64 values when encoding, ``msel`` [n, d] bool
        of the coded values (None: all). Returns the quantized values [n, d] float64, exactly
        what the decoder returns. Default: one quantized Gaussian per value."""
        c, mu_s, sd_s, q = M[a.name]

        def pick(t):
            return (t[msel] if msel is not None else t.reshape(-1)).numpy()

        if encode:
            half = clamp_halfwidth(q, a.q0)
            k = torch.round(torch.maximum(torch.minimum(x, x_mean + half), x_mean - half) / q)
            if emit:
                coder.add(pick(k - c).astype(np.int64), pick(mu_s), pick(sd_s))
        else:
            sym = coder.decode(pick(mu_s), pick(sd_s))
            kk = torch.from_numpy(sym.astype(np.float64))
            if msel is not None:
                k = torch.zeros_like(c)
                k[msel] = kk + c[msel]
            else:
                k = kk.reshape(c.shape) + c
        xq = k * q
        if msel is not None:
            xq = torch.where(msel, xq, torch.zeros_like(xq))
        return xq

    @torch.no_grad()
    def quantize_for_coding(self, xyz, values, gauss_mask=None) -> Dict[str, torch.Tensor]:
        """The values exactly as :meth:`decompress` will return them (float32)."""
        return self._coding_pass(xyz, values, gauss_mask, encode=True, emit=False)[1]

    @torch.no_grad()
    def compress(self, xyz, values, gauss_mask=None, return_values: bool = False):
        """Range code every attribute: ``{name: bytes}`` (and the decoded values if asked).

        ``xyz`` must be the positions the decoder will have (the dequantized 16-bit positions),
        ``gauss_mask`` the decoded masks, and the weights at their stored precision
        (:meth:`serialize` first). Each stream records its chunking and escape limit, so the
        decoder needs no coding options.
        """
        blobs, vq = self._coding_pass(xyz, values, gauss_mask, encode=True)
        return (blobs, vq) if return_values else blobs

    @torch.no_grad()
    def decompress(self, xyz, blobs: Dict[str, bytes], gauss_mask=None, n: Optional[int] = None):
        """Decode what :meth:`compress` produced, given the same positions and masks."""
        if n is not None and int(n) != int(xyz.shape[0]):
            raise ValueError(f"n={n} but {xyz.shape[0]} positions were given")
        return self._coding_pass(xyz, gauss_mask=gauss_mask, blobs=blobs, encode=False)

    # --------------------------------------------------------- serialisation
    def serialize(self, precision: str = "float32", used_xyz=None) -> Dict[str, bytes]:
        """Sections of the model. ``used_xyz`` [N, 3]: the coded anchors' positions, which the
        decoder knows first; a model with a hash grid then codes only the entries they read."""
        raise NotImplementedError

    def load_serialized(self, blobs: Dict[str, bytes], used_xyz=None) -> None:
        raise NotImplementedError


class HashGridContext:
    """Mixin for entropy models whose context is a binary hash grid over the anchors'
    positions: where the grid comes from, its bounds, its hash bits (the grid's own rate), its
    options and file sections, and the model's construction from a config (the grid layout of
    ``entropy.grid``, the context MLP's width).

    ``context`` "own" (HAC): a grid of its own (``self.grid``), trained by the rate, stored in
    the file. "provider" (``entropy.context = "provider"``): the feature provider's grid,
    read, never owned: not a submodule, so it is not in this model's parameters, state, hash
    bits or file sections; read in training through the grid's one shared pass per step
    (:meth:`BinaryHashGrid.shared_query`) with its gradient stopped, so the rate trains the
    context networks and not the provider's tables; its box stays the provider's.
    """

    HEADER_KEYS = EntropyModel.HEADER_KEYS | {"hidden", "grid", "grid_options", "context"}
    CONTEXTS = ("own", "provider")

    @classmethod
    def build(cls, cfg, attrs, n_masks: int, n_anchors: int, context_grid=None):
        """``context_grid``: the feature provider's grid, read as the context when
        ``entropy.context`` is "provider"."""
        if cfg.entropy.context == "provider":
            return cls(attrs, n_masks, grid=context_grid, hidden=cfg.entropy.context_hidden,
                       context="provider")
        return cls(attrs, n_masks, grid_options=grid_options(cfg.entropy.grid, n_anchors),
                   hidden=cfg.entropy.context_hidden)

    @classmethod
    def check_header(cls, entry: dict, key: str) -> int:
        """Returns the grid entries the decoder builds for it: none when the grid is the
        provider's (counted with the provider)."""
        context = entry.get("context", "own")
        if context not in cls.CONTEXTS:
            raise header_error(f"{key}.context", f"must be one of {cls.CONTEXTS}")
        if context == "provider":
            unknown_keys(entry, cls.HEADER_KEYS - {"grid", "grid_options"}, key)
        entries = super().check_header(entry, key)  # type: ignore[misc]
        if "hidden" in entry:
            int_field(entry["hidden"], f"{key}.hidden", 1, MAX_HIDDEN)
        if context == "provider":
            return 0
        for gk in ("grid", "grid_options"):
            if gk in entry:
                entries += check_grid_options(entry[gk], f"{key}.{gk}")
        if not entries:
            raise header_error(f"{key}.grid", f"the '{entry.get('kind')}' entropy model needs "
                                              f"its grid layout")
        return entries

    def _init_grid(self, grid: Optional[BinaryHashGrid], grid_options: Optional[dict],
                   context: str) -> None:
        if context not in self.CONTEXTS:
            raise ValueError(f"context must be one of {self.CONTEXTS}, got {context!r}")
        self.context = context
        if context == "provider":
            if grid is None:
                raise ValueError("a context read from the feature provider needs its grid")
            object.__setattr__(self, "_provider_grid", grid)
        else:
            self.grid = grid if grid is not None else BinaryHashGrid(**(grid_options or {}))

    @property
    def ctx_grid(self) -> BinaryHashGrid:
        """The grid the context is read from: its own, or the provider's."""
        return self._provider_grid if self.context == "provider" else self.grid

    def _features(self, xyz: torch.Tensor) -> torch.Tensor:
        """Training-path context features of ``xyz`` [N, 3]."""
        if self.context == "provider":
            return self._provider_grid.shared_query(xyz).detach()
        return self.grid(xyz)

    def set_bounds(self, xyz_min, xyz_max) -> None:
        """HAC's box at the rate's start; the provider's grid keeps the provider's box."""
        if self.context == "own":
            self.grid.set_bounds(xyz_min, xyz_max)

    def hash_bits(self) -> torch.Tensor:
        """Its own grid's bits; none when the grid is the provider's (the provider's
        ``rate_bits`` counts them)."""
        return self.grid.hash_bits() if self.context == "own" else torch.zeros(())

    def grid_config(self) -> dict:
        """Its entry's grid fields: the grid layout, or ``context = "provider"``."""
        if self.context == "provider":
            return {"context": "provider"}
        return {"grid": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in self.grid.config.items()}}

    def _grid_state(self) -> dict:
        """Its own grid's bounds, stored beside the context weights (none for the provider's)."""
        if self.context == "provider":
            return {}
        return {"xyz_min": self.grid.xyz_min, "xyz_max": self.grid.xyz_max}

    def _grid_sections(self, used_xyz) -> Dict[str, bytes]:
        """Section ``grid`` of its own grid (with ``used_xyz`` only the entries those positions
        read); none for the provider's."""
        if self.context == "provider":
            return {}
        used = None if used_xyz is None else self.grid.used_values(used_xyz)
        return {"grid": self.grid.encode_bits(used)}

    def _load_grid(self, blobs: Dict[str, bytes], sd: dict, used_xyz) -> None:
        """Its own grid from section ``grid`` and the bounds in ``sd`` (popped); with the
        provider's grid, a ``grid`` section is an error."""
        if self.context == "provider":
            if "grid" in blobs:
                raise BitstreamError("entropy model: a grid section in a file whose context is "
                                     "the feature provider's grid")
            return
        if "grid" not in blobs:
            raise BitstreamError("entropy model: missing section 'grid'")
        try:
            self.grid.set_bounds(sd.pop("xyz_min"), sd.pop("xyz_max"))
        except (KeyError, ValueError) as e:
            raise BitstreamError(f"entropy model weights do not fit the model: {e}") from None
        used = None if used_xyz is None else self.grid.used_values(used_xyz)
        self.grid.decode_bits(blobs["grid"], used)


class HACEntropyModel(HashGridContext, EntropyModel):
    """HAC's hash-grid context model (see the module docstring).

    Options: ``grid`` (a :class:`BinaryHashGrid` to use), or ``grid_options`` (its constructor
    arguments, default HAC's layout); ``context`` ("own", or "provider" with ``grid`` the
    feature provider's: :class:`HashGridContext`); ``hidden`` (100); ``chunk``; ``escape_limit``.
    """

    kind = "hac"

    def __init__(self, attrs: Sequence[CodedAttribute], n_masks: int, *, grid: Optional[BinaryHashGrid] = None,
                 grid_options: Optional[dict] = None, hidden: int = 100, context: str = "own",
                 **options):
        super().__init__(attrs, n_masks, **options)
        self._init_grid(grid, grid_options, context)
        self.hidden = int(hidden)
        self.n_out = sum(2 * a.dims for a in self.attrs) + len(self.attrs)
        self.mlp = nn.Sequential(nn.Linear(self.ctx_grid.output_dim, self.hidden), nn.ReLU(),
                                 nn.Linear(self.hidden, self.n_out))

    def config(self) -> dict:
        cfg = super().config()
        cfg.update(hidden=self.hidden, **self.grid_config())
        return cfg

    def _split(self, out, exact: bool) -> Params:
        P, off = {}, 0
        n_attrs = len(self.attrs)
        adj_off = self.n_out - n_attrs
        for i, a in enumerate(self.attrs):
            mean = out[:, off:off + a.dims]
            scale = out[:, off + a.dims:off + 2 * a.dims]
            off += 2 * a.dims
            adj = out[:, adj_off + i:adj_off + i + 1]
            scale = torch.clamp(scale, min=SCALE_FLOOR)
            if exact:
                t = torch.from_numpy(det_tanh(adj.numpy()))
                q = torch.clamp(a.q0 * (1.0 + t), min=a.q0 * Q_FLOOR)
            else:
                q = adaptive_q(a.q0, adj)
            P[a.name] = (mean, scale, q)
        return P

    def _exact_context(self):
        return ExactMLP(self.mlp, in_bits=FEATURE_BITS, in_frac=FEATURE_BITS)

    def params(self, xyz: torch.Tensor, exact: bool = False, _ctx=None) -> Params:
        if exact:
            with torch.no_grad():
                ex = _ctx if _ctx is not None else self._exact_context()
                return self._split(ex(self.ctx_grid.features_fixed(xyz)), exact=True)
        return self._split(self.mlp(self._features(xyz)), exact=False)

    def train_params(self, xyz: torch.Tensor, rows: torch.Tensor):
        """As :meth:`params`, but the mean/scale outputs (172 of HAC's 175 output columns) only
        for ``rows``: every visible anchor needs its adaptive step, only the ~5% rate sample
        needs a likelihood. Same function as the full head; the dropped columns were never
        used (about 2.5x fewer multiply-adds in the context MLP per training step)."""
        h = self.mlp[1](self.mlp[0](self._features(xyz)))  # [N, hidden]
        last = self.mlp[2]
        n_attrs = len(self.attrs)
        adj_off = self.n_out - n_attrs
        adj = F.linear(h, last.weight[adj_off:], last.bias[adj_off:])  # [N, n_attrs]
        q_all = {a.name: adaptive_q(a.q0, adj[:, i:i + 1]) for i, a in enumerate(self.attrs)}
        P_rows = self._split(last(h[rows]), exact=False)
        P_rows = {a.name: (P_rows[a.name][0], P_rows[a.name][1], q_all[a.name][rows])
                  for a in self.attrs}
        return q_all, P_rows

    def serialize(self, precision: str = "float32", used_xyz=None) -> Dict[str, bytes]:
        """Sections ``grid`` (Bernoulli-coded binary tables; with ``used_xyz`` only the entries
        those positions read; none when the grid is the provider's) and ``mlp`` (weights + grid
        bounds).

        Rounds the context MLP in place to ``precision`` first, so the encoder's probabilities
        are the decoder's.
        """
        round_module_(self.mlp, precision)
        sd = self._grid_state()
        sd.update({f"mlp.{k}": v for k, v in self.mlp.state_dict().items()})
        return {**self._grid_sections(used_xyz),
                "mlp": pack_state_dict(sd, precision, keep=("xyz_min", "xyz_max"))}

    def load_serialized(self, blobs: Dict[str, bytes], used_xyz=None) -> None:
        if "mlp" not in blobs:
            raise BitstreamError("entropy model: missing section 'mlp'")
        sd = unpack_state_dict(blobs["mlp"], what="entropy model weights")
        self._load_grid(blobs, sd, used_xyz)
        try:
            self.mlp.load_state_dict({k[4:]: v for k, v in sd.items() if k.startswith("mlp.")})
        except (KeyError, RuntimeError, ValueError) as e:
            raise BitstreamError(f"entropy model weights do not fit the model: {e}") from None


class FactorizedEntropyModel(EntropyModel):
    """Context-free model: one learned Gaussian per channel, fixed step Q = q0.

    Parameters ``mean_<name>`` [d] (init 0) and ``log_scale_<name>`` [d] (init log(10 q0)).
    :meth:`fit_` sets them from data statistics (a quick "trained" state).
    """

    kind = "factorized"
    SECTION_LABELS = {"factorized": ""}     # its one section: "factorized" in pgs info

    def __init__(self, attrs: Sequence[CodedAttribute], n_masks: int, **options):
        super().__init__(attrs, n_masks, **options)
        self.means = nn.ParameterDict()
        self.log_scales = nn.ParameterDict()
        for a in self.attrs:
            self.means[a.name] = nn.Parameter(torch.zeros(a.dims))
            self.log_scales[a.name] = nn.Parameter(torch.full((a.dims,), math.log(10 * a.q0)))

    @torch.no_grad()
    def fit_(self, values: Dict[str, torch.Tensor], gauss_mask=None) -> None:
        for a in self.attrs:
            x = values[a.name].detach().float()
            m = self.value_mask(a, gauss_mask, x.shape[0], device=x.device)
            w = m.float() if m is not None else torch.ones_like(x)
            cnt = w.sum(0).clamp(min=1)
            mu = (x * w).sum(0) / cnt
            var = (((x - mu) ** 2) * w).sum(0) / cnt
            self.means[a.name].copy_(mu)
            self.log_scales[a.name].copy_(torch.log(var.sqrt().clamp(min=a.q0 * 0.1)))

    def params(self, xyz: torch.Tensor, exact: bool = False, _ctx=None) -> Params:
        n = xyz.shape[0]
        P = {}
        for a in self.attrs:
            if exact:
                mean = self.means[a.name].detach().cpu().double()
                scale = torch.from_numpy(det_exp(self.log_scales[a.name].detach().cpu().double().numpy()))
                scale = torch.clamp(scale, min=SCALE_FLOOR)
                q = torch.full((n, 1), a.q0, dtype=torch.float64)
            else:
                mean = self.means[a.name]
                scale = torch.clamp(torch.exp(self.log_scales[a.name]), min=SCALE_FLOOR)
                q = torch.full((n, 1), a.q0, dtype=mean.dtype, device=xyz.device)
                mean = mean.to(xyz.device)
                scale = scale.to(xyz.device)
            P[a.name] = (mean.expand(n, -1), scale.expand(n, -1), q)
        return P

    def serialize(self, precision: str = "float32", used_xyz=None) -> Dict[str, bytes]:
        round_module_(self, precision)
        return {"factorized": pack_state_dict(self.state_dict(), precision)}

    def load_serialized(self, blobs: Dict[str, bytes], used_xyz=None) -> None:
        if "factorized" not in blobs:
            raise BitstreamError("entropy model: missing section 'factorized'")
        sd = unpack_state_dict(blobs["factorized"], what="entropy model weights")
        try:
            self.load_state_dict(sd)
        except RuntimeError as e:
            raise BitstreamError(f"entropy model weights do not fit the model: {e}") from None


def build_entropy_model(config: dict, **overrides) -> EntropyModel:
    """Rebuild an entropy model from :meth:`EntropyModel.config` (e.g. a bitstream header); its
    class is the one registered under the config's ``kind``."""
    cfg = dict(config)
    kind = cfg.pop("kind")
    attrs = [CodedAttribute(str(n), int(d), float(q), bool(m)) for n, d, q, m in cfg.pop("attrs")]
    n_masks = int(cfg.pop("n_masks"))
    cls = registry.component_class("entropy_model", kind)
    if "grid" in cfg:
        cfg["grid_options"] = cfg.pop("grid")
    cfg.update(overrides)
    return cls(attrs, n_masks, **cfg)
