"""The decoder's gate: a ``.pgs`` header checked field by field before anything is allocated.

A container whose CRCs hold can still carry anything in its header (a tester can recompute
every CRC). :func:`check_header` refuses, with one :class:`BitstreamError` naming the key:

* every field of the wrong type, out of its range or above a hard cap (anchor count, Gaussians
  per anchor, attribute dims, grid layouts, network widths, coding options);
* a file whose sections do not belong to it: the header lists every section with a keyed digest
  (BLAKE2b-64 of the payload, keyed by the file's own id, itself a digest of the whole file's
  content), so a section copied from another file (its own CRC valid), a removed section or
  an added one is named;
* a decode whose planned allocation (computed from the checked header: anchors x the bytes each
  needs, hash-grid tables, networks bounded by their sections) exceeds the budget
  (:func:`memory_budget`: 128 x the file size + 256 MiB, or ``PGS_DECODE_MEMORY_MB``).

The config in the header is checked afterwards by the config's own validation (types, ranges,
finiteness: :func:`baseline.config.validate`), which bounds what it can make the decoder build.
"""
from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from typing import Any, Optional

from baseline.codec.container import BitstreamError

FILE_VERSION = 2           # the header's "file_version": 2 = sections bound by keyed digests
MAX_ANCHORS = 1 << 27
MAX_OFFSETS = 64
MAX_DIMS = 4096
MAX_HIDDEN = 4096
MAX_ATTRS = 64
MAX_CHUNK = 1 << 20
MAX_ESCAPE = 1 << 20        # symbols beyond it are stored raw; keeps the coder's alphabet small
MAX_GRID_LEVELS = 32
MAX_GRID_RES = 1 << 16
MAX_GRID_LOG2 = 24
MAX_GRID_FEATURES = 16
DIGEST_BYTES = 8
POSITION_CODINGS = ("raw16", "sorted", "lattice")
MASK_CODINGS = ("bernoulli", "patterns")
GRID_CODINGS = ("all", "used")
WEIGHT_DTYPES = ("float32", "float16")
# what a header without the field means (the encoder writes a coding only when it is not this)
CODING_DEFAULTS = {"weight_dtype": "float32", "position_coding": "raw16",
                   "mask_coding": "bernoulli", "grid_coding": "all"}


BINDING_FIELDS = ("file_version", "file_id", "section_digests")   # added by digest_sections


def file_id_of(header: dict, sections) -> str:
    """The id that keys a file's section digests: BLAKE2b-64 over the rest of its header and
    every section (so one model always encodes to the same bytes, and two files' ids differ
    whenever anything in them does)."""
    import json

    h = hashlib.blake2b(digest_size=DIGEST_BYTES)
    h.update(json.dumps(header, sort_keys=True, separators=(",", ":")).encode("utf-8"))
    for name, payload in sections:
        h.update(name.encode("utf-8") + b"\0" + len(payload).to_bytes(8, "little"))
        h.update(bytes(payload))
    return h.hexdigest()


def section_digest(file_id: str, payload: bytes) -> str:
    """BLAKE2b-64 of ``payload`` keyed by the file's id (hex)."""
    return hashlib.blake2b(bytes(payload), digest_size=DIGEST_BYTES,
                           key=bytes.fromhex(file_id)).hexdigest()


def digest_sections(header: dict, sections) -> dict:
    """Header fields binding ``[(name, payload)]`` to one file: ``file_version``, ``file_id``,
    ``section_digests``."""
    sections = list(sections)
    fid = file_id_of(header, sections)
    return {"file_version": FILE_VERSION, "file_id": fid,
            "section_digests": {n: section_digest(fid, p) for n, p in sections}}


def memory_budget(file_size: int, override: Optional[int] = None) -> int:
    """Bytes a decode may plan to allocate: ``override``, else ``PGS_DECODE_MEMORY_MB``, else
    128 x the file size + 256 MiB (decoded models measured at 30-60 x their file)."""
    if override is not None:
        return int(override)
    env = os.environ.get("PGS_DECODE_MEMORY_MB", "").strip()
    if env:
        try:
            mb = float(env)
        except ValueError:
            raise ValueError(f"PGS_DECODE_MEMORY_MB={env!r} is not a number of MiB") from None
        if not (mb > 0 and mb < float(1 << 40)):        # inf, nan, 0 and negatives refused
            raise ValueError(f"PGS_DECODE_MEMORY_MB={env!r} must be a finite number of MiB "
                             f"above 0")
        return int(mb * (1 << 20))
    return 128 * int(file_size) + (256 << 20)


