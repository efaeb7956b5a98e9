"""The chunk table and escape store shared by the chunked range-coded streams.

Both :mod:`baseline.codec.rangecoder` (Gaussian, constriction) and
:mod:`baseline.codec.mixture` (two-component Gaussian mixture) lay a stream out the same way:
``tag (2 bytes) | u32 chunks | u32 escapes | chunks x (u32 n, i32 smin, i32 smax) |
escapes x i64 | coder payload``. Symbols beyond ``+-limit`` are coded as the edge symbol
``+-(limit + 1)`` and their true values are stored raw in the escape store, in order.
"""
from __future__ import annotations

import struct
from typing import List, Tuple

import numpy as np

from baseline.codec.container import BitstreamError

HEADER = struct.Struct("<2sII")   # tag, n_chunks, n_escapes
ROW = struct.Struct("<Iii")       # n_symbols, smin, smax


class ChunkWriter:
    """Collects the chunk rows and escapes of an encoder.

    ``add(symbols) -> (clipped, smin, smax)``: ``symbols`` int64 ``[N]``; returns them with
    escapes replaced by the edge symbol, and the chunk's alphabet (``smin == smax`` means the
    chunk needs no payload).
    """

    def __init__(self, limit: int):
        self.limit = int(limit)
        self.rows: List[Tuple[int, int, int]] = []
        self._escapes: List[np.ndarray] = []

    def add(self, s: np.ndarray) -> Tuple[np.ndarray, int, int]:
        if s.size == 0:
            self.rows.append((0, 0, 0))
            return s, 0, 0
        esc = np.abs(s) > self.limit
        if esc.any():
            self._escapes.append(s[esc])
            s = np.clip(s, -self.limit - 1, self.limit + 1)
        smin, smax = int(s.min()), int(s.max())
        self.rows.append((int(s.size), smin, smax))
        return s, smin, smax

    def pack(self, tag: bytes, payload: bytes) -> bytes:
        esc = np.concatenate(self._escapes) if self._escapes else np.zeros(0, np.int64)
        parts = [HEADER.pack(tag, len(self.rows), int(esc.size))]
        parts += [ROW.pack(*r) for r in self.rows]
        parts.append(esc.astype("<i8").tobytes())
        parts.append(payload)
        return b"".join(parts)


class ChunkReader:
    """Parses and checks a stream's chunk table and escapes; hands chunks out in order.

    ``payload_offset``: where the coder's bytes start. ``take(n)`` returns the next chunk's
    ``(smin, smax)`` after checking it holds ``n`` symbols; ``restore(s)`` puts the escaped
    values back; ``check_done()`` insists every chunk and escape was used.
    """

    def __init__(self, blob: bytes, tag: bytes, what: str, limit: int, kind: str):
        self.what, self.limit = what, int(limit)
        if len(blob) < HEADER.size:
            raise BitstreamError(f"{what}: truncated {kind} stream header")
        got, n_chunks, n_esc = HEADER.unpack_from(blob)
        if got != tag:
            raise BitstreamError(f"{what}: not a {kind} stream")
        off = HEADER.size
        if n_chunks * ROW.size + 8 * n_esc > len(blob) - off:
            raise BitstreamError(f"{what}: chunk table ({n_chunks} chunks, {n_esc} escapes) "
                                 f"exceeds the {len(blob)}-byte stream")
        self.chunks = [ROW.unpack_from(blob, off + i * ROW.size) for i in range(n_chunks)]
        off += n_chunks * ROW.size
        self.escapes = np.frombuffer(blob, dtype="<i8", count=n_esc, offset=off).astype(np.int64)
        self.payload_offset = off + 8 * n_esc
        for n, smin, smax in self.chunks:
            if n and not (-self.limit - 1 <= smin <= smax <= self.limit + 1):
                raise BitstreamError(f"{what}: invalid symbol range [{smin}, {smax}]")
        self._next = 0
        self._esc_pos = 0

    def take(self, n_expected: int) -> Tuple[int, int]:
        if self._next >= len(self.chunks):
            raise BitstreamError(f"{self.what}: more chunks requested than the stream holds")
        n, smin, smax = self.chunks[self._next]
        self._next += 1
        if n != n_expected:
            raise BitstreamError(f"{self.what}: chunk {self._next - 1} holds {n} symbols, "
                                 f"the decoder expects {n_expected}")
        return smin, smax

    def restore(self, s: np.ndarray) -> np.ndarray:
        esc = np.abs(s) > self.limit
        k = int(esc.sum())
        if k:
            if self._esc_pos + k > self.escapes.size:
                raise BitstreamError(f"{self.what}: more escape symbols than stored escapes")
            s[esc] = self.escapes[self._esc_pos:self._esc_pos + k]
            self._esc_pos += k
        return s

    def check_done(self) -> None:
        if self._next != len(self.chunks) or self._esc_pos != self.escapes.size:
            raise BitstreamError(f"{self.what}: stream holds {len(self.chunks)} chunks / "
                                 f"{self.escapes.size} escapes, decoded {self._next} / "
                                 f"{self._esc_pos}")
