"""Typed checks of a ``.pgs`` header's fields: each raises one
:class:`~baseline.codec.container.BitstreamError` naming the field. The header's own checks
(:mod:`baseline.codec.header`) and every component's (``check_header`` /
``check_codec_state``) use them, so a bad field reads the same wherever it is caught."""
from __future__ import annotations

import math
from typing import Any

from baseline.codec.container import BitstreamError


def header_error(key: str, msg: str) -> BitstreamError:
    return BitstreamError(f"header field '{key}': {msg}")


def int_field(v: Any, key: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise header_error(key, f"expected an integer, got {type(v).__name__} {v!r:.60}")
    if not lo <= v <= hi:
        raise header_error(key, f"{v} is out of range [{lo}, {hi}]")
    return v


def num_field(v: Any, key: str, lo: float = -math.inf, hi: float = math.inf,
              positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise header_error(key, f"expected a number, got {type(v).__name__} {v!r:.60}")
    v = float(v)
    if not math.isfinite(v) or not lo <= v <= hi or (positive and v <= 0):
        raise header_error(key, f"{v} is not a {'positive ' if positive else ''}finite number in "
                                f"[{lo}, {hi}]")
    return v


def str_field(v: Any, key: str, choices=None) -> str:
    if not isinstance(v, str):
        raise header_error(key, f"expected a string, got {type(v).__name__} {v!r:.60}")
    if choices is not None and v not in choices:
        raise header_error(key, f"{v!r:.60} is not one of {', '.join(choices)}")
    return v


def bool_field(v: Any, key: str) -> bool:
    if not isinstance(v, bool):
        raise header_error(key, f"expected true/false, got {type(v).__name__} {v!r:.60}")
    return v


def dict_field(v: Any, key: str) -> dict:
    if not isinstance(v, dict):
        raise header_error(key, f"expected an object, got {type(v).__name__}")
    return v


def list_field(v: Any, key: str, max_len: int) -> list:
    if not isinstance(v, list):
        raise header_error(key, f"expected a list, got {type(v).__name__}")
    if len(v) > max_len:
        raise header_error(key, f"{len(v)} entries, at most {max_len}")
    return v


def unknown_keys(entry: dict, allowed, key: str, what: str = "option") -> None:
    unknown = set(entry) - set(allowed)
    if unknown:
        raise header_error(key, f"unknown {what}(s) {sorted(unknown)}")
