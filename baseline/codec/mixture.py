"""Range coding of integer symbols under a per-symbol mixture of two quantized Gaussians.

HAC++'s feature likelihood is ``w1 N(m1, s1) + w2 N(m2, s2)`` integrated over each symbol's bin;
constriction codes one quantized Gaussian per symbol, not a mixture, and a per-symbol table of
the whole alphabet would cost O(alphabet) per symbol. This coder evaluates the mixture's CDF
only where it needs it, in integers, so encoder and decoder agree bit for bit on any machine:

* ``Phi`` comes from a table (``phi_table.npy``: ``round(Phi(j/1024) 2^30)`` for z in [0, 8],
  computed in 50-digit decimal arithmetic, non-decreasing) with integer linear interpolation on
  z rounded to 2^-20: an integer CDF in [0, 2^40], non-decreasing in z. z = (edge - m) / s is
  one correctly rounded subtraction and division (monotone in the edge).
* The mixture CDF is ``w1i Phi1 + (4096 - w1i) Phi2`` with ``w1i = round(4096 w1)`` clamped to
  [1, 4095]: an integer below 2^52, non-decreasing in the symbol.
* Over the chunk's alphabet ``[smin, smax]`` (A symbols) the cumulative frequency of symbol s is
  ``F(s) = floor(q(s) (2^16 - A)) + (s - smin)`` with ``q`` the CDF normalised to the alphabet
  (one float64 division of exact integers and one multiplication, both monotone): every symbol
  gets at least 1 of 2^16, F(smin) = 0, F(smax + 1) = 2^16. Encoding a symbol needs F at two
  points, decoding a binary search over the alphabet.
* The range coder is LZMA's (32-bit range, 16-bit frequencies, carry through a cached byte).

As :class:`baseline.codec.rangecoder.GaussianStreamEncoder`, symbols are coded chunk by chunk
into one stream, each chunk with its own alphabet; symbols beyond ``+-escape_limit`` are coded
as the edge symbol and stored raw. Layout: ``b"M1" | u32 chunks | u32 escapes | chunks x (u32 n,
i32 smin, i32 smax) | escapes x i64 | range-coder bytes``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from baseline.codec.chunked import ChunkReader, ChunkWriter
from baseline.codec.container import BitstreamError

PHI_TABLE = np.load(Path(__file__).resolve().parent / "phi_table.npy")
PREC = 16
TOTAL = 1 << PREC
W_ONE = 4096
_TAG = b"M1"
_TOP = 1 << 24
_MASK32 = 0xFFFFFFFF
Z_STEP = 1 << 20            # z is rounded to 2^-20
Z_MAX = 8 * Z_STEP


@njit(cache=True)
def _phi_int(z, T):
    """Phi(z) as an integer in [0, 2^40], non-decreasing in z (NaN reads as 0)."""
    if not (z == z):
        z = 0.0
    if z > 8.0:
        z = 8.0
    elif z < -8.0:
        z = -8.0
    zf = np.int64(np.rint(z * 1048576.0))
    a = zf if zf >= 0 else -zf
    j = a >> 10
    fr = a & 1023
    v = T[j] * 1024
    if fr:
        v += (T[j + 1] - T[j]) * fr
    return v if zf >= 0 else (np.int64(1) << 40) - v


@njit(cache=True)
def _cdf(edge, m1, s1, m2, s2, w1, T):
    return w1 * _phi_int((edge - m1) / s1, T) + (4096 - w1) * _phi_int((edge - m2) / s2, T)


@njit(cache=True)
def _freq_at(s, smin, A, lo, span, m1, s1, m2, s2, w1, T):
    """F(s) of the module docstring for smin <= s <= smin + A."""
    if s >= smin + A:
        return np.int64(65536)
    if s <= smin:
        return np.int64(0)
    N = 65536 - A
    if span > 0:
        c = _cdf(np.float64(s) - 0.5, m1, s1, m2, s2, w1, T) - lo
        q = np.float64(c) / np.float64(span)
    else:
        q = np.float64(s - smin) / np.float64(A)
    return np.int64(np.floor(q * N)) + (s - smin)


@njit(cache=True)
def _shift_low(st, out):
    low = st[0]
    if (low & 0xFFFFFFFF) < 0xFF000000 or (low >> 32) != 0:
        carry = low >> 32
        temp = st[2]
        while True:
            out[st[4]] = (temp + carry) & 0xFF
            st[4] += 1
            temp = 0xFF
            st[3] -= 1
            if st[3] == 0:
                break
        st[2] = (low >> 24) & 0xFF
    st[3] += 1
    st[0] = (low & 0x00FFFFFF) << 8


@njit(cache=True)
def _encode(sym, m1, s1, m2, s2, w1, smin, smax, T, st, out):
    """Encode symbols (already inside [smin, smax]) into ``out``; ``st`` = [low, range, cache,
    cache_size, pos] carries the coder's state across chunks."""
    A = smax - smin + 1
    for i in range(sym.shape[0]):
        lo = _cdf(np.float64(smin) - 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        hi = _cdf(np.float64(smax) + 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        span = hi - lo
        s = sym[i]
        f0 = _freq_at(s, smin, A, lo, span, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        f1 = _freq_at(s + 1, smin, A, lo, span, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        r = st[1] >> 16
        st[0] += r * f0
        st[1] = r * (f1 - f0)
        while st[1] < 16777216:
            st[1] = (st[1] << 8) & 0xFFFFFFFF
            _shift_low(st, out)


@njit(cache=True)
def _flush(st, out):
    for _ in range(5):
        _shift_low(st, out)


@njit(cache=True)
def _decode(m1, s1, m2, s2, w1, smin, smax, T, st, data, res):
    """Decode ``res.shape[0]`` symbols; ``st`` = [code, range, pos] across chunks. Returns
    False when the stream runs out of bytes (beyond the 4 the coder may read ahead)."""
    A = smax - smin + 1
    n_data = data.shape[0]
    for i in range(res.shape[0]):
        lo = _cdf(np.float64(smin) - 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        hi = _cdf(np.float64(smax) + 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        span = hi - lo
        r = st[1] >> 16
        if r == 0:
            return False
        v = st[0] // r
        if v > 65535:
            v = 65535
        a = smin
        b = smin + A
        while b - a > 1:
            mid = (a + b) >> 1
            if _freq_at(mid, smin, A, lo, span, m1[i], s1[i], m2[i], s2[i], w1[i], T) <= v:
                a = mid
            else:
                b = mid
        f0 = _freq_at(a, smin, A, lo, span, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        f1 = _freq_at(a + 1, smin, A, lo, span, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        res[i] = a
        st[0] -= r * f0
        st[1] = r * (f1 - f0)
        while st[1] < 16777216:
            byte = 0
            if st[2] < n_data:
                byte = data[st[2]]
            elif st[2] >= n_data + 4:
                return False
            st[2] += 1
            st[0] = ((st[0] << 8) | byte) & 0xFFFFFFFF
            st[1] = (st[1] << 8) & 0xFFFFFFFF
    return True


def _weights(w1) -> np.ndarray:
    w = np.rint(np.asarray(w1, dtype=np.float64) * W_ONE)
    w = np.where(np.isfinite(w), w, W_ONE // 2)
    return np.clip(w, 1, W_ONE - 1).astype(np.int64)


def _params(m1, s1, m2, s2, w1, n):
    out = []
    for v in (m1, s1, m2, s2):
        a = np.ascontiguousarray(v, dtype=np.float64).reshape(-1)
        if a.size != n:
            raise ValueError("mixture parameters must match the symbols in size")
        out.append(a)
    if not (all(np.isfinite(a).all() for a in out) and (out[1] > 0).all() and (out[3] > 0).all()):
        raise ValueError("mixture coding needs finite means and positive finite stds")
    w = _weights(np.asarray(w1).reshape(-1))
    if w.size != n:
        raise ValueError("mixture weights must match the symbols in size")
    return out + [w]


class MixtureStreamEncoder:
    """``add(symbols, m1, s1, m2, s2, w1)`` per chunk (means and stds in symbol units, ``w1`` the
    first component's weight in (0, 1)), then ``finish() -> bytes``."""

    def __init__(self, escape_limit: int = 16383):
        self.limit = int(escape_limit)
        self._table = ChunkWriter(self.limit)
        self._st = np.array([0, _MASK32, 0, 1, 0], dtype=np.int64)
        self._buf = np.zeros(1024, dtype=np.int64)

    def add(self, symbols, m1, s1, m2, s2, w1) -> None:
        s = np.asarray(symbols, dtype=np.int64).reshape(-1)
        n = s.size
        if n == 0:
            self._table.add(s)
            return
        m1, s1, m2, s2, w = _params(m1, s1, m2, s2, w1, n)
        s, smin, smax = self._table.add(s)
        if smin == smax:
            return
        need = int(self._st[4]) + 2 * n + 64
        if need > self._buf.size:
            buf = np.zeros(max(need, 2 * self._buf.size), dtype=np.int64)
            buf[:self._buf.size] = self._buf
            self._buf = buf
        _encode(s, m1, s1, m2, s2, w, smin, smax, PHI_TABLE, self._st, self._buf)

    def finish(self) -> bytes:
        if self._buf.size < self._st[4] + 16:
            self._buf = np.concatenate([self._buf, np.zeros(16, np.int64)])
        _flush(self._st, self._buf)
        payload = self._buf[:self._st[4]].astype(np.uint8).tobytes()
        return self._table.pack(_TAG, payload)


class MixtureStreamDecoder:
    """Decodes a :class:`MixtureStreamEncoder` blob chunk by chunk: ``decode(m1, s1, m2, s2,
    w1)`` with the encoder's parameters for the chunk's symbols."""

    def __init__(self, blob, what: str = "mixture", escape_limit: int = 16383):
        blob = bytes(blob)
        self.what = what
        self._table = ChunkReader(blob, _TAG, what, escape_limit, "mixture")
        off = self._table.payload_offset
        self.data = np.frombuffer(blob, dtype=np.uint8, offset=off).astype(np.int64)
        code = 0
        for i in range(5):
            code = ((code << 8) | (int(self.data[i]) if i < self.data.size else 0)) & _MASK32
        self._st = np.array([code, _MASK32, 5], dtype=np.int64)

    def decode(self, m1, s1, m2, s2, w1) -> np.ndarray:
        n = np.asarray(m1).size
        smin, smax = self._table.take(n)
        if n == 0:
            return np.zeros(0, np.int64)
        m1, s1, m2, s2, w = _params(m1, s1, m2, s2, w1, n)
        if smin == smax:
            s = np.full(n, smin, dtype=np.int64)
        else:
            s = np.empty(n, dtype=np.int64)
            if not _decode(m1, s1, m2, s2, w, smin, smax, PHI_TABLE, self._st, self.data, s):
                raise BitstreamError(f"{self.what}: range decoding ran past the stream's end")
        return self._table.restore(s)

    def check_done(self) -> None:
        """Every chunk and escape used, and every payload byte: a valid stream's decoder ends
        exactly at its last byte (the coder reads 5 bytes ahead of the 5 the encoder flushes)."""
        self._table.check_done()
        if int(self._st[2]) != self.data.size:
            raise BitstreamError(f"{self.what}: the range-coded payload has {self.data.size} "
                                 f"bytes, its symbols used {int(self._st[2])}")


def mixture_pmf(s, smin, smax, m1, s1, m2, s2, w1) -> np.ndarray:
    """The coder's probability of symbol ``s`` (arrays), for tests and size estimates."""
    s = np.asarray(s, dtype=np.int64).reshape(-1)
    m1, s1, m2, s2, w = _params(m1, s1, m2, s2, w1, s.size)
    out = np.empty(s.size)
    _pmf(s, int(smin), int(smax), m1, s1, m2, s2, w, PHI_TABLE, out)
    return out


@njit(cache=True)
def _pmf(sym, smin, smax, m1, s1, m2, s2, w1, T, out):
    A = smax - smin + 1
    for i in range(sym.shape[0]):
        lo = _cdf(np.float64(smin) - 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        hi = _cdf(np.float64(smax) + 0.5, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        f0 = _freq_at(sym[i], smin, A, lo, hi - lo, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        f1 = _freq_at(sym[i] + 1, smin, A, lo, hi - lo, m1[i], s1[i], m2[i], s2[i], w1[i], T)
        out[i] = (f1 - f0) / 65536.0
