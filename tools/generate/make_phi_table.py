"""Write ``baseline/codec/phi_table.npy``: the standard normal CDF as integers, for the
mixture coder (``baseline/codec/mixture.py``).

``T[j] = round(Phi(j / 1024) * 2^30)`` for j = 0 .. 8192 (z in [0, 8]), plus ``T[8193] = 2^30``,
computed in 50-digit decimal arithmetic (the error function's power series), so the table is
the same on every machine; the coder reads it, it never computes a CDF in floating point.
Run: ``python tools/generate/make_phi_table.py`` (about 2 s).
"""
import decimal
from decimal import Decimal as D
from pathlib import Path

import numpy as np

STEPS = 1024          # table entries per unit of z
ZMAX = 8
ONE = 1 << 30

_PI = D("3.14159265358979323846264338327950288419716939937510582097494459")


def phi(j: int) -> D:
    """Phi(j / STEPS) to ~45 digits (j >= 0)."""
    with decimal.localcontext() as ctx:
        ctx.prec = 60
        z = D(j) / D(STEPS)
        z2 = z * z
        term = z
        s = z
        n = 0
        while True:
            n += 1
            term = term * (-z2) / (2 * n)
            t = term / (2 * n + 1)
            s += t
            if abs(t) < D(10) ** -50:
                break
        return D("0.5") + s / (2 * _PI).sqrt()


def table() -> np.ndarray:
    vals = [int((phi(j) * ONE).to_integral_value(rounding=decimal.ROUND_HALF_EVEN))
            for j in range(ZMAX * STEPS + 1)]
    vals.append(ONE)
    t = np.asarray(vals, dtype=np.int64)
    return np.maximum.accumulate(t)          # non-decreasing by construction


if __name__ == "__main__":
    out = Path(__file__).resolve().parents[2] / "baseline" / "codec" / "phi_table.npy"
    np.save(out, table())
    print(f"wrote {out}")
