"""HAC's quantization of the coded attributes (SPEC.md 3).

* base steps come from :class:`baseline.contracts.CodedAttribute` ``q0`` (feat 1, scaling 0.001,
  offsets 0.2);
* adaptive step, one per anchor per attribute: ``Q = q0 * (1 + tanh(adj))``. ``1 + tanh``
  reaches 0 in floating point for very negative ``adj``; Q is floored at ``q0 * Q_FLOOR`` so it
  never divides by zero (HAC would produce NaN there);
* training: additive uniform noise ``x + U(-0.5, 0.5) * Q``;
* evaluation / coding: values clamped to ``mean(x) +- 15000 Q`` then ``round(x / Q) * Q`` with a
  straight-through gradient (identity, also through the clamp, as HAC).
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


class _STERound(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, q, x_mean):
        lo = x_mean - CLAMP_STEPS * q
        hi = x_mean + CLAMP_STEPS * q
        x = torch.maximum(torch.minimum(x, hi), lo)
        return torch.round(x / q) * q

    @staticmethod
    def backward(ctx, grad):
        return grad, None, None


def ste_round(x: torch.Tensor, q, x_mean: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``round(clamp(x, mean +- 15000 q) / q) * q`` with a straight-through gradient.

    ``x_mean`` defaults to the mean of ``x`` (HAC: the mean over all values of the attribute).
    """
    q = torch.as_tensor(q, dtype=x.dtype, device=x.device)
    if x_mean is None:
        x_mean = x.detach().mean() if x.numel() else torch.zeros((), dtype=x.dtype, device=x.device)
    x_mean = torch.as_tensor(x_mean, dtype=x.dtype, device=x.device).detach()
    return _STERound.apply(x, q, x_mean)
