"""Range-coding primitives, anchor positions and weight packing."""
import math

import numpy as np
import pytest
import torch

from baseline.codec.container import BitstreamError
from baseline.testing.fuzz import fuzz_parser
from baseline.codec.rangecoder import (GaussianStreamDecoder, GaussianStreamEncoder, anchor_bounds,
                                       decode_bernoulli, dequantize_positions, encode_bernoulli,
                                       pack_positions, quantize_positions, unpack_positions)
from baseline.codec.weights import (pack_state_dict, round_module_, round_state_dict,
                                    unpack_state_dict)

torch.set_num_threads(1)


def entropy_bytes(n, n1):
    p = n1 / n
    return n * (-(p * math.log2(p) + (1 - p) * math.log2(1 - p))) / 8


@pytest.mark.parametrize("p", [0.5, 0.1, 0.003, 0.97])
def test_bernoulli_round_trip_near_entropy(p):
    rng = np.random.default_rng(0)
    bits = (rng.random(200_000) < p).astype(np.uint8)
    blob = encode_bernoulli(bits)
    out = decode_bernoulli(blob, expected_n=bits.size)
    assert np.array_equal(out, bits)
    assert len(blob) <= entropy_bytes(bits.size, int(bits.sum())) * 1.002 + 32


def test_bernoulli_constant_and_empty_cost_nothing():
    for bits in (np.ones(5_000_000, np.uint8), np.zeros(1234, np.uint8), np.zeros(0, np.uint8)):
        blob = encode_bernoulli(bits)
        assert len(blob) <= 17
        assert np.array_equal(decode_bernoulli(blob), bits)
    # masks as [N, K] bool
    m = np.random.default_rng(1).random((1000, 10)) < 0.6
    assert np.array_equal(decode_bernoulli(encode_bernoulli(m)).reshape(m.shape), m)
    with pytest.raises(ValueError):
        encode_bernoulli(np.array([0, 2]))


def test_bernoulli_hash_grid_size():
    bits = (np.random.default_rng(2).random(1_766_272) < 0.5).astype(np.uint8)
    blob = encode_bernoulli(bits)
    assert len(blob) / 2 ** 20 <= 0.2107  # ~0.21 MB
    assert np.array_equal(decode_bernoulli(blob), bits)


def test_bernoulli_damage_is_reported():
    bits = (np.random.default_rng(3).random(5000) < 0.3).astype(np.uint8)
    blob = encode_bernoulli(bits)
    with pytest.raises(BitstreamError, match="expected"):
        decode_bernoulli(blob, expected_n=4999)
    with pytest.raises(BitstreamError):
        decode_bernoulli(blob[:10])
    huge = bytearray(blob)
    huge[1:9] = (2 ** 62).to_bytes(8, "little")
    with pytest.raises(BitstreamError):
        decode_bernoulli(bytes(huge))
    stats = fuzz_parser(lambda b: decode_bernoulli(b), blob, n=200, seed=0)
    assert stats["error"] + stats["ok"] == 200


def test_gaussian_stream_chunks_and_escapes():
    rng = np.random.default_rng(4)
    enc = GaussianStreamEncoder(escape_limit=100)
    chunks = []
    for n in (1000, 0, 1, 5000):
        mu = rng.normal(0, 0.3, n)
        sd = np.exp(rng.normal(0, 1, n))
        s = np.round(rng.normal(mu, sd)).astype(np.int64)
        if n > 10:
            s[::97] = rng.integers(-10 ** 9, 10 ** 9, s[::97].size)  # escapes
        chunks.append((s, mu, sd))
        enc.add(s, mu, sd)
    blob = enc.finish()
    dec = GaussianStreamDecoder(blob, escape_limit=100)
    for s, mu, sd in chunks:
        assert np.array_equal(dec.decode(mu, sd), s)
    dec.check_done()
    dec = GaussianStreamDecoder(blob, escape_limit=100)
    with pytest.raises(BitstreamError, match="holds 1000 symbols"):
        dec.decode(np.zeros(999), np.ones(999))
    with pytest.raises(BitstreamError):
        GaussianStreamDecoder(blob[:5])
    with pytest.raises(ValueError):
        GaussianStreamEncoder().add([1], [0.0], [0.0])


