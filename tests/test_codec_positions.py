"""Lossless coding of the 16-bit anchor positions as a set (codec.positions = "sorted")."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from baseline.codec.container import BitstreamError
from baseline.testing.fuzz import fuzz_parser
from baseline.codec.positions import (decode_positions, decode_uints, encode_positions,
                                      encode_uints, morton, unmorton)


def _lattice(n, seed):
    """Anchor-like positions: a few voxel lattices on a surface-ish band, 16-bit."""
    rng = np.random.default_rng(seed)
    out = []
    for step in (64, 16, 4):
        k = n // 3
        u = rng.uniform(0, 1, (k, 2))
        z = 0.5 + 0.1 * np.sin(6 * u[:, 0]) + rng.normal(0, 0.01, k)
        p = np.stack([u[:, 0], u[:, 1], z], 1) * 65535
        out.append(np.round(p / step) * step)
    return np.clip(np.concatenate(out), 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("q", [
    np.zeros((0, 3), np.uint16),
    np.array([[5, 6, 7]], np.uint16),
    np.array([[0, 0, 0], [65535, 65535, 65535]], np.uint16),
    np.array([[9, 9, 9]] * 4 + [[1, 2, 3]], np.uint16),          # duplicates: zero gaps
    np.random.default_rng(1).integers(0, 65536, (2000, 3)).astype(np.uint16),
    _lattice(3000, 2),
], ids=["empty", "one", "extremes", "duplicates", "uniform", "lattice"])
def test_round_trip_returns_the_set_in_the_coded_order(q):
    blob, order = encode_positions(q)
    assert sorted(order.tolist()) == list(range(len(q)))         # a permutation
    out = decode_positions(blob, len(q))
    assert out.dtype == np.uint16 and out.shape == q.shape
    assert np.array_equal(out, q[order])
    # the order is the Morton order of the per-axis dictionary indices: deterministic
    assert np.array_equal(encode_positions(q)[0], blob)


def test_lattice_positions_cost_far_less_than_48_bits():
    q = _lattice(30000, 3)
    blob, _ = encode_positions(q)
    bits = 8 * len(blob) / len(q)
    assert bits < 30, bits                 # truck: ~15 bits per anchor (README)
    # uniform noise is incompressible, but the coder stays near 48 bits, not far above
    u = np.random.default_rng(4).integers(0, 65536, (30000, 3)).astype(np.uint16)
    assert 8 * len(encode_positions(u)[0]) / len(u) < 48.5


def test_morton_inverts():
    ix = np.random.default_rng(5).integers(0, 65536, (1000, 3)).astype(np.uint64)
    assert np.array_equal(unmorton(morton(ix)), ix)
    assert int(morton(np.array([[1, 0, 0]], np.uint64))[0]) == 1
    assert int(morton(np.array([[0, 0, 1]], np.uint64))[0]) == 4


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.uint64, st.integers(0, 300),
                  elements=st.integers(0, (1 << 48) - 1)))
def test_uint_sequences_round_trip(v):
    blob = encode_uints(v, 48)
    out, pos = decode_uints(blob, 0, 48, "t")
    assert pos == len(blob) and np.array_equal(out, v)


@settings(max_examples=40, deadline=None)
@given(hnp.arrays(np.uint16, st.tuples(st.integers(0, 200), st.just(3)),
                  elements=st.integers(0, 65535)))
def test_any_position_set_round_trips(q):
    blob, order = encode_positions(q)
    assert np.array_equal(decode_positions(blob, len(q)), q[order])


def test_damage_is_named_never_a_crash():
    q = _lattice(600, 6)
    blob, _ = encode_positions(q)
    with pytest.raises(BitstreamError, match="holds 600 anchors, the header says 601"):
        decode_positions(blob, 601)
    with pytest.raises(BitstreamError, match="not a sorted-position stream"):
        decode_positions(b"XX" + blob[2:], 600)
    with pytest.raises(BitstreamError, match="trailing"):
        decode_positions(blob + b"\0", 600)
    for cut in (0, 3, 6, len(blob) // 2, len(blob) - 1):
        with pytest.raises(BitstreamError):
            decode_positions(blob[:cut], 600)

    def parse(b):     # no CRC inside the section (the container has it): only no crash / hang
        out = decode_positions(b, 600)
        assert out.shape == (600, 3) and out.dtype == np.uint16
        return None

    stats = fuzz_parser(parse, blob, n=300, seed=3)
    assert stats["error"] > 0


def test_pre_encode_positions_use_the_coded_anchors_bounds():
    """The evaluation before encoding must see the positions the decoder will have: bounds over
    the coded (valid) anchors only, as encode_model takes them. An uncoded anchor outside their
    box (every mask off) must not move the others (it did: 0.04 dB between the training's test
    line and the decoded file on a truck run)."""
    import torch

    from baseline.codec.rangecoder import anchor_bounds, dequantize_positions, quantize_positions
    from baseline.pipeline import quantized_positions

    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(500, 3, generator=g) * 2 - 1
    xyz[7] = torch.tensor([9.0, -9.0, 9.0])          # an uncoded anchor far outside
    coded = torch.ones(500, dtype=torch.bool)
    coded[7] = False
    x = xyz[coded].numpy()
    lo, hi = anchor_bounds(x)
    in_file = torch.from_numpy(dequantize_positions(quantize_positions(x, lo, hi), lo, hi))
    got = quantized_positions(xyz, coded)
    assert torch.equal(got[coded], in_file)
    # bounds over every anchor give other positions: the mismatch this guards against
    assert not torch.equal(quantized_positions(xyz, torch.ones(500, dtype=torch.bool))[coded],
                           in_file)


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float32, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=64)
                  .map(lambda s: (s[0], 3)),
                  elements=st.floats(-1e4, 1e4, width=32)),
       st.floats(0.0, 1.0))
def test_training_positions_are_the_files_bit_for_bit(x, cut):
    """``box_positions`` (training's 16-bit positions, torch) gives exactly the decoder's
    positions (the codec's numpy quantize + dequantize) for any anchors and any box, anchors
    outside the box included (both clip to its levels)."""
    import torch

    from baseline.codec.rangecoder import (anchor_bounds, box_positions, dequantize_positions,
                                           quantize_positions)

    lo, hi = anchor_bounds(x[: max(1, int(cut * len(x)))])     # a box of some of them
    want = dequantize_positions(quantize_positions(x, lo, hi), lo, hi)
    got = box_positions(torch.from_numpy(x), lo, hi)
    assert got.dtype == torch.float32
    assert np.array_equal(got.numpy(), want)
