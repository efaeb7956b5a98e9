"""Gaussian masks coded per anchor as K-bit patterns (codec.masks = "patterns")."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from baseline.codec.container import BitstreamError
from baseline.testing.fuzz import fuzz_parser
from baseline.codec.masks import decode_mask_patterns, encode_mask_patterns, mask_pattern_counts
from baseline.codec.rangecoder import encode_bernoulli


def _anchor_like(n, k, seed):
    """Slot-dependent masks, as trained models have them (some slots nearly always off)."""
    rng = np.random.default_rng(seed)
    p = np.linspace(0.9, 0.0, k)
    return (rng.uniform(size=(n, k)) < p).astype(np.uint8)


@pytest.mark.parametrize("m", [
    np.zeros((0, 10), np.uint8), np.ones((7, 10), np.uint8), np.zeros((4, 10), np.uint8),
    np.zeros((3, 0), np.uint8), _anchor_like(2000, 10, 1), _anchor_like(300, 48, 2),
], ids=["empty", "all-on", "all-off", "k0", "anchor-like", "k48"])
def test_round_trip_and_counts(m):
    blob = encode_mask_patterns(m)
    out = decode_mask_patterns(blob, *m.shape)
    assert out.dtype == np.uint8 and np.array_equal(out, m)
    assert mask_pattern_counts(blob) == (m.size, int(m.sum()))


def test_slot_structure_costs_less_than_one_global_probability():
    m = _anchor_like(20000, 10, 3)
    assert len(encode_mask_patterns(m)) < 0.8 * len(encode_bernoulli(m))
    # a constant mask (all on: the case a scene does not use masks) costs next to nothing
    assert len(encode_mask_patterns(np.ones((20000, 10), np.uint8))) < 64


@settings(max_examples=50, deadline=None)
@given(hnp.arrays(np.uint8, st.tuples(st.integers(0, 150), st.integers(0, 12)),
                  elements=st.integers(0, 1)))
def test_any_masks_round_trip(m):
    assert np.array_equal(decode_mask_patterns(encode_mask_patterns(m), *m.shape), m)


def test_damage_is_named_never_a_crash():
    m = _anchor_like(500, 10, 4)
    blob = encode_mask_patterns(m)
    with pytest.raises(BitstreamError, match="holds 500 x 10 masks, expected 500 x 9"):
        decode_mask_patterns(blob, 500, 9)
    with pytest.raises(BitstreamError, match="not a mask-pattern stream"):
        decode_mask_patterns(b"B" + blob[1:], 500, 10)
    with pytest.raises(BitstreamError):
        decode_mask_patterns(blob + b"\0", 500, 10)
    for cut in (0, 5, 8, len(blob) // 2, len(blob) - 1):
        with pytest.raises(BitstreamError):
            decode_mask_patterns(blob[:cut], 500, 10)
    with pytest.raises(ValueError):
        encode_mask_patterns(np.full((3, 4), 2, np.uint8))

    def parse(b):       # the container's CRC guards files; here: no crash, no hang
        out = decode_mask_patterns(b, 500, 10)
        assert out.shape == (500, 10)
        return None

    assert fuzz_parser(parse, blob, n=300, seed=5)["error"] > 0