def test_anchor_bounds_follow_hac_rule():
    xyz = np.array([[-2.0, 1.0, -5.0], [3.0, 4.0, -1.0]])
    lo, hi = anchor_bounds(xyz)
    np.testing.assert_allclose(lo, [-2.4, 0.8, -6.0], rtol=1e-6)
    np.testing.assert_allclose(hi, [3.6, 4.8, -0.8], rtol=1e-6)
    assert lo.dtype == np.float32 and np.all(lo <= xyz.min(0)) and np.all(hi >= xyz.max(0))
    lo, hi = anchor_bounds(np.zeros((4, 3)))
    assert np.all(hi > lo)


def test_position_quantization_round_trip():
    rng = np.random.default_rng(5)
    xyz = rng.normal(0, 5, (10000, 3)).astype(np.float32)
    lo, hi = anchor_bounds(xyz)
    q = quantize_positions(xyz, lo, hi)
    assert q.dtype == np.uint16 and q.shape == (10000, 3)
    dq = dequantize_positions(q, lo, hi)
    step = (hi.astype(np.float64) - lo) / 65535
    assert np.all(np.abs(dq - xyz) <= step / 2 + 1e-6 * np.abs(xyz) + 1e-7)
    blob = pack_positions(q)
    assert len(blob) == 6 * 10000
    assert np.array_equal(unpack_positions(blob, 10000), q)
    with pytest.raises(BitstreamError):
        unpack_positions(blob[:-1], 10000)
    # decoding is a pure function of (q, bounds): the encoder uses the decoded positions
    assert np.array_equal(dequantize_positions(unpack_positions(blob, 10000), lo, hi), dq)


def _module():
    torch.manual_seed(0)
    m = torch.nn.Sequential(torch.nn.Linear(54, 50), torch.nn.ReLU(), torch.nn.Linear(50, 70))
    m.register_buffer("count", torch.tensor([3, 4], dtype=torch.int64))
    m.register_buffer("flag", torch.tensor([True, False]))
    return m


def test_weights_float32_exact_and_deterministic():
    m = _module()
    blob = pack_state_dict(m.state_dict())
    assert blob == pack_state_dict(_module().state_dict())
    sd = unpack_state_dict(blob)
    assert list(sd) == list(m.state_dict())
    for k, v in m.state_dict().items():
        assert sd[k].dtype == v.dtype and torch.equal(sd[k], v)
    assert len(blob) < (54 * 50 + 50 + 50 * 70 + 70) * 4 + 400


def test_weights_float16_and_rounding_helper():
    m = _module()
    blob = pack_state_dict(m.state_dict(), "float16", keep=("count",))
    sd = unpack_state_dict(blob)
    assert len(blob) < (54 * 50 + 50 + 50 * 70 + 70) * 2 + 400
    rounded = round_state_dict(m.state_dict(), "float16")
    round_module_(m, "float16")
    for k, v in m.state_dict().items():
        assert torch.equal(sd[k], v) and torch.equal(rounded[k], v), k
    # rounding is idempotent: packing the rounded module again changes nothing
    assert pack_state_dict(m.state_dict(), "float16", keep=("count",)) == blob
    ex = unpack_state_dict(pack_state_dict(m.state_dict(), exclude=("0.",)))
    assert not any(k.startswith("0.") for k in ex)


def test_weights_damage_is_reported():
    blob = pack_state_dict(_module().state_dict())
    with pytest.raises(BitstreamError):
        unpack_state_dict(blob[:-3])
    with pytest.raises(BitstreamError):
        unpack_state_dict(blob + b"\x00")
    with pytest.raises(BitstreamError):
        unpack_state_dict(b"XX" + blob[2:])
    fuzz_parser(lambda b: unpack_state_dict(b), blob, n=300, seed=1)


