"""Numba kernels of the hash grid's float (training) path: fused interpolation and its backward.

The PyTorch path of :meth:`baseline.hac.hashgrid.GridLevels.encode` materializes per-corner
index and weight tensors ([n, L, 2^dim] each, several temporaries) and gathers through
``embedding_bag``; on 100k anchors x (12 3D + 12 plane levels) that measured 175 ms forward and
310 ms backward on 2 cores, the largest cost of a training step. These kernels
compute corners, weights and hashes in registers:

* :func:`grid_fwd`: ``out[i, l*F:(l+1)*F] = sum_c w_c table[idx_c] / sum_c w_c`` (HAC's
  boundary-corner exclusion and renormalization, exactly the PyTorch path's arithmetic in
  float32 except the order of the corner sum), parallel over chunks of points.
* :func:`grid_bwd`: ``dtable[idx_c] += w_c / wn * dout``, parallel over contiguous point ranges
  with one table-sized buffer each, summed in a fixed order (deterministic for a given number of
  ranges; the caller uses the thread count). Parallel over levels (disjoint row ranges, no
  buffers) was tried and measured 3.5x slower.

Inside a chunk both run level by level (the level's resolution, kind and offsets stay in
registers) over straight-line code for the 8 (3D) or 4 (plane) corners, and the backward
scatters 4-feature rows (HAC's layout) as four named accumulations: on 80k anchors of one
thread, forward 1.3x (3D grid) to 1.7x (planes) and backward 2x (3D) to 2.8x (planes) the
speed of a point-by-point loop over the levels with the corners in scratch arrays, with the
same bits
(every table row belongs to one level, so each entry still receives its terms in point order,
then corner order; ``tests/reference_grid_kernels.py`` keeps that loop as the tests' oracle).

Points whose coordinates leave [0, 1] (or are NaN) output zeros and receive no gradient.
No gradient is computed for the positions (anchor positions are not trained; the PyTorch path
is used when they require a gradient). :func:`grid_fwd_exact` is the exact (coding) path's
forward, bit-identical to the PyTorch float64 path (integer weights, exact sums).

Arrays: ``u`` [n, dim] float32, ``table`` [rows, F] float32, ``res`` [L] int64, ``rows`` [L]
int64 (rows of each level), ``offsets`` [L] int64, ``kinds`` [L] int64 (:func:`level_kinds`;
the exact path takes ``hashed`` [L] uint8), ``strides`` [L, dim] int64.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

_PRIMES = (np.int64(1), np.int64(2654435761), np.int64(805459861))
_MASK32 = np.int64(0xFFFFFFFF)


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _inside(u, i, dim):
    for d in range(dim):
        v = u[i, d]
        if not (v >= 0.0 and v <= 1.0):  # NaN fails both
            return False
    return True


_CHUNK = 256  # points per parallel task (scratch arrays are allocated once per task)

# Level kinds of the float path (see :func:`level_kinds`).
DENSE, HASH_POW2, HASH_MOD = 0, 1, 2


def level_kinds(rows, hashed) -> np.ndarray:
    """int64 [L]: DENSE, HASH_POW2 (hashed, power-of-two rows: ``& (rows - 1)``) or HASH_MOD."""
    rows = np.asarray(rows, dtype=np.int64)
    pow2 = (rows & (rows - 1)) == 0
    return np.where(np.asarray(hashed, dtype=bool), np.where(pow2, HASH_POW2, HASH_MOD),
                    DENSE).astype(np.int64)


@njit(cache=True, inline="always")
def _wrap(h, kind, nr):
    if kind == HASH_POW2:
        return h & (nr - 1)
    return h % nr


@njit(cache=True, inline="always")
def _level3(ux, uy, uz, r, kind, nr, sy, sz):
    """The 8 corner rows (within the level) and weights of one point at one 3D level, in the
    HAC's corner order (bit 0: x, bit 1: y, bit 2: z), and their sum: weight ``wz * (wy * wx)``,
    the weight sum in corner order, the XOR of the masked ``coord * prime`` terms (hashed) or the
    sum of ``coord * stride`` (dense)."""
    gx, gx1, wx0, wx1 = _axis(ux, r)
    gy, gy1, wy0, wy1 = _axis(uy, r)
    gz, gz1, wz0, wz1 = _axis(uz, r)
    if kind == DENSE:
        ty0 = gy * sy
        ty1 = gy1 * sy
        tz0 = gz * sz
        tz1 = gz1 * sz
        i0 = gx + ty0 + tz0
        i1 = gx1 + ty0 + tz0
        i2 = gx + ty1 + tz0
        i3 = gx1 + ty1 + tz0
        i4 = gx + ty0 + tz1
        i5 = gx1 + ty0 + tz1
        i6 = gx + ty1 + tz1
        i7 = gx1 + ty1 + tz1
    else:
        tx0 = gx & _MASK32
        tx1 = gx1 & _MASK32
        ty0 = (gy * _PRIMES[1]) & _MASK32
        ty1 = (gy1 * _PRIMES[1]) & _MASK32
        tz0 = (gz * _PRIMES[2]) & _MASK32
        tz1 = (gz1 * _PRIMES[2]) & _MASK32
        h00 = tx0 ^ ty0
        h10 = tx1 ^ ty0
        h01 = tx0 ^ ty1
        h11 = tx1 ^ ty1
        i0 = _wrap(h00 ^ tz0, kind, nr)
        i1 = _wrap(h10 ^ tz0, kind, nr)
        i2 = _wrap(h01 ^ tz0, kind, nr)
        i3 = _wrap(h11 ^ tz0, kind, nr)
        i4 = _wrap(h00 ^ tz1, kind, nr)
        i5 = _wrap(h10 ^ tz1, kind, nr)
        i6 = _wrap(h01 ^ tz1, kind, nr)
        i7 = _wrap(h11 ^ tz1, kind, nr)
    p00 = wy0 * wx0
    p10 = wy0 * wx1
    p01 = wy1 * wx0
    p11 = wy1 * wx1
    w0 = wz0 * p00
    w1 = wz0 * p10
    w2 = wz0 * p01
    w3 = wz0 * p11
    w4 = wz1 * p00
    w5 = wz1 * p10
    w6 = wz1 * p01
    w7 = wz1 * p11
    wn = np.float32(0.0) + w0
    wn = wn + w1
    wn = wn + w2
    wn = wn + w3
    wn = wn + w4
    wn = wn + w5
    wn = wn + w6
    wn = wn + w7
    return (i0, i1, i2, i3, i4, i5, i6, i7), (w0, w1, w2, w3, w4, w5, w6, w7), wn


@njit(cache=True, inline="always")
def _level2(ux, uy, r, kind, nr, sy):
    """As :func:`_level3` for a plane level: 4 corners (bit 0: first axis), weight ``wy * wx``."""
    gx, gx1, wx0, wx1 = _axis(ux, r)
    gy, gy1, wy0, wy1 = _axis(uy, r)
    if kind == DENSE:
        ty0 = gy * sy
        ty1 = gy1 * sy
        i0 = gx + ty0
        i1 = gx1 + ty0
        i2 = gx + ty1
        i3 = gx1 + ty1
    else:
        tx0 = gx & _MASK32
        tx1 = gx1 & _MASK32
        ty0 = (gy * _PRIMES[1]) & _MASK32
        ty1 = (gy1 * _PRIMES[1]) & _MASK32
        i0 = _wrap(tx0 ^ ty0, kind, nr)
        i1 = _wrap(tx1 ^ ty0, kind, nr)
        i2 = _wrap(tx0 ^ ty1, kind, nr)
        i3 = _wrap(tx1 ^ ty1, kind, nr)
    w0 = wy0 * wx0
    w1 = wy0 * wx1
    w2 = wy1 * wx0
    w3 = wy1 * wx1
    wn = np.float32(0.0) + w0
    wn = wn + w1
    wn = wn + w2
    wn = wn + w3
    return (i0, i1, i2, i3), (w0, w1, w2, w3), wn


@njit(cache=True, inline="always")
def _entry(v, signs):
    if signs:
        return np.float32(1.0) if v >= 0 else np.float32(-1.0)
    return v


@njit(cache=True, error_model="numpy")
def _fwd_block(u, table, res, rows, offsets, kinds, strides, out, lo, hi, inside, signs):
    """Forward of points [lo, hi): level by level (each level's constants stay in registers),
    points inside a level in order. ``inside`` [hi - lo] bool scratch; ``signs``: read each
    entry as +1 where it is >= 0, else -1 (NaN: -1), the binarization of the STE."""
    dim = u.shape[1]
    L = res.shape[0]
    F = table.shape[1]
    for i in range(lo, hi):
        ok = _inside(u, i, dim)
        inside[i - lo] = ok
        if not ok:
            for k in range(L * F):
                out[i, k] = 0.0
    for l in range(L):
        r = res[l]
        kind = kinds[l]
        nr = rows[l]
        off = offsets[l]
        sy = strides[l, 1]
        base = l * F
        if dim == 3:
            sz = strides[l, 2]
            for i in range(lo, hi):
                if not inside[i - lo]:
                    continue
                ix, w, wn = _level3(u[i, 0], u[i, 1], u[i, 2], r, kind, nr, sy, sz)
                if wn == 0.0:
                    wn = np.float32(1e-9)
                inv = np.float32(1.0) / wn
                for k in range(F):
                    # +-1 entries: a zero-weight corner adds +-0, which leaves a sum that
                    # started at +0 unchanged (the reference skips it: the same bits)
                    a = np.float32(0.0)
                    for c in range(8):
                        a += w[c] * _entry(table[off + ix[c], k], signs)
                    out[i, base + k] = a * inv
        else:
            for i in range(lo, hi):
                if not inside[i - lo]:
                    continue
                ix, w, wn = _level2(u[i, 0], u[i, 1], r, kind, nr, sy)
                if wn == 0.0:
                    wn = np.float32(1e-9)
                inv = np.float32(1.0) / wn
                for k in range(F):
                    a = np.float32(0.0)
                    for c in range(4):
                        a += w[c] * _entry(table[off + ix[c], k], signs)
                    out[i, base + k] = a * inv


@njit(cache=True, parallel=True, error_model="numpy")
def grid_fwd(u, table, res, rows, offsets, kinds, strides, out, signs):
    """``out[i, l*F:(l+1)*F] = sum_c w_c table[idx_c] / sum_c w_c`` for every point and level
    (zeros for points outside [0, 1]). ``table`` entries must be finite (the binarized +-1),
    or with ``signs`` the float parameters, read as their binarization (+1 where >= 0)."""
    n = u.shape[0]
    for ch in prange((n + _CHUNK - 1) // _CHUNK):
        lo = ch * _CHUNK
        hi = min(n, lo + _CHUNK)
        inside = np.empty(hi - lo, np.bool_)
        _fwd_block(u, table, res, rows, offsets, kinds, strides, out, lo, hi, inside, signs)


@njit(cache=True, error_model="numpy")
def _bwd_range(u, gout, res, rows, offsets, kinds, strides, gtable, start, stop):
    """``gtable[idx_c] += w_c / wn * gout`` for points [start, stop), level by level. Every row
    belongs to one level, so each entry receives its terms in point order, then corner order,
    as a point-by-point loop gives them."""
    dim = u.shape[1]
    L = res.shape[0]
    F = gtable.shape[1]
    inside = np.empty(max(stop - start, 0), np.bool_)
    for i in range(start, stop):
        inside[i - start] = _inside(u, i, dim)
    for l in range(L):
        r = res[l]
        kind = kinds[l]
        nr = rows[l]
        off = offsets[l]
        sy = strides[l, 1]
        base = l * F
        if dim == 3:
            sz = strides[l, 2]
            for i in range(start, stop):
                if not inside[i - start]:
                    continue
                ix, w, wn = _level3(u[i, 0], u[i, 1], u[i, 2], r, kind, nr, sy, sz)
                if wn == 0.0:
                    continue
                inv = np.float32(1.0) / wn
                if F == 4:
                    g0 = gout[i, base]
                    g1 = gout[i, base + 1]
                    g2 = gout[i, base + 2]
                    g3 = gout[i, base + 3]
                    for c in range(8):
                        if w[c] != 0.0:
                            s = w[c] * inv
                            rr = off + ix[c]
                            gtable[rr, 0] += s * g0
                            gtable[rr, 1] += s * g1
                            gtable[rr, 2] += s * g2
                            gtable[rr, 3] += s * g3
                    continue
                for c in range(8):
                    if w[c] != 0.0:
                        s = w[c] * inv
                        rr = off + ix[c]
                        for k in range(F):
                            gtable[rr, k] += s * gout[i, base + k]
        else:
            for i in range(start, stop):
                if not inside[i - start]:
                    continue
                ix, w, wn = _level2(u[i, 0], u[i, 1], r, kind, nr, sy)
                if wn == 0.0:
                    continue
                inv = np.float32(1.0) / wn
                if F == 4:
                    g0 = gout[i, base]
                    g1 = gout[i, base + 1]
                    g2 = gout[i, base + 2]
                    g3 = gout[i, base + 3]
                    for c in range(4):
                        if w[c] != 0.0:
                            s = w[c] * inv
                            rr = off + ix[c]
                            gtable[rr, 0] += s * g0
                            gtable[rr, 1] += s * g1
                            gtable[rr, 2] += s * g2
                            gtable[rr, 3] += s * g3
                    continue
                for c in range(4):
                    if w[c] != 0.0:
                        s = w[c] * inv
                        rr = off + ix[c]
                        for k in range(F):
                            gtable[rr, k] += s * gout[i, base + k]


@njit(cache=True, parallel=True, error_model="numpy")
def grid_bwd(u, gout, res, rows, offsets, kinds, strides, gtable, nparts):
    """Accumulate into ``gtable`` [rows, F] (zeroed by the caller).

    The points are split into ``nparts`` contiguous ranges, each accumulated into its own
    buffer (no write conflicts), then the buffers are summed in part order: deterministic for a
    given ``nparts``.
    """
    n = u.shape[0]
    if nparts <= 1:
        _bwd_range(u, gout, res, rows, offsets, kinds, strides, gtable, 0, n)
        return
    R, F = gtable.shape
    step = (n + nparts - 1) // nparts
    buf = np.zeros((nparts, R, F), np.float32)
    for p in prange(nparts):
        _bwd_range(u, gout, res, rows, offsets, kinds, strides, buf[p], p * step, min(n, (p + 1) * step))
    for r in prange(R):
        for p in range(nparts):
            for k in range(F):
                gtable[r, k] += buf[p, r, k]


@njit(cache=True, parallel=True, error_model="numpy")
def ste_mask(params, grad):
    """The straight-through binarization's backward in place: ``grad`` [R, F] kept where
    ``|params| <= 1``, else 0 (NaN: 0)."""
    R, F = grad.shape
    for r in prange(R):
        for k in range(F):
            if not (abs(params[r, k]) <= 1.0):
                grad[r, k] = 0.0


@njit(cache=True, parallel=True, error_model="numpy")
def count_nonneg(params):
    """The number of entries of ``params`` [R, F] that are >= 0 (their binarization's ones)."""
    R, F = params.shape
    n = 0
    for r in prange(R):
        for k in range(F):
            if params[r, k] >= 0:
                n += 1
    return n


@njit(cache=True, parallel=True, error_model="numpy")
def ste_fill(params, g, out):
    """``out`` [R, F] = ``g`` where ``|params| <= 1``, else 0 (NaN: 0): the straight-through
    gradient of a term that depends on the entries through the count of ones only."""
    R, F = params.shape
    for r in prange(R):
        for k in range(F):
            out[r, k] = g if abs(params[r, k]) <= 1.0 else np.float32(0.0)


# ------------------------------------------------------------------ exact (coding) path
_WEIGHT_ONE = 32768  # 2^WEIGHT_BITS (hashgrid.WEIGHT_BITS = 15)


@njit(cache=True, inline="always")
def _axis_exact(uv, r):
    """As :func:`_axis` in float64 with integer weights ``round(f * 2^15)`` (half to even)."""
    pos = uv * np.float64(r - 2)
    pos = pos + 0.5          # two rounded operations, as the PyTorch path (no FMA: no fastmath)
    gf = np.floor(pos)
    f = pos - gf             # exact
    g = np.int64(gf)
    g1 = min(g + 1, r - 1)
    w1 = np.int64(np.rint(f * np.float64(_WEIGHT_ONE)))
    w0 = _WEIGHT_ONE - w1
    if g <= 0 or g >= r - 1:
        w0 = 0
    if g1 <= 0 or g1 >= r - 1:
        w1 = 0
    return g, g1, w0, w1


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def grid_fwd_exact(u, table, res, rows, offsets, hashed, strides, out):
    """The exact path of :meth:`GridLevels.encode` (``exact=True``), fused.

    ``u`` [n, dim] float64, ``table`` [rows, F] int8 (entries +-1), ``out`` [n, L*F] float64.
    Corner weights are the same integers as the PyTorch path's (< 2^45), sums are done in int64
    (exact), and the one rounding is the final float64 division of two integers below 2^53:
    bit-identical to the PyTorch float64 path whatever the thread count. The int8 table keeps
    the random gathers in cache (measured 3.5x faster than a float64 table).
    """
    n, dim = u.shape
    L = res.shape[0]
    F = table.shape[1]
    nc = 8 if dim == 3 else 4
    for ch in prange((n + _CHUNK - 1) // _CHUNK):
        rix = np.empty(8, np.int64)
        wts = np.empty(8, np.int64)
        ti = np.empty(6, np.int64)
        tw = np.empty(6, np.int64)
        acc = np.empty(F, np.int64)
        for i in range(ch * _CHUNK, min(n, (ch + 1) * _CHUNK)):
            if not _inside(u, i, dim):
                for k in range(L * F):
                    out[i, k] = 0.0
                continue
            for l in range(L):
                r = res[l]
                hl = hashed[l]
                for d in range(dim):
                    g, g1, w0, w1 = _axis_exact(u[i, d], r)
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
                wn = 0
                for c in range(nc):
                    b0 = c & 1
                    b1 = 2 + ((c >> 1) & 1)
                    w = tw[b1] * tw[b0]
                    if dim == 3:
                        b2 = 4 + (c >> 2)
                        w = tw[b2] * w
                        h = (ti[b0] ^ ti[b1] ^ ti[b2]) if hl else (ti[b0] + ti[b1] + ti[b2])
                    else:
                        h = (ti[b0] ^ ti[b1]) if hl else (ti[b0] + ti[b1])
                    if hl:
                        h = (h & (nr - 1)) if pow2 else (h % nr)
                    rix[c] = off + h
                    wts[c] = w
                    wn += w
                for k in range(F):
                    acc[k] = 0
                for c in range(nc):
                    w = wts[c]
                    if w != 0:
                        rr = rix[c]
                        for k in range(F):
                            acc[k] += w * np.int64(table[rr, k])
                den = np.float64(wn) if wn != 0 else 1.0
                for k in range(F):
                    out[i, l * F + k] = np.float64(acc[k]) / den
