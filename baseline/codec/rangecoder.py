"""Entropy coding primitives on top of constriction's range coder (queue / FIFO order).

* Bernoulli coding of binary arrays with one global p (Gaussian masks, the binarised hash
  grids): ``encode_bernoulli`` / ``decode_bernoulli``. The blob stores ``n`` and ``n1`` (the
  decoder recomputes ``p = n1 / n`` exactly); an all-0 or all-1 array is 17 bytes, no payload.
* Quantized-Gaussian coding of integer symbols with per-symbol (mean, std) in symbol units:
  :class:`GaussianStreamEncoder` / :class:`GaussianStreamDecoder`. Symbols are coded chunk by
  chunk into one range-coder stream; each chunk has its own symbol range ``[smin, smax]``
  (constriction's leaky quantizer needs a finite alphabet, a tight one wastes least
  probability mass). Symbols beyond ``+-escape_limit`` are coded as an escape symbol and their
  true value is stored raw (int64) after the chunk table: never hit by a sane model, but a
  wild value can never break or bloat the coder.
* Anchor positions: HAC's widened bounds and 16-bit uniform quantization, stored raw
  little-endian uint16 [N, 3].

Every decoder validates what it reads and raises :class:`~baseline.codec.container.BitstreamError`
on inconsistent data; lengths are checked against the bytes present before allocating.
"""
from __future__ import annotations

import struct
from typing import Optional, Tuple

import numpy as np

from baseline.codec.chunked import ChunkReader, ChunkWriter
from baseline.codec.container import BitstreamError

try:  # constriction is a hard dependency of coding, not of importing this module
    import constriction
except ImportError:  # pragma: no cover
    constriction = None


class _CoderError(Exception):
    pass


def _call_coder(fn, *args):
    """Run a constriction call; any failure (including a Rust panic, which pyo3 raises as a
    BaseException) becomes a ``_CoderError``. Interrupts still propagate."""
    try:
        return fn(*args)
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as e:  # noqa: BLE001 - pyo3's PanicException is a BaseException
        raise _CoderError(f"{type(e).__name__}: {e}") from None


_CODER_ERRORS = (_CoderError,)


def _require_constriction():
    if constriction is None:  # pragma: no cover
        raise ImportError("entropy coding needs the 'constriction' package (pip install constriction)")
    return constriction


def _words_to_bytes(words: np.ndarray) -> bytes:
    return np.asarray(words, dtype="<u4").tobytes()


def _bytes_to_words(buf, what: str) -> np.ndarray:
    if len(buf) % 4:
        raise BitstreamError(f"{what}: range-coder payload length {len(buf)} is not a multiple of 4")
    return np.frombuffer(bytes(buf), dtype="<u4").astype(np.uint32)


# --------------------------------------------------------------------------- Bernoulli
_BERN_HDR = struct.Struct("<cQQ")
_BERN_TAG = b"B"
MAX_BERNOULLI = 1 << 31  # never allocate more than this from a length field


def bernoulli_p(n1: int, n: int) -> float:
    """The coding probability of a 1: ``n1 / n`` (exact float64 division, both sides)."""
    return float(n1) / float(n)


def encode_bernoulli(bits) -> bytes:
    """Range code a binary array (any shape, values 0/1 or bool) with one global p = n1 / n."""
    b = np.asarray(bits).reshape(-1)
    if b.size and not np.isin(b, (0, 1)).all():
        raise ValueError("encode_bernoulli expects values in {0, 1}")
    b = b.astype(np.int32)
    n = int(b.size)
    n1 = int(b.sum())
    head = _BERN_HDR.pack(_BERN_TAG, n, n1)
    if n1 == 0 or n1 == n:
        return head
    c = _require_constriction()
    enc = c.stream.queue.RangeEncoder()
    enc.encode(b, c.stream.model.Bernoulli(bernoulli_p(n1, n), perfect=False))
    return head + _words_to_bytes(enc.get_compressed())