@dataclass
class HeaderFacts:
    """What the decoder may rely on once :func:`check_header` passed."""
    n_anchors: int
    n_offsets: int
    bounds: tuple          # (lo [3], hi [3]) floats
    attrs: list            # [{"name", "dims", "q0", "masked"}]
    position_coding: str
    mask_coding: str
    grid_coding: str
    weight_dtype: str
    planned_bytes: int


# ------------------------------------------------------------------------------ primitives
def _err(key: str, msg: str) -> BitstreamError:
    return BitstreamError(f"header field '{key}': {msg}")


def _int(v: Any, key: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _err(key, f"expected an integer, got {type(v).__name__} {v!r:.60}")
    if not lo <= v <= hi:
        raise _err(key, f"{v} is out of range [{lo}, {hi}]")
    return v


def _num(v: Any, key: str, lo: float = -math.inf, hi: float = math.inf,
         positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(key, f"expected a number, got {type(v).__name__} {v!r:.60}")
    v = float(v)
    if not math.isfinite(v) or not lo <= v <= hi or (positive and v <= 0):
        raise _err(key, f"{v} is not a {'positive ' if positive else ''}finite number in "
                        f"[{lo}, {hi}]")
    return v


def _str(v: Any, key: str, choices=None) -> str:
    if not isinstance(v, str):
        raise _err(key, f"expected a string, got {type(v).__name__} {v!r:.60}")
    if choices is not None and v not in choices:
        raise _err(key, f"{v!r:.60} is not one of {', '.join(choices)}")
    return v


def _bool(v: Any, key: str) -> bool:
    if not isinstance(v, bool):
        raise _err(key, f"expected true/false, got {type(v).__name__} {v!r:.60}")
    return v


def _dict(v: Any, key: str) -> dict:
    if not isinstance(v, dict):
        raise _err(key, f"expected an object, got {type(v).__name__}")
    return v


def _list(v: Any, key: str, max_len: int) -> list:
    if not isinstance(v, list):
        raise _err(key, f"expected a list, got {type(v).__name__}")
    if len(v) > max_len:
        raise _err(key, f"{len(v)} entries, at most {max_len}")
    return v


# ------------------------------------------------------------------------------ grid layouts
GRID_KEYS = {"resolutions_3d", "log2_table_3d", "resolutions_2d", "log2_table_2d", "n_features",
             "planes", "init_range", "oob"}


def check_grid_options(g: Any, key: str) -> int:
    """A :class:`~baseline.hac.hashgrid.BinaryHashGrid` layout; returns its table entries
    (rows x features) so the caller can plan the allocation."""
    from baseline.hac.hashgrid import level_rows

    g = _dict(g, key)
    unknown = set(g) - GRID_KEYS
    if unknown:
        raise _err(key, f"unknown grid option(s) {sorted(unknown)}")
    r3 = [_int(r, f"{key}.resolutions_3d", 2, MAX_GRID_RES)
          for r in _list(g.get("resolutions_3d", []), f"{key}.resolutions_3d", MAX_GRID_LEVELS)]
    r2 = [_int(r, f"{key}.resolutions_2d", 2, MAX_GRID_RES)
          for r in _list(g.get("resolutions_2d", []), f"{key}.resolutions_2d", MAX_GRID_LEVELS)]
    l3 = _int(g.get("log2_table_3d", 13), f"{key}.log2_table_3d", 1, MAX_GRID_LOG2)
    l2 = _int(g.get("log2_table_2d", 15), f"{key}.log2_table_2d", 1, MAX_GRID_LOG2)
    nf = _int(g.get("n_features", 4), f"{key}.n_features", 1, MAX_GRID_FEATURES)
    planes = [_str(p, f"{key}.planes", ("xy", "xz", "yz"))
              for p in _list(g.get("planes", ["xy", "xz", "yz"]), f"{key}.planes", 3)]
    if len(set(planes)) != len(planes):
        raise _err(f"{key}.planes", "a plane is listed twice")
    if "init_range" in g:
        _num(g["init_range"], f"{key}.init_range", 0, 1e3)
    if "oob" in g:
        _str(g["oob"], f"{key}.oob", ("per_grid", "all"))
    if not r3 and not (r2 and planes):
        raise _err(key, "a grid needs at least one 3D level or one plane level")
    rows = sum(level_rows(r, 3, l3) for r in r3) + len(planes) * sum(level_rows(r, 2, l2)
                                                                       for r in r2)
    return rows * nf


# ------------------------------------------------------------------------------ the header
def check_header(header: dict, sections: dict, file_size: int,
                 max_bytes: Optional[int] = None) -> HeaderFacts:
    """Check every field the decoder reads (see the module docstring)."""
    from baseline.codec.model_codec import FORMAT

    if header.get("format") != FORMAT:
        raise _err("format", f"{header.get('format')!r:.60}, expected {FORMAT!r}")
    version = header.get("file_version")
    if version != FILE_VERSION:
        if version is None:
            raise BitstreamError("written by an older pgs (no section digests in the header): "
                                 "encode its run again with `pgs encode`")
        raise _err("file_version", f"{version!r:.60}; this reader reads version {FILE_VERSION}")
    _check_digests(header, sections)
    n = _int(header.get("n_anchors"), "n_anchors", 0, MAX_ANCHORS)
    k = _int(header.get("n_offsets"), "n_offsets", 1, MAX_OFFSETS)
    pb = _list(header.get("position_bounds"), "position_bounds", 2)
    if len(pb) != 2:
        raise _err("position_bounds", "expected [min, max]")
    lo = [_num(x, "position_bounds[0]", -3e38, 3e38)
          for x in _list(pb[0], "position_bounds[0]", 3)]
    hi = [_num(x, "position_bounds[1]", -3e38, 3e38)
          for x in _list(pb[1], "position_bounds[1]", 3)]
    if len(lo) != 3 or len(hi) != 3 or any(b <= a for a, b in zip(lo, hi)):
        raise _err("position_bounds", f"expected two [x, y, z] with min < max, got {pb!r:.120}")
    attrs = _check_attrs(header.get("attrs"), k, sections)
    names = [a["name"] for a in attrs]
    prov = _list(header.get("provider_attrs", []), "provider_attrs", MAX_ATTRS)
    for p in prov:
        if _str(p, "provider_attrs") not in names:
            raise _err("provider_attrs", f"{p!r:.60} is not a coded attribute")
    states = _dict(header.get("module_state", {}), "module_state")
    grid_entries = 0
    for name, st in states.items():
        st = _dict(st, f"module_state.{name}")
        if "grid" in st:
            grid_entries += check_grid_options(st["grid"], f"module_state.{name}.grid")
    grid_entries += _check_entropy(header.get("entropy"), attrs, k)
    wd, pc, mc, gc = (_str(header.get(f, CODING_DEFAULTS[f]), f, allowed) for f, allowed in (
        ("weight_dtype", WEIGHT_DTYPES), ("position_coding", POSITION_CODINGS),
        ("mask_coding", MASK_CODINGS), ("grid_coding", GRID_CODINGS)))
    if "scene" in header and header["scene"] is not None:
        _str(header["scene"], "scene")
    if "view_center" in header:
        vc = _list(header["view_center"], "view_center", 3)
        if len(vc) != 3:
            raise _err("view_center", "expected [x, y, z]")
        for x in vc:
            _num(x, "view_center", -3e38, 3e38)
    _dict(header.get("config"), "config")
    for sec in ("positions", "masks"):
        if sec not in sections:
            raise BitstreamError(f"missing section '{sec}'")
    if pc == "raw16" and len(sections["positions"]) != 6 * n:
        raise BitstreamError(f"section 'positions': {len(sections['positions'])} bytes, "
                             f"{n} anchors of 16-bit x, y, z need {6 * n}")
    # planned allocation: per anchor, positions (uint16, float64, float32), masks (uint8 and
    # two float32 copies), per-anchor parameters and the decoded values (float32, each held
    # twice at most), the feature cache; hash-grid tables as float32 plus their decoded bits
    dims = sum(a["dims"] for a in attrs)
    per_anchor = 4 * (12 + 3 * k + 2 * 3 * k + 2 * dims + 2 * MAX_FEATURE_GUESS)
    planned = n * per_anchor + 6 * grid_entries + 4 * file_size
    budget = memory_budget(file_size, max_bytes)
    if planned > budget:
        raise BitstreamError(
            f"decoding would allocate about {planned / 2 ** 20:.0f} MiB for {n} anchors "
            f"(header field 'n_anchors') and {grid_entries} hash-grid entries, more than the "
            f"{budget / 2 ** 20:.0f} MiB allowed for a {file_size}-byte file "
            f"(PGS_DECODE_MEMORY_MB raises the limit)")
    return HeaderFacts(n, k, (lo, hi), attrs, pc, mc, gc, wd, planned)


MAX_FEATURE_GUESS = 64     # the decoder features per anchor a plan counts (HAC 50)


def _check_digests(header: dict, sections: dict) -> None:
    fid = _str(header.get("file_id"), "file_id")
    if len(fid) != 16 or any(c not in "0123456789abcdef" for c in fid):
        raise _err("file_id", f"{fid!r:.60} is not 16 hex digits")
    dg = _dict(header.get("section_digests"), "section_digests")
    missing = [s for s in dg if s not in sections]
    if missing:
        raise BitstreamError(f"missing section(s) {missing} (listed in the header)")
    extra = [s for s in sections if s not in dg]
    if extra:
        raise BitstreamError(f"section(s) {extra} are not listed in the header (added to the "
                             f"file?)")
    for name, payload in sections.items():
        d = dg[name]
        if not isinstance(d, str) or section_digest(fid, payload) != d:
            raise BitstreamError(f"section '{name}' does not belong to this file (its digest "
                                 f"does not match the header's: copied from another file?)")
    # the id is content-derived: a header edited after writing (its CRC fixed) no longer
    # hashes to it, even where every section still matches its digest
    rest = {k: v for k, v in header.items() if k not in BINDING_FIELDS}
    if file_id_of(rest, list(sections.items())) != fid:
        raise BitstreamError("file_id: the header does not hash to the file's id (a header "
                             "field was edited after the file was written)")


def _check_attrs(v: Any, k: int, sections: dict) -> list:
    out, seen = [], set()
    for i, a in enumerate(_list(v, "attrs", MAX_ATTRS)):
        key = f"attrs[{i}]"
        a = _dict(a, key)
        name = _str(a.get("name"), f"{key}.name")
        if not name or name in seen:
            raise _err(f"{key}.name", f"empty or repeated name {name!r:.60}")
        seen.add(name)
        dims = _int(a.get("dims"), f"{key}.dims", 1, MAX_DIMS)
        q0 = _num(a.get("q0"), f"{key}.q0", 0, 1e30, positive=True)
        masked = _bool(a.get("masked", False), f"{key}.masked")
        if masked and dims % k:
            raise _err(f"{key}.dims", f"{dims} is not a multiple of n_offsets {k}")
        if name not in sections:
            raise BitstreamError(f"missing attribute section '{name}'")
        out.append({"name": name, "dims": dims, "q0": q0, "masked": masked})
    if not out:
        raise _err("attrs", "no coded attribute")
    return out


ENTROPY_KEYS = {"kind", "n_masks", "attrs", "hidden", "grid", "grid_options", "chunk",
                "escape_limit", "pipeline", "main", "n_chunks", "chunk_hidden"}


def _check_entropy(v: Any, attrs: list, k: int) -> int:
    """The entropy model's config; returns its hash-grid entries."""
    from baseline import registry

    e = _dict(v, "entropy")
    unknown = set(e) - ENTROPY_KEYS
    if unknown:
        raise _err("entropy", f"unknown option(s) {sorted(unknown)}")
    kind = _str(e.get("kind"), "entropy.kind")
    known = set(registry.names("entropy_model")) | {"hac", "factorized"}
    if kind not in known:
        raise _err("entropy.kind", f"{kind!r:.60} is not a known entropy model "
                                   f"({', '.join(sorted(known))})")
    if _int(e.get("n_masks"), "entropy.n_masks", 1, MAX_OFFSETS) != k:
        raise _err("entropy.n_masks", f"{e['n_masks']} differs from n_offsets {k}")
    ea = _list(e.get("attrs"), "entropy.attrs", MAX_ATTRS)
    want = [[a["name"], a["dims"], a["masked"]] for a in attrs]
    got = []
    for i, a in enumerate(ea):
        a = _list(a, f"entropy.attrs[{i}]", 4)
        if len(a) != 4:
            raise _err(f"entropy.attrs[{i}]", "expected [name, dims, q0, masked]")
        got.append([_str(a[0], f"entropy.attrs[{i}]"), _int(a[1], f"entropy.attrs[{i}]", 1, MAX_DIMS),
                    _bool(a[3], f"entropy.attrs[{i}]")])
        _num(a[2], f"entropy.attrs[{i}]", 0, 1e30, positive=True)
    if got != want:
        raise _err("entropy.attrs", "do not match the header's coded attributes")
    if "hidden" in e:
        _int(e["hidden"], "entropy.hidden", 1, MAX_HIDDEN)
    if "chunk" in e:
        _int(e["chunk"], "entropy.chunk", 1, MAX_CHUNK)
    if "escape_limit" in e:
        _int(e["escape_limit"], "entropy.escape_limit", 1, MAX_ESCAPE)
    if "pipeline" in e:
        _bool(e["pipeline"], "entropy.pipeline")
    if "main" in e and _str(e["main"], "entropy.main") not in [a["name"] for a in attrs]:
        raise _err("entropy.main", f"{e['main']!r:.60} is not a coded attribute")
    if "n_chunks" in e:
        _int(e["n_chunks"], "entropy.n_chunks", 1, 64)
    if "chunk_hidden" in e:
        _int(e["chunk_hidden"], "entropy.chunk_hidden", 1, MAX_HIDDEN)
    entries = 0
    for gk in ("grid", "grid_options"):
        if gk in e:
            entries += check_grid_options(e[gk], f"entropy.{gk}")
    if kind in ("hac", "hacpp") and not entries:
        raise _err("entropy.grid", "HAC's entropy model needs its grid layout")
    return entries
