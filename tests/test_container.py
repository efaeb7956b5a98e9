"""The .pgs container: round trip, and every kind of damage gives a BitstreamError naming it."""
import os
import struct
import zlib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from baseline.codec.container import (FORMAT_VERSION, MAGIC, BitstreamError, build_container,
                                      read_container, write_container)
from baseline.testing.fuzz import check_parse, fuzz_parser

HEADER = {"format": "pgs", "n_anchors": 1234, "bounds": [[-1.5, 0.25, 3.0], [2.0, 4.5, 9.0]],
          "attrs": [["feat", 50, 1.0, False]]}
SECTIONS = [("positions", bytes(range(256)) * 3), ("feat", b"\x01\x02\x03" * 50),
            ("empty", b""), ("mlp", os.urandom(300)), ("x" * 40, b"tail")]


def _layout(data):
    """Offsets of the file parts: (header start, header end, table start, table end, payload ends)."""
    hlen, nsec = struct.unpack_from("<II", data, 6)
    h0 = 14
    h1 = h0 + hlen
    t0 = h1 + 4
    off = t0
    lens = []
    for _ in range(nsec):
        (nl,) = struct.unpack_from("<H", data, off)
        off += 2 + nl
        plen, _ = struct.unpack_from("<QI", data, off)
        off += 12
        lens.append(plen)
    t1 = off + 4
    ends, p = [], t1
    for plen in lens:
        ends.append((p, p + plen))
        p += plen
    return h0, h1, t0, t1, ends


@pytest.fixture(scope="module")
def good():
    return build_container(HEADER, SECTIONS)


def test_round_trip_bytes_and_file(tmp_path, good):
    header, sections = read_container(good)
    assert header == HEADER
    assert list(sections.items()) == SECTIONS
    path = tmp_path / "m.pgs"
    n = write_container(path, HEADER, SECTIONS)
    assert n == path.stat().st_size == len(good)
    assert path.read_bytes() == good
    assert read_container(path) == (header, sections)
    assert [p.name for p in tmp_path.iterdir()] == ["m.pgs"]  # no temp file left


def test_write_is_atomic_on_failure(tmp_path):
    path = tmp_path / "m.pgs"
    write_container(path, HEADER, SECTIONS)
    with pytest.raises(ValueError):
        write_container(path, {"bad": float("nan")}, SECTIONS)
    assert read_container(path)[0] == HEADER  # the old file is intact
    assert [p.name for p in tmp_path.iterdir()] == ["m.pgs"]


def test_deterministic_and_duplicate_names_rejected():
    assert build_container(HEADER, SECTIONS) == build_container(dict(reversed(list(HEADER.items()))), SECTIONS)
    with pytest.raises(ValueError):
        build_container(HEADER, [("a", b""), ("a", b"1")])


def test_zero_length_and_wrong_magic(tmp_path, good):
    p = tmp_path / "empty.pgs"
    p.write_bytes(b"")
    with pytest.raises(BitstreamError, match="empty file"):
        read_container(p)
    with pytest.raises(BitstreamError, match="not a .pgs file"):
        read_container(b"PK\x03\x04" + good[4:])
    with pytest.raises(BitstreamError, match="not a .pgs file"):
        read_container(b"hello")
    with pytest.raises(BitstreamError, match="no such file"):
        read_container(tmp_path / "missing.pgs")


def test_wrong_version(good):
    bad = good[:4] + struct.pack("<H", FORMAT_VERSION + 1) + good[6:]
    with pytest.raises(BitstreamError, match=f"unsupported .pgs format version {FORMAT_VERSION + 1}"):
        read_container(bad)