def bernoulli_counts(blob, what: str = "bernoulli") -> Tuple[int, int]:
    """``(n, n_ones)`` of an :func:`encode_bernoulli` stream, read and checked from its header
    (no decoding; :func:`decode_bernoulli` starts with it)."""
    head = bytes(blob[:_BERN_HDR.size])
    if len(head) < _BERN_HDR.size:
        raise BitstreamError(f"{what}: truncated Bernoulli header ({len(head)} bytes)")
    tag, n, n1 = _BERN_HDR.unpack_from(head)
    if tag != _BERN_TAG:
        raise BitstreamError(f"{what}: not a Bernoulli stream")
    if n1 > n:
        raise BitstreamError(f"{what}: count of ones {n1} exceeds length {n}")
    if n > MAX_BERNOULLI:
        raise BitstreamError(f"{what}: absurd length {n}")
    return int(n), int(n1)


def decode_bernoulli(blob, expected_n: Optional[int] = None, what: str = "bernoulli") -> np.ndarray:
    """Inverse of :func:`encode_bernoulli`: uint8 array of 0/1 (flat)."""
    blob = bytes(blob)
    n, n1 = bernoulli_counts(blob, what)
    if expected_n is not None and n != expected_n:
        raise BitstreamError(f"{what}: holds {n} values, expected {expected_n}")
    payload = blob[_BERN_HDR.size:]
    if n1 == 0 or n1 == n:
        if payload:
            raise BitstreamError(f"{what}: unexpected payload after a constant stream")
        return np.full(n, 1 if (n1 == n and n) else 0, dtype=np.uint8)
    # A range coder spends at least ~log2(1/max(p,1-p)) bits per symbol; bound n by the payload
    # so a corrupt length never allocates a huge array.
    p = bernoulli_p(n1, n)
    min_bits = -np.log2(max(p, 1 - p))
    if n * min_bits > 8 * len(payload) + 64 or not payload:
        raise BitstreamError(f"{what}: length {n} inconsistent with a {len(payload)}-byte payload")
    words = _bytes_to_words(payload, what)
    c = _require_constriction()
    try:
        dec = _call_coder(c.stream.queue.RangeDecoder, words)
        out = _call_coder(dec.decode, c.stream.model.Bernoulli(p, perfect=False), int(n))
    except _CODER_ERRORS as e:  # corrupt payloads
        raise BitstreamError(f"{what}: range decoding failed ({e})") from None
    out = np.asarray(out, dtype=np.uint8)
    if int(out.sum()) != n1:
        raise BitstreamError(f"{what}: decoded {int(out.sum())} ones, header says {n1}")
    if not dec.maybe_exhausted():
        raise BitstreamError(f"{what}: the payload holds words its {n} values did not use")
    return out


# ------------------------------------------------------------------------ categorical
def categorical_probabilities(counts) -> np.ndarray:
    """The coding distribution of a stored histogram: counts / total in float64 (both sides)."""
    counts = np.asarray(counts, dtype=np.int64)
    return counts.astype(np.float64) / float(counts.sum())


def encode_categorical(symbols, counts) -> bytes:
    """Range code symbol indices ``0..len(counts)-1`` whose histogram is ``counts`` (stored by
    the caller). One symbol kind needs no payload: ``b""``."""
    counts = np.asarray(counts, dtype=np.int64)
    if len(counts) < 2:
        return b""
    c = _require_constriction()
    enc = c.stream.queue.RangeEncoder()
    enc.encode(np.asarray(symbols, dtype=np.int32).reshape(-1),
               c.stream.model.Categorical(categorical_probabilities(counts), perfect=False))
    return _words_to_bytes(enc.get_compressed())


def decode_categorical(payload, counts, what: str) -> np.ndarray:
    """Inverse of :func:`encode_categorical`: int64 [sum(counts)] indices, checked against the
    histogram (a corrupt payload is a BitstreamError, never a wrong result of the right size)."""
    counts = np.asarray(counts, dtype=np.int64)
    n = int(counts.sum())
    if len(counts) < 2:
        if payload:
            raise BitstreamError(f"{what}: unexpected payload for a single symbol kind")
        return np.zeros(n, np.int64)
    c = _require_constriction()
    try:
        dec = _call_coder(c.stream.queue.RangeDecoder, _bytes_to_words(payload, what))
        idx = _call_coder(dec.decode, c.stream.model.Categorical(
            categorical_probabilities(counts), perfect=False), n)
    except _CODER_ERRORS as e:
        raise BitstreamError(f"{what}: range decoding failed ({e})") from None
    idx = np.asarray(idx, np.int64)
    if (idx.size != n or np.any(idx < 0) or np.any(idx >= len(counts))
            or not np.array_equal(np.bincount(idx, minlength=len(counts)), counts)):
        raise BitstreamError(f"{what}: decoded symbols do not match their histogram")
    if not dec.maybe_exhausted():
        raise BitstreamError(f"{what}: the payload holds words its {n} symbols did not use")
    return idx