def test_gaussian_stream_fuzz_never_crashes():
    rng = np.random.default_rng(6)
    sizes = (300, 1, 700)
    params = [(rng.normal(0, 0.3, n), np.exp(rng.normal(0, 1, n))) for n in sizes]
    enc = GaussianStreamEncoder(escape_limit=20)
    for mu, sd in params:
        s = np.round(rng.normal(mu, sd * 8)).astype(np.int64)
        enc.add(s, mu, sd)
    blob = enc.finish()

    def parse(b):
        dec = GaussianStreamDecoder(b, escape_limit=20)
        out = [dec.decode(mu, sd) for mu, sd in params]
        dec.check_done()
        return out

    stats = fuzz_parser(parse, blob, n=300, seed=2)
    assert stats["error"] > 0


def test_categorical_with_a_stored_histogram():
    from baseline.codec.rangecoder import decode_categorical, encode_categorical

    rng = np.random.default_rng(8)
    sym = rng.choice(4, size=3000, p=[0.7, 0.2, 0.09, 0.01])
    counts = np.bincount(sym, minlength=4)
    blob = encode_categorical(sym, counts)
    assert np.array_equal(decode_categorical(blob, counts, "t"), sym)
    assert len(blob) * 8 < 1.05 * 3000 * 1.26 + 64          # near the entropy (~1.23 bits)
    assert encode_categorical(np.zeros(5, int), [5]) == b""
    assert np.array_equal(decode_categorical(b"", [5], "t"), np.zeros(5))
    with pytest.raises(BitstreamError, match="single symbol kind"):
        decode_categorical(b"\0\0\0\0", [5], "t")
    with pytest.raises(BitstreamError, match="t:"):      # a histogram the payload does not hold
        decode_categorical(blob, counts + np.array([5, -5, 0, 0]), "t")


def test_every_range_coded_stream_is_consumed_exactly():
    """A payload with words (or bytes) its symbols did not use is refused, for the Gaussian,
    mixture, Bernoulli and categorical streams; the valid stream decodes."""
    import numpy as np

    from baseline.codec.container import BitstreamError
    from baseline.codec.mixture import MixtureStreamDecoder, MixtureStreamEncoder
    from baseline.codec.rangecoder import (GaussianStreamDecoder, GaussianStreamEncoder,
                                           decode_bernoulli, decode_categorical,
                                           encode_bernoulli, encode_categorical)

    rng = np.random.default_rng(0)
    n = 400
    m, s = rng.normal(size=n) * 3, rng.uniform(0.5, 3, n)
    sym = np.round(m + rng.normal(size=n) * s).astype(np.int64)
    e = GaussianStreamEncoder()
    e.add(sym, m, s)
    blob = e.finish()
    # (one appended 32-bit word is inside constriction's decoder look-ahead, so it cannot be
    # told from the stream's end: it decodes the same symbols; two or more are refused)
    for extra, ok in ((b"", True), (bytes(8), False), (b"\x01\x02\x03\x04" * 3, False)):
        d = GaussianStreamDecoder(blob + extra)
        try:
            out = d.decode(m, s)
            d.check_done()
            assert ok and np.array_equal(out, sym)
        except BitstreamError:
            assert not ok
    w = rng.uniform(0.1, 0.9, n)
    e = MixtureStreamEncoder()
    e.add(sym, m, s, m + 1, s, w)
    blob = e.finish()
    for extra, ok in ((b"", True), (bytes(1), False), (bytes(10 * len(blob)), False)):
        d = MixtureStreamDecoder(blob + extra)
        try:
            out = d.decode(m, s, m + 1, s, w)
            d.check_done()
            assert ok and np.array_equal(out, sym)
        except BitstreamError:
            assert not ok
    bits = (rng.uniform(size=n) < 0.3).astype(np.uint8)
    b = encode_bernoulli(bits)
    assert np.array_equal(decode_bernoulli(b), bits)
    with pytest.raises(BitstreamError, match="did not use"):
        decode_bernoulli(b + bytes(8))
    counts = np.array([5, 9, 2])
    idx = rng.permutation(np.repeat(np.arange(3), counts))
    c = encode_categorical(idx, counts)
    assert np.array_equal(decode_categorical(c, counts, "cat"), idx)
    with pytest.raises(BitstreamError, match="did not use"):
        decode_categorical(c + bytes(8), counts, "cat")
