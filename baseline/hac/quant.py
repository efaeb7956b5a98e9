"""HAC's quantization of the coded attributes (docs/method.md section 3).

* base steps come from :class:`baseline.contracts.CodedAttribute` ``q0`` (feat 1, scaling 0.001,
  offsets 0.2);
* adaptive step, one per anchor per attribute: ``Q = q0 * (1 + tanh(adj))``. ``1 + tanh``
  reaches 0 in floating point for very negative ``adj``; Q is floored at ``q0 * Q_FLOOR`` so it
  never divides by zero (HAC would produce NaN there);
* training: additive uniform noise ``x + U(-0.5, 0.5) * Q``;
* evaluation / coding: values clamped to ``mean(x) +- 15000 Q`` then ``round(x / Q) * Q`` with a
  straight-through gradient (identity, also through the clamp, as HAC). Where the base step
  ``q0`` is given the clamp is ``mean(x) +- 15000 max(Q, q0)``: identical while ``Q >= q0``, but
  when nothing holds the steps up (lambda = 0: the rate never pushes back) HAC's clamp shrinks
  with them and cuts off the values themselves (measured on the synthetic scene at lambda 0:
  16.5% of the scalings clipped, 38.0 dB raw -> 27.7 dB decoded). The codec escapes the large
  symbols this allows (int64), so no bound on the step is needed for coding;
* training with ``entropy.decoder_quant = "ste"`` (not HAC's default): the decoder sees the
  rounded values of evaluation (:func:`ste_round_q`), the rate is still estimated on the noisy
  ones. See :func:`ste_round_q` for why.
"""
from __future__ import annotations

from typing import Optional

import torch

Q_FLOOR = 2.0 ** -20
CLAMP_STEPS = 15000


def adaptive_q(q0: float, adj: torch.Tensor) -> torch.Tensor:
    """``q0 * (1 + tanh(adj))``, floored at ``q0 * Q_FLOOR``."""
    return torch.clamp(q0 * (1 + torch.tanh(adj)), min=q0 * Q_FLOOR)


def noise_quantize(x: torch.Tensor, q) -> torch.Tensor:
    """Training proxy of quantization: ``x + U(-0.5, 0.5) * q`` (``q`` broadcasts)."""
    return x + (torch.rand_like(x) - 0.5) * q


def clamp_halfwidth(q, q0: Optional[float] = None):
    """Half-width of the clamp around the mean: ``15000 Q`` (HAC), ``15000 max(Q, q0)`` with q0."""
    if q0 is None:
        return CLAMP_STEPS * q
    return CLAMP_STEPS * torch.clamp(torch.as_tensor(q), min=float(q0))


class _STERound(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, q, x_mean, half):
        x = torch.maximum(torch.minimum(x, x_mean + half), x_mean - half)
        return torch.round(x / q) * q

    @staticmethod
    def backward(ctx, grad):
        return grad, None, None, None


def _prepare(x, q, x_mean, q0):
    q = torch.as_tensor(q, dtype=x.dtype, device=x.device)
    if x_mean is None:
        x_mean = x.detach().mean() if x.numel() else torch.zeros((), dtype=x.dtype, device=x.device)
    x_mean = torch.as_tensor(x_mean, dtype=x.dtype, device=x.device).detach()
    return q, x_mean, clamp_halfwidth(q.detach(), q0)


def ste_round(x: torch.Tensor, q, x_mean: Optional[torch.Tensor] = None,
              q0: Optional[float] = None) -> torch.Tensor:
    """``round(clamp(x, mean +- 15000 q) / q) * q`` with a straight-through gradient
    (``15000 max(q, q0)`` when the base step ``q0`` is given; see the module docstring).

    ``x_mean`` defaults to the mean of ``x`` (HAC: the mean over all values of the attribute).
    """
    q, x_mean, half = _prepare(x, q, x_mean, q0)
    return _STERound.apply(x, q, x_mean, half)


class _STERoundQ(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, q, x_mean, half):
        xq = torch.round(torch.maximum(torch.minimum(x, x_mean + half), x_mean - half) / q) * q
        ctx.save_for_backward(x, q, xq)
        return xq

    @staticmethod
    def backward(ctx, grad):
        x, q, xq = ctx.saved_tensors
        gq = None
        if ctx.needs_input_grad[1]:
            # d/dq of x + q * e with e = (xq - x) / q held constant: the rounding error in steps
            gq = grad * (xq - x) / q
            while gq.dim() > q.dim():
                gq = gq.sum(0)
            for d, n in enumerate(q.shape):
                if n == 1 and gq.shape[d] != 1:
                    gq = gq.sum(d, keepdim=True)
        return grad, gq, None, None


def ste_round_q(x: torch.Tensor, q: torch.Tensor, x_mean: Optional[torch.Tensor] = None,
                q0: Optional[float] = None) -> torch.Tensor:
    """The values :func:`ste_round` gives (what evaluation and the decoder see), for training.

    Gradients: identity to ``x`` (straight through) and, to the step ``q``, the rounding error in
    steps ``(round(x/q) q - x) / q``: the value is written ``x + q e`` with ``e`` held constant, as
    the noise proxy ``x + q u`` gives ``u`` (without it, nothing but the rate would move an
    adaptive step, and every step would grow to its maximum).

    Why (``entropy.decoder_quant = "ste"``): with HAC's proxy the decoder MLPs are trained on
    ``x + U(-0.5, 0.5) q``. Each render draws new noise, and a pixel averages many Gaussians, so
    the noise dithers: a feature at ``0.3 q`` still shifts the decoded Gaussians on average, and
    training learns to carry information below the quantization step, which rounding then
    deletes. Measured on the synthetic scene at 6k iterations, lambda 0.004 (HAC, mask loss
    off): raw features 37.81 dB, features with fresh noise 37.45-37.51 dB, rounded features
    34.12 dB (74% of the features lie within half a step of zero). Training the decoder on the
    rounded values while the likelihood keeps the noise is the usual remedy in learned
    compression ("mixed" quantization, Minnen & Singh 2020).
    """
    q, x_mean, half = _prepare(x, q, x_mean, q0)
    return _STERoundQ.apply(x, q, x_mean, half)
