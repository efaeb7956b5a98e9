"""The CPU grid kernels' float path as a point-by-point loop: the oracle that
:mod:`baseline.hac._grid_kernels` (level by level, straight-line corners) must match bit for
bit. Point i, then level l, then corner c; the scratch arrays hold the corners of one
point-level. Signatures as the product kernels but with ``hashed`` [L] uint8 in place of the
level kinds."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

_PRIMES = (np.int64(1), np.int64(2654435761), np.int64(805459861))
_MASK32 = np.int64(0xFFFFFFFF)


@njit(cache=False, inline="always")
def _axis(uv, r):
    """Lower / upper corner coordinates and weights along one axis (weight 0 = excluded)."""
    pos = uv * np.float32(r - 2) + np.float32(0.5)
    g = np.int64(np.floor(pos))
    f = pos - np.float32(g)
    g1 = min(g + 1, r - 1)
    w0 = np.float32(1.0) - f
    w1 = f
    if g <= 0 or g >= r - 1:
        w0 = np.float32(0.0)
    if g1 <= 0 or g1 >= r - 1:
        w1 = np.float32(0.0)
    return g, g1, w0, w1


@njit(cache=False, inline="always")
def _inside(u, i, dim):
    for d in range(dim):
        v = u[i, d]
        if not (v >= 0.0 and v <= 1.0):  # NaN fails both
            return False
    return True


@njit(cache=False, inline="always")
def _corners(u, i, l, dim, res, rows, hashed, strides, offsets, rix, wts, ti, tw):
    """Fill rix[:2^dim] / wts[:2^dim] with the corner rows and weights of point i at level l.

    Per-axis index terms and weights are computed once (``ti``/``tw`` [6] scratch), then the
    corners combine them: ``^`` of the masked ``coord * prime`` terms for hashed levels, ``+`` of
    ``coord * stride`` for dense ones. Corner c takes the upper neighbour on axis d when bit d of
    c is set, and its weight is ``w2 * (w1 * w0)`` (the PyTorch path's product order).
    Returns the weight sum.
    """
    r = res[l]
    hl = hashed[l]
    for d in range(dim):
        g, g1, w0, w1 = _axis(u[i, d], r)
        if hl:
            ti[2 * d] = (g * _PRIMES[d]) & _MASK32
            ti[2 * d + 1] = (g1 * _PRIMES[d]) & _MASK32
        else:
            ti[2 * d] = g * strides[l, d]
            ti[2 * d + 1] = g1 * strides[l, d]
        tw[2 * d] = w0
        tw[2 * d + 1] = w1
    nr = rows[l]
    pow2 = (nr & (nr - 1)) == 0
    off = offsets[l]
    wn = np.float32(0.0)
    if dim == 3:
        for c in range(8):
            b0 = c & 1
            b1 = 2 + ((c >> 1) & 1)
            b2 = 4 + (c >> 2)
            w = tw[b2] * (tw[b1] * tw[b0])
            if hl:
                h = ti[b0] ^ ti[b1] ^ ti[b2]
                h = (h & (nr - 1)) if pow2 else (h % nr)
            else:
                h = ti[b0] + ti[b1] + ti[b2]
            rix[c] = off + h
            wts[c] = w
            wn += w
    else:
        for c in range(4):
            b0 = c & 1
            b1 = 2 + (c >> 1)
            w = tw[b1] * tw[b0]
            if hl:
                h = ti[b0] ^ ti[b1]
                h = (h & (nr - 1)) if pow2 else (h % nr)
            else:
                h = ti[b0] + ti[b1]
            rix[c] = off + h
            wts[c] = w
            wn += w
    return wn


_CHUNK = 256  # points per parallel task (scratch arrays are allocated once per task)


@njit(cache=False, parallel=True, error_model="numpy")
def grid_fwd(u, table, res, rows, offsets, hashed, strides, out):
    n, dim = u.shape
    L = res.shape[0]
    F = table.shape[1]
    nc = 8 if dim == 3 else 4
    for ch in prange((n + _CHUNK - 1) // _CHUNK):
        rix = np.empty(8, np.int64)
        wts = np.empty(8, np.float32)
        ti = np.empty(6, np.int64)
        tw = np.empty(6, np.float32)
        acc = np.empty(F, np.float32)
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            if not _inside(u, i, dim):
                for k in range(L * F):
                    out[i, k] = 0.0
                continue
            for l in range(L):
                wn = _corners(u, i, l, dim, res, rows, hashed, strides, offsets, rix, wts, ti, tw)
                for k in range(F):
                    acc[k] = 0.0
                for c in range(nc):
                    w = wts[c]
                    if w != 0.0:
                        rr = rix[c]
                        for k in range(F):
                            acc[k] += w * table[rr, k]
                if wn == 0.0:
                    wn = np.float32(1e-9)
                inv = np.float32(1.0) / wn
                for k in range(F):
                    out[i, l * F + k] = acc[k] * inv


@njit(cache=False, error_model="numpy")
def _bwd_range(u, gout, res, rows, offsets, hashed, strides, gtable, start, stop):
    n, dim = u.shape
    L = res.shape[0]
    F = gtable.shape[1]
    nc = 8 if dim == 3 else 4
    rix = np.empty(8, np.int64)
    wts = np.empty(8, np.float32)
    ti = np.empty(6, np.int64)
    tw = np.empty(6, np.float32)
    for i in range(start, stop):
        if not _inside(u, i, dim):
            continue
        for l in range(L):
            wn = _corners(u, i, l, dim, res, rows, hashed, strides, offsets, rix, wts, ti, tw)
            if wn == 0.0:
                continue
            inv = np.float32(1.0) / wn
            for c in range(nc):
                w = wts[c]
                if w != 0.0:
                    s = w * inv
                    rr = rix[c]
                    for k in range(F):
                        gtable[rr, k] += s * gout[i, l * F + k]


@njit(cache=False, parallel=True, error_model="numpy")
def grid_bwd(u, gout, res, rows, offsets, hashed, strides, gtable, nparts):
    """Accumulate into ``gtable`` [rows, F] (zeroed by the caller).

    The points are split into ``nparts`` contiguous ranges, each accumulated into its own
    buffer (no write conflicts), then the buffers are summed in part order: deterministic for a
    given ``nparts``.
    """
    n = u.shape[0]
    if nparts <= 1:
        _bwd_range(u, gout, res, rows, offsets, hashed, strides, gtable, 0, n)
        return
    R, F = gtable.shape
    step = (n + nparts - 1) // nparts
    buf = np.zeros((nparts, R, F), np.float32)
    for p in prange(nparts):
        _bwd_range(u, gout, res, rows, offsets, hashed, strides, buf[p], p * step, min(n, (p + 1) * step))
    for r in prange(R):
        for p in range(nparts):
            for k in range(F):
                gtable[r, k] += buf[p, r, k]


