"""Lossless voxel-lattice positions (codec.positions = "lattice", HAC++'s kind of coding)."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from baseline.codec.container import BitstreamError
from baseline.testing.fuzz import fuzz_parser
from baseline.codec.lattice import (MAX_DEPTH, decode_lattice, encode_lattice, lattice_coordinates,
                                    lattice_positions)
from baseline.codec.positions import encode_positions


def _surface(n, seed, span=4000):
    """Anchor-like lattice points: a wavy surface band on three lattices (steps 16, 4, 1)."""
    rng = np.random.default_rng(seed)
    out = []
    for step in (16, 4, 1):
        u = rng.uniform(0, 1, (n // 3, 2))
        z = 0.5 + 0.1 * np.sin(6 * u[:, 0]) + rng.normal(0, 0.003, n // 3)
        out.append(np.round(np.stack([u[:, 0], u[:, 1], z], 1) * span / step) * step)
    return np.unique(np.concatenate(out).astype(np.int64), axis=0) - 1234


@pytest.mark.parametrize("k", [
    np.zeros((0, 3), np.int64),
    np.array([[5, -6, 7]], np.int64),
    np.array([[0, 0, 0], [(1 << MAX_DEPTH) - 1] * 3], np.int64),
    np.array([[-3, 2, 1], [-3, 2, 2], [-4, 2, 1]], np.int64),
    np.unique(np.random.default_rng(1).integers(-500, 500, (2000, 3)), axis=0),
    _surface(3000, 2),
], ids=["empty", "one", "extremes", "neighbours", "uniform", "surface"])
def test_round_trip_returns_the_set_in_the_coded_order(k):
    blob, order = encode_lattice(k, 0.01)
    assert sorted(order.tolist()) == list(range(len(k)))
    out, v = decode_lattice(blob, len(k))
    assert v == 0.01 and out.dtype == np.int64 and np.array_equal(out, k[order])
    assert np.array_equal(encode_lattice(k, 0.01)[0], blob)          # deterministic


@settings(max_examples=40, deadline=None)
@given(hnp.arrays(np.int64, st.tuples(st.integers(0, 150), st.just(3)),
                  elements=st.integers(-3000, 3000)))
def test_any_point_set_round_trips(k):
    k = np.unique(k, axis=0)
    blob, order = encode_lattice(k, 0.25)
    out, _ = decode_lattice(blob, len(k))
    assert np.array_equal(out, k[order])


def test_positions_decode_bit_for_bit_and_off_lattice_is_refused():
    """The decoded positions are the ones anchor creation made (float32 of k * v in float64),
    whatever the voxel size; a position off the lattice is refused by count, never rounded."""
    for v in (0.01, 0.0123456789, 3.0, 1e-5):
        k = _surface(900, 3)
        xyz = (torch.from_numpy(k).double() * v).float().numpy()      # anchors.voxelize's expression
        kk = lattice_coordinates(xyz, v)
        assert np.array_equal(kk, k)
        blob, order = encode_lattice(kk, v)
        kd, vd = decode_lattice(blob, len(k))
        assert np.array_equal(lattice_positions(kd, vd), xyz[order])
    xyz = lattice_positions(_surface(300, 4), 0.01)
    xyz[[3, 50]] += np.float32(0.001)
    with pytest.raises(ValueError, match="2 of .* anchors are off the voxel lattice"):
        lattice_coordinates(xyz, 0.01)
    with pytest.raises(ValueError, match="share a position"):
        encode_lattice(np.array([[1, 2, 3], [1, 2, 3]]), 0.01)
    with pytest.raises(ValueError, match="at most 2\\^21"):
        encode_lattice(np.array([[0, 0, 0], [1 << MAX_DEPTH, 0, 0]]), 0.01)


def test_grown_anchors_sit_on_the_lattice():
    """Growing places anchors at k * factor * v computed as the lattice coder rebuilds them,
    for any factor (not only powers of two)."""
    from baseline.scaffold.densify import grow_anchors
    from baseline.config import build_config
    from baseline.scaffold.build import build_model

    for init, hier in ((16, 4), (6, 3)):
        cfg = build_config(["demo"], [f"model.update_init_factor={init}",
                                      f"model.update_hierarchy_factor={hier}",
                                      "model.voxel_size=0.0173"])
        g = torch.Generator().manual_seed(0)
        pts = torch.rand(400, 3, generator=g) * 2
        model, v = build_model(cfg, pts)
        K = model.n_offsets
        with torch.no_grad():
            model.per_anchor["offsets"].normal_(0, 3, generator=g)
        n0 = model.n_anchors
        grads = torch.ones(n0 * K)
        added = grow_anchors(model, grads, torch.ones(n0 * K, dtype=torch.bool), cfg, v,
                             rand=lambda n: torch.ones(n))
        assert added > 0
        xyz = model.xyz.detach().numpy()
        k = lattice_coordinates(xyz, v)                       # raises if any is off the lattice
        assert np.array_equal(lattice_positions(k, v), xyz)


def test_it_beats_the_sorted_coder_on_anchor_like_sets():
    """Truck (-r 4, 166,565 anchors): 9.5 bits per anchor against the sorted coder's 15.0."""
    k = _surface(30000, 5)
    lat = 8 * len(encode_lattice(k, 0.01)[0]) / len(k)
    srt = 8 * len(encode_positions((k - k.min(0)).astype(np.uint16))[0]) / len(k)
    assert lat < 0.85 * srt, (lat, srt)


def test_damage_is_named_never_a_crash():
    k = _surface(600, 6)
    blob, _ = encode_lattice(k, 0.01)
    n = len(k)
    with pytest.raises(BitstreamError, match=f"holds {n} anchors, the header says {n + 1}"):
        decode_lattice(blob, n + 1)
    with pytest.raises(BitstreamError, match="not a lattice-position stream"):
        decode_lattice(b"XX" + blob[2:], n)
    bad_depth = blob[:6] + bytes([30]) + blob[7:]
    with pytest.raises(BitstreamError, match="octree depth 30"):
        decode_lattice(bad_depth, n)
    import struct
    bad_v = blob[:31] + struct.pack("<d", float("nan")) + blob[39:]
    with pytest.raises(BitstreamError, match="voxel size"):
        decode_lattice(bad_v, n)
    with pytest.raises(BitstreamError, match="did not use"):
        decode_lattice(blob + b"\0\0\0\1" * 2, n)    # one word lies in the look-ahead
    for cut in (0, 5, 20, len(blob) // 2, len(blob) - 4):
        with pytest.raises(BitstreamError):
            decode_lattice(blob[:cut], n)

    def parse(b):     # no CRC inside the section (the container has it): only no crash / hang
        out, _ = decode_lattice(b, n)
        assert out.shape == (n, 3)
        return None

    stats = fuzz_parser(parse, blob, n=300, seed=3)
    assert stats["error"] > 0


def test_position_coders_tool_ranks_the_coders():
    """tools/probes/position_coders.py: every coder round-trips (checked inside) and the lattice coder
    is the smallest on an anchor-like set."""
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "position_coders", pathlib.Path(__file__).parents[1] / "tools" / "probes" / "position_coders.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    xyz = lattice_positions(_surface(6000, 7), 0.02)
    rows = {name: b for name, b, _, _ in mod.coders(xyz, 0.02, repeat=1)}
    assert rows["raw16"] == 6 * len(xyz)
    assert rows["lattice"] < rows["sorted"] < rows["raw16"]
    assert not any("LOSSY" in name for name in rows)
