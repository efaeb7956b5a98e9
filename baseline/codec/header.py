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

Each component checks its own fields: the entropy model its entry (``check_header`` of the class
the header's ``entropy.kind`` names in the registry), the feature provider and refiner their
``module_state`` (``check_codec_state`` of the classes the header's config names).

The config in the header is checked afterwards by the config's own validation (types, ranges,
finiteness: :func:`baseline.config.validate`), which bounds what it can make the decoder build.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from typing import Any, Optional

from baseline import registry
from baseline.codec.container import BitstreamError
from baseline.codec.fields import (bool_field, dict_field, header_error, int_field, list_field,
                                   num_field, str_field)
from baseline.codec.format import (CODING_DEFAULTS, DIGEST_BYTES, FILE_VERSION, FORMAT,
                                   GRID_CODINGS, MASK_CODINGS, MAX_ANCHORS, MAX_ATTRS, MAX_DIMS,
                                   MAX_FEATURE_GUESS, MAX_OFFSETS, POSITION_CODINGS, WEIGHT_DTYPES)

BINDING_FIELDS = ("file_version", "file_id", "section_digests")   # added by digest_sections


def file_id_of(header: dict, sections) -> str:
    """The id that keys a file's section digests: BLAKE2b-64 over the rest of its header and
    every section (so one model always encodes to the same bytes, and two files' ids differ
    whenever anything in them does)."""
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


# ------------------------------------------------------------------------------ the header
def check_header(header: dict, sections: dict, file_size: int,
                 max_bytes: Optional[int] = None) -> HeaderFacts:
    """Check every field the decoder reads (see the module docstring)."""
    if header.get("format") != FORMAT:
        raise header_error("format", f"{header.get('format')!r:.60}, expected {FORMAT!r}")
    version = header.get("file_version")
    if version != FILE_VERSION:
        if version is None:
            raise BitstreamError("written by an older pgs (no section digests in the header): "
                                 "encode its run again with `pgs encode`")
        raise header_error("file_version", f"{version!r:.60}; this reader reads version "
                                           f"{FILE_VERSION}")
    _check_digests(header, sections)
    n = int_field(header.get("n_anchors"), "n_anchors", 0, MAX_ANCHORS)
    k = int_field(header.get("n_offsets"), "n_offsets", 1, MAX_OFFSETS)
    pb = list_field(header.get("position_bounds"), "position_bounds", 2)
    if len(pb) != 2:
        raise header_error("position_bounds", "expected [min, max]")
    lo = [num_field(x, "position_bounds[0]", -3e38, 3e38)
          for x in list_field(pb[0], "position_bounds[0]", 3)]
    hi = [num_field(x, "position_bounds[1]", -3e38, 3e38)
          for x in list_field(pb[1], "position_bounds[1]", 3)]
    if len(lo) != 3 or len(hi) != 3 or any(b <= a for a, b in zip(lo, hi)):
        raise header_error("position_bounds", f"expected two [x, y, z] with min < max, got "
                                              f"{pb!r:.120}")
    attrs = _check_attrs(header.get("attrs"), k, sections)
    names = [a["name"] for a in attrs]
    prov = list_field(header.get("provider_attrs", []), "provider_attrs", MAX_ATTRS)
    for p in prov:
        if str_field(p, "provider_attrs") not in names:
            raise header_error("provider_attrs", f"{p!r:.60} is not a coded attribute")
    config = dict_field(header.get("config"), "config")
    grid_entries = _check_module_states(header.get("module_state", {}), config)
    grid_entries += _check_entropy(header.get("entropy"), attrs, k)
    wd, pc, mc, gc = (str_field(header.get(f, CODING_DEFAULTS[f]), f, allowed)
                      for f, allowed in (("weight_dtype", WEIGHT_DTYPES),
                                         ("position_coding", POSITION_CODINGS),
                                         ("mask_coding", MASK_CODINGS),
                                         ("grid_coding", GRID_CODINGS)))
    if "scene" in header and header["scene"] is not None:
        str_field(header["scene"], "scene")
    if "view_center" in header:
        vc = list_field(header["view_center"], "view_center", 3)
        if len(vc) != 3:
            raise header_error("view_center", "expected [x, y, z]")
        for x in vc:
            num_field(x, "view_center", -3e38, 3e38)
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


def _check_digests(header: dict, sections: dict) -> None:
    fid = str_field(header.get("file_id"), "file_id")
    if len(fid) != 16 or any(c not in "0123456789abcdef" for c in fid):
        raise header_error("file_id", f"{fid!r:.60} is not 16 hex digits")
    dg = dict_field(header.get("section_digests"), "section_digests")
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
    for i, a in enumerate(list_field(v, "attrs", MAX_ATTRS)):
        key = f"attrs[{i}]"
        a = dict_field(a, key)
        name = str_field(a.get("name"), f"{key}.name")
        if not name or name in seen:
            raise header_error(f"{key}.name", f"empty or repeated name {name!r:.60}")
        seen.add(name)
        dims = int_field(a.get("dims"), f"{key}.dims", 1, MAX_DIMS)
        q0 = num_field(a.get("q0"), f"{key}.q0", 0, 1e30, positive=True)
        masked = bool_field(a.get("masked", False), f"{key}.masked")
        if masked and dims % k:
            raise header_error(f"{key}.dims", f"{dims} is not a multiple of n_offsets {k}")
        if name not in sections:
            raise BitstreamError(f"missing attribute section '{name}'")
        out.append({"name": name, "dims": dims, "q0": q0, "masked": masked})
    if not out:
        raise header_error("attrs", "no coded attribute")
    return out


# module_state entry -> (registry kind, the config's model key that names the component)
MODULE_COMPONENTS = {"provider": ("feature_provider", "feature_provider"),
                     "refiner": ("refiner", "refiner")}


def _component(config: dict, kind: str, key: str):
    """The class the header's config names for ``kind`` (``config.model.<key>``)."""
    model = dict_field(config.get("model"), "config.model")
    name = str_field(model.get(key), f"config.model.{key}")
    if name not in registry.names(kind):
        raise header_error(f"config.model.{key}", f"{name!r:.60} is not a registered {kind} "
                                                  f"(is the plugin that wrote this file "
                                                  f"installed?)")
    return registry.component_class(kind, name)


def _check_module_states(v: Any, config: dict) -> int:
    """Each module's construction state, checked by its own class; returns their hash-grid
    entries."""
    entries = 0
    for name, st in dict_field(v, "module_state").items():
        key = f"module_state.{name}"
        if name not in MODULE_COMPONENTS:
            raise header_error(key, f"no such module (known: {', '.join(MODULE_COMPONENTS)})")
        entries += _component(config, *MODULE_COMPONENTS[name]).check_codec_state(st, key)
    return entries


def _check_entropy(v: Any, attrs: list, k: int) -> int:
    """The entropy model's entry: its kind, masks and attributes here, its own options by its
    class (``check_header``); returns its hash-grid entries."""
    e = dict_field(v, "entropy")
    kind = str_field(e.get("kind"), "entropy.kind")
    known = registry.names("entropy_model")
    if kind not in known:
        raise header_error("entropy.kind", f"{kind!r:.60} is not a known entropy model "
                                           f"({', '.join(known)})")
    if int_field(e.get("n_masks"), "entropy.n_masks", 1, MAX_OFFSETS) != k:
        raise header_error("entropy.n_masks", f"{e['n_masks']} differs from n_offsets {k}")
    ea = list_field(e.get("attrs"), "entropy.attrs", MAX_ATTRS)
    want = [[a["name"], a["dims"], a["masked"]] for a in attrs]
    got = []
    for i, a in enumerate(ea):
        a = list_field(a, f"entropy.attrs[{i}]", 4)
        if len(a) != 4:
            raise header_error(f"entropy.attrs[{i}]", "expected [name, dims, q0, masked]")
        got.append([str_field(a[0], f"entropy.attrs[{i}]"),
                    int_field(a[1], f"entropy.attrs[{i}]", 1, MAX_DIMS),
                    bool_field(a[3], f"entropy.attrs[{i}]")])
        num_field(a[2], f"entropy.attrs[{i}]", 0, 1e30, positive=True)
    if got != want:
        raise header_error("entropy.attrs", "do not match the header's coded attributes")
    return registry.component_class("entropy_model", kind).check_header(e, "entropy")