def test_truncated_at_every_boundary(good):
    h0, h1, t0, t1, ends = _layout(good)
    names = [n for n, _ in SECTIONS]
    cuts = {1: "preamble", 3: "preamble", 4: "preamble", 10: "preamble", h0: "header", h0 + 5: "header",
            h1: "header", t0: "section table", t1 - 1: "section table"}
    for (start, end), name in zip(ends, names):
        if end < len(good):
            # cut exactly at the end of this section = at the start of the next one
            nxt = names[names.index(name) + 1]
            cuts[end] = f"section '{nxt}'" if ends[names.index(nxt)][1] > end else None
        if end > start:
            cuts[start + (end - start) // 2] = f"section '{name}'"
    for cut, where in cuts.items():
        with pytest.raises(BitstreamError, match="truncated") as ei:
            read_container(good[:cut])
        if where:
            assert where in str(ei.value), (cut, str(ei.value))


def test_truncated_at_every_offset(good):
    for cut in range(0, len(good)):
        with pytest.raises(BitstreamError):
            read_container(good[:cut])


def test_trailing_bytes(good):
    with pytest.raises(BitstreamError, match="unexpected bytes after the last section"):
        read_container(good + b"\x00")


@pytest.mark.parametrize("part", ["header", "section table"] + [n for n, p in SECTIONS if p])
def test_flipped_byte_names_the_part(good, part):
    h0, h1, t0, t1, ends = _layout(good)
    if part == "header":
        spans = [(h0, h1 + 4)]
    elif part == "section table":
        spans = [(t0, t1)]
    else:
        spans = [ends[[n for n, _ in SECTIONS].index(part)]]
    start, end = spans[0]
    for i in range(start, end, max(1, (end - start) // 17)):
        bad = bytearray(good)
        bad[i] ^= 0x20
        with pytest.raises(BitstreamError) as ei:
            read_container(bytes(bad))
        msg = str(ei.value)
        if part in ("header", "section table"):
            assert part in msg or "truncated" in msg or "absurd" in msg, msg
        else:
            assert f"CRC mismatch in section '{part}'" in msg


def test_flipped_preamble_fields(good):
    for i in range(4, 14):
        bad = bytearray(good)
        bad[i] ^= 0x01
        with pytest.raises(BitstreamError):
            read_container(bytes(bad))


def test_absurd_lengths_do_not_allocate(good):
    # header length 4 GiB - 1, section count 2^32 - 1, payload length 2^64 - 1
    bad = good[:6] + struct.pack("<I", 0xFFFFFFFF) + good[10:]
    with pytest.raises(BitstreamError, match="absurd header length"):
        read_container(bad)
    bad = good[:10] + struct.pack("<I", 0xFFFFFFFF) + good[14:]
    with pytest.raises(BitstreamError, match="absurd section count"):
        read_container(bad)
    # a valid table CRC over a huge payload length: only the length check can catch it
    h0, h1, t0, t1, ends = _layout(good)
    table = bytearray(good[t0:t1 - 4])
    nl = struct.unpack_from("<H", table, 0)[0]
    struct.pack_into("<Q", table, 2 + nl, 2 ** 64 - 1)
    bad = good[:t0] + bytes(table) + struct.pack("<I", zlib.crc32(bytes(table))) + good[t1:]
    with pytest.raises(BitstreamError, match="truncated in section 'positions'"):
        read_container(bad)


def test_random_mutations_fuzz(good):
    expect = read_container(good)
    stats = fuzz_parser(read_container, good, n=400, seed=1, expect=expect, time_limit=2.0)
    assert stats["error"] >= 390


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=2048))
def test_hypothesis_random_bytes(data):
    check_parse(read_container, data, time_limit=2.0)
    check_parse(read_container, MAGIC + data, time_limit=2.0)
    check_parse(read_container, MAGIC + struct.pack("<H", FORMAT_VERSION) + data, time_limit=2.0)


_GOOD = build_container(HEADER, SECTIONS)
_EXPECT = read_container(_GOOD)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(_GOOD) - 1), st.integers(0, 255)), min_size=1, max_size=8),
       st.integers(0, len(_GOOD)))
def test_hypothesis_mutations(edits, cut):
    b = bytearray(_GOOD)
    for i, v in edits:
        b[i] = v
    data = bytes(b[:cut])
    check_parse(read_container, data, expect=_EXPECT if data != _GOOD else None, time_limit=2.0)
    if data != _GOOD:
        with pytest.raises(BitstreamError):
            read_container(data)


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(st.text(max_size=8), st.one_of(st.integers(), st.text(max_size=20), st.booleans()),
                       max_size=6),
       st.lists(st.tuples(st.text(min_size=1, max_size=12), st.binary(max_size=64)), max_size=6,
                unique_by=lambda t: t[0]))
def test_hypothesis_round_trip(header, sections):
    data = build_container(header, sections)
    h, s = read_container(data)
    assert h == header and list(s.items()) == [(n, bytes(p)) for n, p in sections]


def test_readers_refuse_devices_and_oversized_files_before_reading(tmp_path, monkeypatch):
    """A device or an endless stream is never read (its size is checked first), nor a file over
    PGS_MAX_FILE_MB; the env values are parsed with ranges (inf, 0, negatives refused)."""
    from baseline.codec.container import BitstreamError, read_container, read_file_bytes
    from baseline.codec.header import memory_budget

    with pytest.raises(BitstreamError, match="/dev/zero: not a regular file"):
        read_container("/dev/zero")
    with pytest.raises(BitstreamError, match="is a directory"):
        read_file_bytes(tmp_path)
    f = tmp_path / "big.pgs"
    f.write_bytes(b"\0" * (3 << 20))
    monkeypatch.setenv("PGS_MAX_FILE_MB", "2")
    with pytest.raises(BitstreamError, match="above the 2097152-byte cap"):
        read_file_bytes(f)
    monkeypatch.setenv("PGS_MAX_FILE_MB", "4")
    assert len(read_file_bytes(f)) == 3 << 20
    for bad in ("inf", "nan", "0", "-5", "x"):
        monkeypatch.setenv("PGS_MAX_FILE_MB", bad)
        with pytest.raises(ValueError, match="PGS_MAX_FILE_MB"):
            read_file_bytes(f)
        monkeypatch.setenv("PGS_DECODE_MEMORY_MB", bad)
        with pytest.raises(ValueError, match="PGS_DECODE_MEMORY_MB"):
            memory_budget(1000)
    monkeypatch.setenv("PGS_DECODE_MEMORY_MB", "1.5")
    assert memory_budget(1000) == int(1.5 * (1 << 20))
