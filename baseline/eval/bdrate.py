"""Bjontegaard delta rate (BD-rate) and delta PSNR (BD-PSNR), piecewise cubic (PCHIP) mode.

The classic Bjontegaard metric (VCEG-M33) fits a cubic polynomial through the R-D points; the
piecewise cubic variant (VCEG-AL22 / the JCT-VC spreadsheet, the ``pchip`` mode of the common
``bjontegaard`` Python packages) interpolates them with a monotone piecewise cubic Hermite
interpolant (PCHIP, Fritsch-Carlson) instead, which never overshoots between points.

For curves ``A`` (anchor / baseline) and ``B`` (test / contender), each given as rates ``R``
(any unit, the same for both) and PSNRs ``D``:

* BD-rate: interpolate ``log10 R`` as a function of ``D`` for each curve, integrate both over the
  overlapping PSNR interval ``[max(min D_A, min D_B), min(max D_A, max D_B)]``, take the mean
  difference ``d = (int_B - int_A) / (hi - lo)``; BD-rate = ``(10^d - 1) * 100`` percent
  (negative = B needs fewer bits for the same quality).
* BD-PSNR: interpolate ``D`` as a function of ``log10 R`` and integrate over the overlapping
  log-rate interval; BD-PSNR = ``(int_B - int_A) / (hi - lo)`` dB (positive = B is better).

The interpolants are integrated exactly (``PchipInterpolator.integrate`` integrates the
piecewise cubic polynomial), not by sampling.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator


class BDError(ValueError):
    """The curves do not allow a Bjontegaard measurement (too few points, no overlap, ...)."""


def _curve(x, y, what: str) -> PchipInterpolator:
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise BDError(f"{what}: rates and PSNRs must be 1-D arrays of the same length")
    if len(x) < 2:
        raise BDError(f"{what}: needs at least 2 points, got {len(x)}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise BDError(f"{what}: non-finite value in {x.tolist()} / {y.tolist()}")
    order = np.argsort(x, kind="stable")
    x, y = x[order], y[order]
    if np.any(np.diff(x) <= 0):
        raise BDError(f"{what}: two points at the same abscissa {x.tolist()}")
    return PchipInterpolator(x, y, extrapolate=False)


def _mean_difference(xa, ya, xb, yb, what: str, axis: str, show=lambda v: v) -> float:
    """Mean of (B - A) over the overlap of the abscissa ranges; ``show`` maps x for messages."""
    fa = _curve(xa, ya, f"{what} (baseline)")
    fb = _curve(xb, yb, f"{what} (contender)")
    lo = max(fa.x[0], fb.x[0])
    hi = min(fa.x[-1], fb.x[-1])
    if not hi > lo:
        raise BDError(f"{what}: no {axis} overlap (baseline {show(fa.x[0]):.4g}-{show(fa.x[-1]):.4g}, "
                      f"contender {show(fb.x[0]):.4g}-{show(fb.x[-1]):.4g})")
    return float((fb.integrate(lo, hi) - fa.integrate(lo, hi)) / (hi - lo))


def _log_rate(rate, what: str) -> np.ndarray:
    r = np.asarray(rate, dtype=np.float64)
    if np.any(~(r > 0)):
        raise BDError(f"{what}: rates must be positive, got {r.tolist()}")
    return np.log10(r)


def bd_rate(rate_a, psnr_a, rate_b, psnr_b) -> float:
    """BD-rate of B against A in percent (negative: B saves bits at equal PSNR)."""
    la, lb = _log_rate(rate_a, "BD-rate baseline"), _log_rate(rate_b, "BD-rate contender")
    d = _mean_difference(psnr_a, la, psnr_b, lb, "BD-rate", "PSNR")
    return float((10.0 ** d - 1.0) * 100.0)


def bd_psnr(rate_a, psnr_a, rate_b, psnr_b) -> float:
    """BD-PSNR of B against A in dB (positive: B has higher PSNR at equal rate)."""
    la, lb = _log_rate(rate_a, "BD-PSNR baseline"), _log_rate(rate_b, "BD-PSNR contender")
    return _mean_difference(la, psnr_a, lb, psnr_b, "BD-PSNR", "rate",
                            show=lambda v: 10.0 ** v)


def overlap(a, b) -> tuple[float, float, float]:
    """The interval both curves cover along one axis (PSNR for BD-rate, log10 rate for BD-PSNR)
    and the share of the wider curve's span it is: ``(lo, hi, share)``, share 0 when the
    curves do not overlap. A Bjontegaard delta integrates over this interval only, so a small
    share means the delta describes a sliver of the comparison (a flat curve's narrow span
    inside a steep one's is such a sliver too)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    lo, hi = max(a.min(), b.min()), min(a.max(), b.max())
    span = max(a.max() - a.min(), b.max() - b.min())
    share = 0.0 if not hi > lo else (1.0 if not span > 0 else float((hi - lo) / span))
    return float(lo), float(hi), share


def non_monotone(rate, psnr) -> list[int]:
    """Indices (into the given order) of the points that have more rate but no more PSNR than a
    point of lower rate on the same curve. A rate-distortion curve rises with rate; where it
    does not, the points differ by less than their noise (seeds, a saturated schedule), and a
    delta that interpolates through them measures that noise."""
    r = np.asarray(rate, dtype=np.float64)
    d = np.asarray(psnr, dtype=np.float64)
    order = np.argsort(r, kind="stable")
    best, out = -np.inf, []
    for i in order:
        if d[i] <= best:
            out.append(int(i))
        best = max(best, d[i])
    return sorted(out)


def rising_envelope(rate, psnr) -> list[int]:
    """Indices of the points that make a curve rise, in order of rate: every point except those
    :func:`non_monotone` names (more rate, no more PSNR than a smaller point). On it, PSNR grows
    strictly with rate, so each axis is a function of the other."""
    r = np.asarray(rate, dtype=np.float64)
    bad = set(non_monotone(rate, psnr))
    return [int(i) for i in np.argsort(r, kind="stable") if int(i) not in bad]


def _reading(xs, ys, x) -> float | None:
    """Linear interpolation of ``ys`` at ``x`` between the two neighbouring ``xs`` (increasing);
    None outside ``[xs[0], xs[-1]]``: a reading never extrapolates."""
    for x0, x1, y0, y1 in zip(xs, xs[1:], ys, ys[1:]):
        if x0 <= x <= x1:
            return float(y0 + (x - x0) / (x1 - x0) * (y1 - y0))
    return None


def rate_at_psnr(rate, psnr, at: float) -> float | None:
    """The rate a curve needs for PSNR ``at``: its log-rate interpolated linearly between the two
    points of its rising envelope around ``at``; None outside the envelope's PSNR range or with
    fewer than two envelope points.

    A point against another method's curve (``rate / rate_at_psnr(...) - 1``) is a reading at
    one PSNR, not a Bjontegaard delta: it serves where a curve has too few points for one, and
    it moves with the point's own seed noise."""
    env = rising_envelope(rate, psnr)
    if len(env) < 2:
        return None
    lr = _log_rate([rate[i] for i in env], "rate_at_psnr")
    v = _reading([float(psnr[i]) for i in env], lr.tolist(), float(at))
    return None if v is None else float(10.0 ** v)


def psnr_at_rate(rate, psnr, at: float) -> float | None:
    """The PSNR a curve reaches at rate ``at``: interpolated linearly in log-rate between the two
    points of its rising envelope around ``at``; None outside its rate range or with fewer than
    two envelope points."""
    env = rising_envelope(rate, psnr)
    if len(env) < 2 or not at > 0:
        return None
    lr = _log_rate([rate[i] for i in env], "psnr_at_rate")
    return _reading(lr.tolist(), [float(psnr[i]) for i in env], float(np.log10(at)))
