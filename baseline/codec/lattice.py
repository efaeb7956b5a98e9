"""Lossless coding of anchor positions on the voxel lattice (``codec.positions = "lattice"``).

Anchors are created on the voxel lattice: the initial ones by voxelizing the SfM points
(``k * voxel_size``), the grown ones on multiples of it (``voxel_size * 16 / 4 / 1``). HAC++
rounds its anchors to that lattice (``round(anchor / voxel_size)``) and codes the integer
coordinates losslessly with MPEG's G-PCC (an octree coder with neighbour contexts). Here the
positions are already on the lattice (nothing moves an anchor; ``(k * v)`` in float64 rounded to
float32, the same expression everywhere), so the file stores the integer coordinates ``k`` and the
voxel size, and the decoder rebuilds bit-identical positions.

The coder is an octree over ``k - min(k)`` (depth ``D`` = bits of the largest coordinate):
level by level, every occupied node's 8 child-occupancy bits are range coded one by one
(the 8th is implied when the first 7 are 0), each with an adaptive probability chosen by a
context: the bit's octant, how many of the node's earlier bits were 1, how many of the node's
6 face neighbours (same level) are occupied, and how many of the 3 neighbours on the octant's
side are. The probabilities are counts of what was coded before in the same context (weight 16
per bit, divided by 16 at each new level, p = (n1 + 8) / (n + 16), integers until one exact
float64 division), updated every :data:`CHUNK` nodes, so the decoder derives the same ones; no
table is stored. On truck (-r 4, 166,565 anchors, voxel 0.01): 9.5 bits per anchor, against
15.0 for the ``sorted`` coder (baseline/codec/positions.py) and 15.3 for Google's Draco (kd-tree
point-cloud coder, ``DracoPy``, quantized exactly onto the integers, compression level 5-10),
which is why this is hand-written: no Python library codes integer point sets this well
(G-PCC's reference encoder is a C++ program, not a Python dependency).

The leaves come out in Morton order (children in octant order under parents in Morton order):
:func:`encode_lattice` returns that order and every other per-anchor section follows it.
"""
from __future__ import annotations

import math
import struct
from typing import Tuple

import numpy as np

from baseline.codec.container import BitstreamError
from baseline.codec.positions import read_head
from baseline.codec.rangecoder import _CODER_ERRORS, _bytes_to_words, _call_coder, _require_constriction

TAG = b"L1"
_HEAD = struct.Struct("<2sIB3qd")   # tag, n anchors, depth, min k (3), voxel size
MAX_DEPTH = 21                      # bits per axis (the neighbour keys pack 3 x 21 bits)
MAX_ABS_K = 1 << 40                 # |min k|: positions stay far inside float32's range
CHUNK = 1024                        # nodes between probability updates
_W = 16                             # count weight of one coded bit (and the per-level divisor)
N_CTX = 8 * 8 * 7 * 4               # octant x earlier ones x face neighbours x side neighbours


def lattice_positions(k: np.ndarray, voxel_size: float) -> np.ndarray:
    """[n,3] integer lattice coordinates -> float32 positions, ``float32(float64(k) * v)``: the
    expression anchor creation uses (baseline/scaffold/anchors.py, densify.py)."""
    return (np.asarray(k, np.int64).astype(np.float64) * float(voxel_size)).astype(np.float32)


def lattice_coordinates(xyz: np.ndarray, voxel_size: float) -> np.ndarray:
    """float32 positions -> [n,3] int64 lattice coordinates; ValueError naming how many anchors
    are off the lattice (their positions would not decode bit for bit)."""
    v = float(voxel_size)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"lattice positions need a positive voxel size, got {voxel_size}")
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    if not np.isfinite(xyz).all():
        raise ValueError("lattice positions: non-finite anchor positions")
    k = np.round(xyz.astype(np.float64) / v).astype(np.int64)
    off = np.any(lattice_positions(k, v) != xyz, axis=1)
    if off.any():
        raise ValueError(f"{int(off.sum())} of {len(xyz)} anchors are off the voxel lattice "
                         f"(voxel {v}): code the positions as 'sorted' or 'raw16'")
    return k