# --------------------------------------------------------------------------- Gaussian
_G_TAG = b"G1"
DEFAULT_ESCAPE_LIMIT = 16383
CALL_SYMBOLS = 1 << 16  # symbols per constriction call (it holds the GIL while it runs)


class GaussianStreamEncoder:
    """Range codes integer symbols with per-symbol quantized Gaussians, chunk by chunk.

    ``add(symbols, means, stds)``: ``symbols`` int, ``means``/``stds`` float64 in symbol units
    (bin ``k`` is ``[k - 0.5, k + 0.5)``); ``finish() -> bytes``. Layout: see
    :mod:`baseline.codec.chunked`.
    """

    def __init__(self, escape_limit: int = DEFAULT_ESCAPE_LIMIT):
        c = _require_constriction()
        self.limit = int(escape_limit)
        self._enc = c.stream.queue.RangeEncoder()
        self._table = ChunkWriter(self.limit)

    def add(self, symbols, means, stds) -> None:
        s = np.asarray(symbols, dtype=np.int64).reshape(-1)
        m = np.ascontiguousarray(means, dtype=np.float64).reshape(-1)
        d = np.ascontiguousarray(stds, dtype=np.float64).reshape(-1)
        if not (s.size == m.size == d.size):
            raise ValueError("symbols, means and stds must have the same size")
        if s.size and not (np.isfinite(m).all() and np.isfinite(d).all() and (d > 0).all()):
            raise ValueError("Gaussian coding needs finite means and positive finite stds")
        s, smin, smax = self._table.add(s)
        if smin == smax:  # a constant chunk needs no payload (and constriction needs smax > smin)
            return
        s32 = s.astype(np.int32)
        model = constriction.stream.model.QuantizedGaussian(smin, smax)
        for i in range(0, s32.size, CALL_SYMBOLS):  # short calls: other threads get the GIL
            self._enc.encode(s32[i:i + CALL_SYMBOLS], model, m[i:i + CALL_SYMBOLS], d[i:i + CALL_SYMBOLS])

    def finish(self) -> bytes:
        return self._table.pack(_G_TAG, _words_to_bytes(self._enc.get_compressed()))


class GaussianStreamDecoder:
    """Decodes a :class:`GaussianStreamEncoder` blob; ``decode(means, stds)`` per chunk, in order."""

    def __init__(self, blob, what: str = "gaussian", escape_limit: int = DEFAULT_ESCAPE_LIMIT):
        c = _require_constriction()
        blob = bytes(blob)
        self.what = what
        self._table = ChunkReader(blob, _G_TAG, what, escape_limit, "Gaussian")
        words = _bytes_to_words(blob[self._table.payload_offset:], what)
        try:
            self._dec = _call_coder(c.stream.queue.RangeDecoder, words)
        except _CoderError as e:
            raise BitstreamError(f"{what}: {e}") from None

    def decode(self, means, stds) -> np.ndarray:
        m = np.ascontiguousarray(means, dtype=np.float64).reshape(-1)
        d = np.ascontiguousarray(stds, dtype=np.float64).reshape(-1)
        smin, smax = self._table.take(m.size)
        n = m.size
        if n == 0:
            return np.zeros(0, np.int64)
        if not (np.isfinite(m).all() and np.isfinite(d).all() and (d > 0).all()):
            raise ValueError("Gaussian decoding needs finite means and positive finite stds")
        if smin == smax:
            s = np.full(n, smin, dtype=np.int64)
        else:
            try:
                model = _call_coder(constriction.stream.model.QuantizedGaussian, int(smin), int(smax))
                s = np.concatenate([np.asarray(_call_coder(self._dec.decode, model, m[i:i + CALL_SYMBOLS],
                                                           d[i:i + CALL_SYMBOLS]), dtype=np.int64)
                                    for i in range(0, n, CALL_SYMBOLS)])
            except _CODER_ERRORS as e:
                raise BitstreamError(f"{self.what}: range decoding failed ({e})") from None
        return self._table.restore(s)

    def check_done(self) -> None:
        """Every chunk and escape used, and the range-coded words too (words its symbols did
        not need, e.g. a payload padded after encoding, are refused; one appended word lies
        inside constriction's decoder look-ahead and cannot be told from the end: the symbols
        decoded are the same)."""
        self._table.check_done()
        if not self._dec.maybe_exhausted():
            raise BitstreamError(f"{self.what}: the range-coded payload holds words its symbols "
                                 f"did not use")


