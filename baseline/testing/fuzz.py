"""Fuzzing helpers for bitstream parsers (usable from tests and by hand).

    from baseline.testing.fuzz import fuzz_parser
    stats = fuzz_parser(read_container, good_bytes, n=500, seed=0)

Each iteration applies one random mutation to a valid input (bit flip, byte overwrite,
truncation, insertion, deletion, duplication, a huge little-endian length written anywhere) and
calls the parser. The parser must either raise an allowed error (default
:class:`BitstreamError`) or, if ``expect`` is given, return exactly ``expect`` (a mutation that
changed nothing). Anything else — another exception type, a different result (a silently wrong
model), or a call slower than ``time_limit`` seconds (a hang) — fails with a reproducible
description (seed, iteration, mutation).
"""
from __future__ import annotations

import random
import struct
import time
from typing import Callable, List, Optional, Tuple

from baseline.codec.container import BitstreamError

MUTATIONS = ("flip", "byte", "truncate", "insert", "delete", "duplicate", "huge")


def mutate(data: bytes, rng: random.Random, kind: Optional[str] = None) -> Tuple[bytes, str]:
    """One random mutation of ``data``: (mutated bytes, description)."""
    kind = kind or rng.choice(MUTATIONS)
    n = len(data)
    b = bytearray(data)
    if n == 0:
        return bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 16))), "random (empty input)"
    i = rng.randrange(n)
    if kind == "flip":
        bit = rng.randrange(8)
        b[i] ^= 1 << bit
        return bytes(b), f"flip bit {bit} of byte {i}"
    if kind == "byte":
        v = rng.getrandbits(8)
        if v == b[i]:
            v ^= 0xFF
        b[i] = v
        return bytes(b), f"set byte {i} to {v}"
    if kind == "truncate":
        return bytes(b[:i]), f"truncate to {i} bytes"
    if kind == "insert":
        k = rng.randint(1, 16)
        return bytes(b[:i]) + bytes(rng.getrandbits(8) for _ in range(k)) + bytes(b[i:]), f"insert {k} bytes at {i}"
    if kind == "delete":
        k = rng.randint(1, min(16, n - i))
        return bytes(b[:i] + b[i + k:]), f"delete {k} bytes at {i}"
    if kind == "duplicate":
        k = rng.randint(1, min(64, n - i))
        return bytes(b[:i + k] + b[i:i + k] + b[i + k:]), f"duplicate {k} bytes at {i}"
    if kind == "huge":
        fmt = rng.choice(["<I", "<Q", "<H"])
        size = struct.calcsize(fmt)
        if n < size:
            return bytes(b[:-1]), "truncate by one"
        i = rng.randrange(n - size + 1)
        v = rng.choice([0, 1, 2 ** (8 * size) - 1, 2 ** (8 * size - 1), rng.getrandbits(8 * size)])
        b[i:i + size] = struct.pack(fmt, v)
        return bytes(b), f"write {fmt} {v} at {i}"
    raise ValueError(f"unknown mutation {kind!r}")


def check_parse(parse: Callable, data: bytes, allowed=(BitstreamError,), expect=None,
                time_limit: float = 5.0, what: str = "") -> str:
    """Parse ``data``; returns 'error' or 'ok'; raises AssertionError on any contract violation."""
    t0 = time.perf_counter()
    try:
        result = parse(data)
        status = "ok"
    except allowed:
        status = "error"
    except Exception as e:  # noqa: BLE001 - that is the point
        raise AssertionError(f"{what}: parser raised {type(e).__name__}: {e}") from e
    dt = time.perf_counter() - t0
    if dt > time_limit:
        raise AssertionError(f"{what}: parser took {dt:.2f} s (limit {time_limit} s)")
    if status == "ok" and expect is not None and result != expect:
        raise AssertionError(f"{what}: damaged input parsed into a different result")
    return status


def fuzz_parser(parse: Callable, data: bytes, n: int = 200, seed: int = 0, allowed=(BitstreamError,),
                expect=None, time_limit: float = 5.0, kinds: Optional[List[str]] = None) -> dict:
    """Run ``n`` random single mutations of ``data`` through ``parse``; returns counts."""
    rng = random.Random(seed)
    stats = {"error": 0, "ok": 0}
    for it in range(n):
        kind = rng.choice(kinds) if kinds else None
        mutated, desc = mutate(data, rng, kind)
        status = check_parse(parse, mutated, allowed, expect if mutated != data else None, time_limit,
                             what=f"seed {seed} iteration {it} ({desc})")
        if status == "ok" and expect is not None and mutated != data:
            # accepted only if the parse equals the original (checked in check_parse)
            pass
        stats[status] += 1
    return stats