def _contexts(nodes: np.ndarray) -> np.ndarray:
    """Face-neighbour occupancy [n,6] (+x, -x, +y, -y, +z, -z) of one level's nodes [n,3]
    (coordinates < 2^21): per axis, the nodes sorted with that axis as the lowest key field;
    a neighbour along it is the next (previous) key plus (minus) one."""
    n = len(nodes)
    occ = np.zeros((n, 6), np.int64)
    for a in range(3):
        o1, o2 = [x for x in range(3) if x != a]
        key = (nodes[:, o1] << 42) | (nodes[:, o2] << 21) | nodes[:, a]
        perm = np.argsort(key, kind="stable")
        ks = key[perm]
        step = ks[1:] == ks[:-1] + 1
        occ[perm[:-1], 2 * a] = step
        occ[perm[1:], 2 * a + 1] = step
    return occ


def _side(nb: np.ndarray, b: int) -> np.ndarray:
    """Occupied face neighbours on octant ``b``'s side (x, y, z bits of b pick +/-)."""
    return sum(nb[:, 2 * a + (0 if (b >> a) & 1 else 1)] for a in range(3))


class _Model:
    """The adaptive context counts both sides keep."""

    def __init__(self):
        self.n1 = np.zeros(N_CTX, np.int64)
        self.n = np.zeros(N_CTX, np.int64)

    def new_level(self):
        self.n1 //= _W
        self.n //= _W

    def probs(self, ctx):
        return (self.n1[ctx] + _W // 2).astype(np.float64) / (self.n[ctx] + _W).astype(np.float64)

    def update(self, ctx, bits):
        self.n1 += _W * np.bincount(ctx, weights=bits, minlength=N_CTX).astype(np.int64)
        self.n += _W * np.bincount(ctx, minlength=N_CTX)


def _children(nodes: np.ndarray, occ: np.ndarray) -> np.ndarray:
    """Children of ``nodes`` [n,3] with occupancy bytes ``occ`` [n]: parents' order, octants
    ascending (Morton order when the parents are)."""
    bits = (occ[:, None] >> np.arange(8)) & 1                      # [n, 8]
    par, octant = np.nonzero(bits)
    oct_xyz = np.stack([octant & 1, (octant >> 1) & 1, octant >> 2], 1)
    return nodes[par] * 2 + oct_xyz


def encode_lattice(k, voxel_size: float) -> Tuple[bytes, np.ndarray]:
    """Code int [N,3] lattice coordinates: ``(section bytes, order)`` with
    ``decode_lattice(blob, N)[0] == k[order]``."""
    c = _require_constriction()
    k = np.asarray(k, np.int64).reshape(-1, 3)
    n = len(k)
    kmin = k.min(0) if n else np.zeros(3, np.int64)
    if np.abs(kmin).max() > MAX_ABS_K:
        raise ValueError(f"lattice coordinates too large ({kmin.tolist()})")
    k0 = k - kmin
    top = int(k0.max()) if n else 0
    depth = max(1, top.bit_length())
    if depth > MAX_DEPTH:
        raise ValueError(f"the anchors span {top + 1} voxels on an axis; the lattice coder takes "
                         f"at most 2^{MAX_DEPTH} (use a larger voxel or the 'sorted' coder)")
    # Morton order of the leaves (the order the decoder produces)
    m = np.zeros(n, np.uint64)
    for b in range(depth):
        for a in range(3):
            m |= ((k0[:, a].astype(np.uint64) >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + a)
    order = np.argsort(m, kind="stable")
    if n > 1 and np.any(m[order][1:] == m[order][:-1]):
        raise ValueError("the lattice coder codes a set: two anchors share a position")
    leaves = k0[order]
    enc = c.stream.queue.RangeEncoder()
    family = c.stream.model.Bernoulli(perfect=False)
    model = _Model()
    nodes = np.zeros((1 if n else 0, 3), np.int64)
    for lev in range(depth if n else 0):
        sh = depth - lev - 1
        child = leaves >> sh                                        # Morton order, repeats
        first = np.ones(n, bool)
        first[1:] = np.any(child[1:] != child[:-1], axis=1)
        child = child[first]
        parent = child >> 1
        pfirst = np.ones(len(child), bool)
        pfirst[1:] = np.any(parent[1:] != parent[:-1], axis=1)
        pidx = np.cumsum(pfirst) - 1
        octant = (child[:, 0] & 1) | ((child[:, 1] & 1) << 1) | ((child[:, 2] & 1) << 2)
        occ = np.zeros(int(pfirst.sum()), np.int64)
        np.bitwise_or.at(occ, pidx, 1 << octant)
        model.new_level()
        nb = _contexts(nodes)
        nb6 = nb.sum(1)
        before = np.zeros(len(nodes), np.int64)
        for b in range(8):
            bit = (occ >> b) & 1
            ctx = ((b * 8 + before) * 7 + nb6) * 4 + _side(nb, b)
            coded = before > 0 if b == 7 else np.ones(len(nodes), bool)
            for s in range(0, len(nodes), CHUNK):
                sl = slice(s, s + CHUNK)
                sel = coded[sl]
                cx, bx = ctx[sl][sel], bit[sl][sel]
                if len(cx):
                    enc.encode(bx.astype(np.int32), family, model.probs(cx))
                    model.update(cx, bx)
            before += bit
        nodes = _children(nodes, occ)
    assert len(nodes) == n and np.array_equal(nodes, leaves)
    head = _HEAD.pack(TAG, n, depth, *[int(x) for x in kmin], float(voxel_size))
    return head + np.asarray(enc.get_compressed(), "<u4").tobytes(), order


def decode_lattice(blob, n: int, what: str = "section 'positions'") -> Tuple[np.ndarray, float]:
    """Inverse of :func:`encode_lattice`: ``(k int64 [N,3] in the coded order, voxel size)``."""
    buf = bytes(blob)
    _, _, depth, kx, ky, kz, v = read_head(buf, _HEAD, TAG, n, what, "lattice-position")
    if not 1 <= depth <= MAX_DEPTH:
        raise BitstreamError(f"{what}: octree depth {depth} outside [1, {MAX_DEPTH}]")
    kmin = np.array([kx, ky, kz], np.int64)
    if np.abs(kmin).max() > MAX_ABS_K:
        raise BitstreamError(f"{what}: lattice origin {kmin.tolist()} out of range")
    if not (math.isfinite(v) and 1e-6 <= v <= 1e6):
        raise BitstreamError(f"{what}: voxel size {v} outside [1e-6, 1e6]")
    words = _bytes_to_words(buf[_HEAD.size:], what)
    if n == 0:
        if len(words):
            raise BitstreamError(f"{what}: unexpected payload for zero anchors")
        return np.zeros((0, 3), np.int64), v
    c = _require_constriction()
    family = c.stream.model.Bernoulli(perfect=False)
    try:
        dec = _call_coder(c.stream.queue.RangeDecoder, words)
    except _CODER_ERRORS as e:
        raise BitstreamError(f"{what}: range decoding failed ({e})") from None
    model = _Model()
    nodes = np.zeros((1, 3), np.int64)
    for lev in range(depth):
        model.new_level()
        nb = _contexts(nodes)
        nb6 = nb.sum(1)
        before = np.zeros(len(nodes), np.int64)
        occ = np.zeros(len(nodes), np.int64)
        for b in range(8):
            ctx = ((b * 8 + before) * 7 + nb6) * 4 + _side(nb, b)
            coded = before > 0 if b == 7 else np.ones(len(nodes), bool)
            bit = np.where(coded, 0, 1).astype(np.int64)            # the implied 8th bit
            for s in range(0, len(nodes), CHUNK):
                sl = slice(s, s + CHUNK)
                sel = coded[sl]
                cx = ctx[sl][sel]
                if len(cx):
                    try:
                        got = _call_coder(dec.decode, family, model.probs(cx))
                    except _CODER_ERRORS as e:
                        raise BitstreamError(f"{what}: range decoding failed ({e})") from None
                    got = np.asarray(got, np.int64)
                    bit[s:s + CHUNK][sel] = got
                    model.update(cx, got)
            occ |= bit << b
            before += bit
        total = int(before.sum())
        if total > n:   # before any allocation proportional to the count
            raise BitstreamError(f"{what}: octree level {lev + 1} has {total} nodes, more than "
                                 f"the {n} anchors")
        nodes = _children(nodes, occ)
    if len(nodes) != n:
        raise BitstreamError(f"{what}: the octree has {len(nodes)} leaves, the header says {n}")
    if not dec.maybe_exhausted():
        raise BitstreamError(f"{what}: the payload holds words its octree did not use")
    return nodes + kmin, v