# --------------------------------------------------------------------------- positions
POSITION_BITS = 16
POSITION_LEVELS = (1 << POSITION_BITS) - 1


def anchor_bounds(xyz) -> Tuple[np.ndarray, np.ndarray]:
    """HAC's anchor bounds: per-axis min/max widened outward (x1.2 away from 0, x0.8 toward 0).

    ``min *= 1.2 if min < 0 else 0.8``; ``max *= 1.2 if max > 0 else 0.8``. An axis that stays
    degenerate (all anchors at 0) gets ``max = min + 1``. Returned as float32 [3] arrays (the
    bitstream stores them exactly).
    """
    x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if x.shape[0] == 0:
        return np.zeros(3, np.float32), np.ones(3, np.float32)
    if not np.isfinite(x).all():
        raise ValueError("anchor positions must be finite")
    lo = x.min(axis=0)
    hi = x.max(axis=0)
    lo = np.where(lo < 0, lo * 1.2, lo * 0.8)
    hi = np.where(hi > 0, hi * 1.2, hi * 0.8)
    lo = lo.astype(np.float32)
    hi = hi.astype(np.float32)
    # float32 rounding must not cut anchors off
    lo = np.where(lo.astype(np.float64) > x.min(axis=0), np.nextafter(lo, np.float32(-np.inf)), lo)
    hi = np.where(hi.astype(np.float64) < x.max(axis=0), np.nextafter(hi, np.float32(np.inf)), hi)
    hi = np.where(hi <= lo, lo + np.float32(1.0), hi)
    return lo.astype(np.float32), hi.astype(np.float32)


def _steps(lo, hi) -> Tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lo, dtype=np.float32).astype(np.float64).reshape(3)
    hi = np.asarray(hi, dtype=np.float32).astype(np.float64).reshape(3)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (hi <= lo).any():
        raise ValueError(f"invalid position bounds {lo.tolist()} {hi.tolist()}")
    return lo, (hi - lo) / POSITION_LEVELS


def quantize_positions(xyz, lo, hi) -> np.ndarray:
    """16-bit uniform quantization to the nearest level: uint16 [N, 3].

    (HAC floors; rounding to the nearest level halves the worst error at the same cost.)
    """
    base, step = _steps(lo, hi)
    x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    q = np.rint((x - base) / step)
    return np.clip(q, 0, POSITION_LEVELS).astype(np.uint16)


def dequantize_positions(q, lo, hi) -> np.ndarray:
    """Decoded positions float32 [N, 3] = ``lo + q * step`` (float64 arithmetic, then float32)."""
    base, step = _steps(lo, hi)
    q = np.asarray(q, dtype=np.float64).reshape(-1, 3)
    return (base + q * step).astype(np.float32)


def box_positions(xyz, lo, hi):
    """torch [N,3] -> float32 [N,3]: ``dequantize_positions(quantize_positions(xyz, lo, hi), lo,
    hi)`` on the tensor's device, bit for bit (the same float64 operations in the same order;
    round half to even in both): the positions training draws where the file will store them
    at 16 bits (``train.positions = "coded"``)."""
    import torch

    base, step = (torch.from_numpy(a).to(xyz.device) for a in _steps(lo, hi))
    t = xyz.to(torch.float64, copy=True)     # in place from here: half the time of new tensors
    t.sub_(base).div_(step).round_().clamp_(0, POSITION_LEVELS).mul_(step).add_(base)
    return t.float()


def pack_positions(q) -> bytes:
    return np.ascontiguousarray(q, dtype="<u2").reshape(-1, 3).tobytes()


def unpack_positions(blob, n: int, what: str = "positions") -> np.ndarray:
    blob = bytes(blob)
    if len(blob) != 6 * int(n):
        raise BitstreamError(f"{what}: {len(blob)} bytes, expected {6 * int(n)} for {n} anchors")
    return np.frombuffer(blob, dtype="<u2").reshape(-1, 3).astype(np.uint16)
