"""Bit-reproducible arithmetic for the entropy coder's probability model.

Encoder and decoder must compute *bit-identical* distribution parameters, also when they run
with different thread counts, SIMD paths or BLAS libraries (docs/method.md section 5). Rounding float results
to a coarse grid only makes a mismatch unlikely; here every step is exact or a single correctly
rounded IEEE operation, so a mismatch is impossible by construction:

* Linear layers run in *fixed point held in float64*: inputs are integers (|a| <= 2^in_bits),
  weights are rounded to integers ``round(W * 2^s)`` with ``s`` chosen per layer from a static
  bound, biases to the product scale. Every product and every partial sum of the matmul is then
  an integer below 2^53, so float64 matmul returns the exact result whatever the summation
  order, blocking, FMA use or thread count. Between layers, ReLU is exact and the hidden values
  are rescaled by a power of two and rounded half-to-even (deterministic).
* Nonlinearities use only +, -, *, / and ``ldexp`` (correctly rounded in IEEE 754), in a fixed
  order on numpy float64 arrays: :func:`det_exp` (Cody-Waite range reduction + degree-13 Taylor
  polynomial) and :func:`det_tanh`. Library ``exp``/``tanh`` are avoided because vectorised and
  scalar implementations differ in the last bit.

The cost of exactness is a relative perturbation of about 2^-20 of the coder's parameters with
respect to the float32 training path, which changes the rate by far less than 0.1%.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np
import torch
import torch.nn as nn
from math import ldexp

_LN2_HI = 6.93147180369123816490e-01  # high part of ln 2: trailing zero bits, k * _LN2_HI exact
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e+00


def _factorials(n: int) -> List[float]:
    out, f = [], 1
    for i in range(n):
        if i:
            f *= i
        out.append(1.0 / float(f))
    return out


_EXP_TAYLOR = _factorials(14)  # 1/0! .. 1/13!


def det_exp(x) -> np.ndarray:
    """exp(x) for float64 arrays using only correctly rounded operations (reproducible).

    Relative error below ~2e-16 on [-700, 700]; inputs are clipped to that range.
    """
    x = np.clip(np.asarray(x, dtype=np.float64), -700.0, 700.0)
    k = np.rint(x * _INV_LN2)
    r = (x - k * _LN2_HI) - k * _LN2_LO  # |r| <= ~0.347
    p = np.full_like(r, _EXP_TAYLOR[13])
    for c in reversed(_EXP_TAYLOR[:13]):
        p = p * r
        p = p + c
    return np.ldexp(p, k.astype(np.int64))


def det_tanh(x) -> np.ndarray:
    """tanh(x) for float64 arrays using only correctly rounded operations (reproducible)."""
    x = np.asarray(x, dtype=np.float64)
    e = det_exp(-2.0 * np.abs(x))
    t = (1.0 - e) / (1.0 + e)
    return np.where(x < 0, -t, t)


def _exponent(v: float) -> int:
    """Smallest e with |v| < 2^e (v > 0)."""
    return int(np.frexp(v)[1])


@dataclass
class _FixedLayer:
    w: torch.Tensor      # [out, in] float64 integers
    b: torch.Tensor      # [out] float64 integers, at scale 2^(in_frac + w_frac)
    w_frac: int          # weights are W * 2^w_frac
    in_frac: int         # inputs are a * 2^in_frac
    relu: bool
    slope: float         # 0 for ReLU; LeakyReLU's negative slope otherwise
    out_frac_next: int   # fractional bits of the requantised output (hidden layers)
    bound: int           # static bound of |output| in integer units (before requantisation)


class ExactMLP:
    """Exact fixed-point evaluation of an ``nn.Sequential`` of ``Linear`` and ``ReLU`` (or
    ``LeakyReLU``) layers. A LeakyReLU multiplies the exact negative integer sums by its slope
    (one correctly rounded multiplication) before the requantisation's rounding: deterministic,
    and bounded by the ReLU-free bound.

    Build once from the (stored-precision) module, then call on integer inputs:

        ex = ExactMLP(mlp, in_bits=20, in_frac=20)  # inputs |a| <= 2^20, value = a * 2^-20
        y = ex(a_int)                                # float64 real outputs [N, out]

    ``in_bits`` bounds the integer inputs (|a| <= 2^in_bits; the caller clamps). ``hidden_bits``
    bounds the requantised hidden activations. Weights are rounded to at most ``weight_bits``
    significant bits per layer (fewer if a layer's static bound would exceed 2^52).
    """

    MAX_SUM = 2 ** 52

    def __init__(self, mlp: nn.Module, in_bits: int = 20, in_frac: int = 20,
                 hidden_bits: int = 22, weight_bits: int = 23):
        mods = list(mlp) if isinstance(mlp, nn.Sequential) else [mlp]
        self.layers: List[_FixedLayer] = []
        a_bits, a_frac = int(in_bits), int(in_frac)
        i = 0
        while i < len(mods):
            lin = mods[i]
            if not isinstance(lin, nn.Linear):
                raise TypeError(f"ExactMLP supports Linear/(Leaky)ReLU stacks, got "
                                f"{type(lin).__name__}")
            act = mods[i + 1] if i + 1 < len(mods) else None
            relu = isinstance(act, (nn.ReLU, nn.LeakyReLU))
            slope = float(act.negative_slope) if isinstance(act, nn.LeakyReLU) else 0.0
            i += 2 if relu else 1
            W = lin.weight.detach().to("cpu", torch.float64)
            b = (lin.bias.detach().to("cpu", torch.float64) if lin.bias is not None
                 else torch.zeros(W.shape[0], dtype=torch.float64))
            if not (torch.isfinite(W).all() and torch.isfinite(b).all()):
                raise ValueError("ExactMLP: non-finite weights")
            wmax = float(W.abs().max()) if W.numel() else 0.0
            w_frac = (weight_bits - _exponent(wmax)) if wmax > 0 else 0
            while True:
                Wi = torch.round(W * ldexp(1.0, w_frac))  # power-of-two scaling: exact
                bi = torch.round(b * ldexp(1.0, w_frac + a_frac))
                # static bound in exact integer arithmetic
                row = Wi.abs().sum(dim=1).to(torch.int64)  # each |Wi| < 2^24: exact
                bound_rows = row * (1 << a_bits) + bi.abs().to(torch.int64) if bi.abs().max() < 2 ** 62 \
                    else None
                if bound_rows is not None and int(bound_rows.max()) < self.MAX_SUM:
                    break
                w_frac -= 1
                if w_frac < -1100:
                    raise ValueError("ExactMLP: weights/bias too large for exact evaluation")
            bound = int(bound_rows.max()) if bound_rows.numel() else 0
            is_last = i >= len(mods)
            if not is_last:
                # requantise hidden outputs to |h| <= 2^hidden_bits
                real_bound = bound * 2.0 ** -(w_frac + a_frac)
                out_frac = hidden_bits - (_exponent(real_bound) if real_bound > 0 else 0)
            else:
                out_frac = 0
            self.layers.append(_FixedLayer(Wi, bi, w_frac, a_frac, relu, slope, out_frac, bound))
            if not is_last:
                a_bits, a_frac = hidden_bits, out_frac
        self.in_bits = int(in_bits)

    def __call__(self, a: torch.Tensor) -> torch.Tensor:
        """``a`` [N, in] float64 integers (|a| <= 2^in_bits) -> real outputs [N, out] float64."""
        lim = float(2 ** self.in_bits)
        h = a.to(torch.float64).clamp(-lim, lim)
        n = len(self.layers)
        for j, L in enumerate(self.layers):
            y = torch.addmm(L.b, h, L.w.T)  # exact: every partial sum is an integer < 2^53
            if L.relu and L.slope == 0.0:
                y.clamp_(min=0.0)
            elif L.relu:
                y = torch.where(y < 0, y * L.slope, y)
            scale = L.w_frac + L.in_frac
            if j + 1 < n:
                h = y.mul_(ldexp(1.0, L.out_frac_next - scale)).round_()  # power of 2: exact
            else:
                h = y.mul_(ldexp(1.0, -scale))
        return h
