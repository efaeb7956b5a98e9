"""Gaussian masks coded per anchor as K-bit patterns (``codec.masks = "patterns"``).

HAC codes the [N, K] mask bits with one global probability. They are far from independent: some
offset slots are almost always on or off, and an anchor's K bits go together (truck, lambda
0.004: 70 distinct patterns of 1024 in 171k anchors). Here each anchor's K bits form one symbol,
range coded with the file's own pattern histogram (stored as coded gaps and counts). On truck:
206 KB -> 67 KB and 212 KB -> 83 KB for two methods' files, the same masks.
"""
from __future__ import annotations

import struct
from typing import Tuple

import numpy as np

from baseline.codec.container import BitstreamError
from baseline.codec.positions import decode_uints, encode_uints
from baseline.codec.rangecoder import decode_categorical, encode_categorical

TAG = b"M1"
_HEAD = struct.Struct("<2sIB")     # tag, n anchors, K
_LEN = struct.Struct("<I")
MAX_K = 48
MAX_N = 1 << 31


def encode_mask_patterns(m) -> bytes:
    """uint8/bool [N, K] masks -> bytes (K <= 48)."""
    m = np.asarray(m).astype(np.uint8)
    if m.ndim != 2 or m.shape[1] > MAX_K or (m.size and m.max() > 1):
        raise ValueError(f"masks must be [N, K<= {MAX_K}] of 0/1, got {m.shape}")
    n, k = m.shape
    pat = (m.astype(np.uint64) << np.arange(k, dtype=np.uint64)).sum(1, dtype=np.uint64)
    uniq, inv, counts = np.unique(pat, return_inverse=True, return_counts=True)
    parts = [_HEAD.pack(TAG, n, k),
             encode_uints(np.diff(uniq.astype(np.int64), prepend=0).astype(np.uint64)
                          if uniq.size else uniq, max(k, 1)),
             encode_uints(counts.astype(np.uint64), 32)]
    words = encode_categorical(inv, counts)
    parts += [_LEN.pack(len(words)), words]
    return b"".join(parts)


def _table(buf: bytes, n: int, k: int, what: str) -> Tuple[np.ndarray, np.ndarray, int]:
    gaps, pos = decode_uints(buf, _HEAD.size, max(k, 1), f"{what}, patterns",
                             max_n=min(n, 1 << min(k, 31)) if n else 0)
    if gaps.size > 1 and np.any(gaps[1:] == 0):
        raise BitstreamError(f"{what}: patterns are not strictly increasing")
    uniq = np.cumsum(gaps, dtype=np.uint64)
    if uniq.size and (int(uniq[-1]) >> k):
        raise BitstreamError(f"{what}: a pattern has more than {k} bits")
    counts, pos = decode_uints(buf, pos, 32, f"{what}, counts", expected_n=uniq.size)
    if int(counts.sum()) != n or (uniq.size and counts.min() == 0):
        raise BitstreamError(f"{what}: pattern counts sum to {int(counts.sum())}, expected {n}")
    return uniq, counts.astype(np.int64), pos


def _header(blob, what: str) -> Tuple[bytes, int, int]:
    buf = bytes(blob)
    if len(buf) < _HEAD.size:
        raise BitstreamError(f"{what}: truncated header ({len(buf)} bytes)")
    tag, n, k = _HEAD.unpack_from(buf)
    if tag != TAG:
        raise BitstreamError(f"{what}: not a mask-pattern stream (tag {tag!r})")
    if n > MAX_N or k > MAX_K:
        raise BitstreamError(f"{what}: absurd size {n} x {k}")
    return buf, n, k


def mask_pattern_counts(blob, what: str = "masks") -> Tuple[int, int]:
    """``(n values = N K, n on)`` from the stream's table, without decoding the symbols."""
    buf, n, k = _header(blob, what)
    uniq, counts, _ = _table(buf, n, k, what)
    ones = ((uniq[:, None] >> np.arange(k, dtype=np.uint64)) & np.uint64(1)).sum(1, dtype=np.int64)
    return n * k, int((ones * counts).sum())


def decode_mask_patterns(blob, n_expected: int, k_expected: int,
                         what: str = "section 'masks'") -> np.ndarray:
    """Inverse of :func:`encode_mask_patterns`: uint8 [N, K]."""
    buf, n, k = _header(blob, what)
    if (n, k) != (n_expected, k_expected):
        raise BitstreamError(f"{what}: holds {n} x {k} masks, expected {n_expected} x {k_expected}")
    uniq, counts, pos = _table(buf, n, k, what)
    if pos + _LEN.size > len(buf):
        raise BitstreamError(f"{what}: truncated")
    (n_words,) = _LEN.unpack_from(buf, pos)
    pos += _LEN.size
    words = buf[pos:pos + n_words]
    if len(words) != n_words or pos + n_words != len(buf):
        raise BitstreamError(f"{what}: payload is {len(buf) - pos} bytes, its length field "
                             f"says {n_words}")
    if uniq.size == 0 and words:
        raise BitstreamError(f"{what}: unexpected payload for no masks")
    pat = uniq[decode_categorical(words, counts, what)] if uniq.size else np.zeros(0, np.uint64)
    return ((pat[:, None] >> np.arange(k, dtype=np.uint64)) & np.uint64(1)).astype(np.uint8)
