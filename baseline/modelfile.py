"""Encode a trained anchor model into one self-contained ``.pgs`` file, decode it back.

Sections (each with length + CRC32 in the container, :mod:`baseline.codec.container`):
    positions            anchor positions, 16-bit (HAC's widened bounds in the header): raw
                         uint16 [N,3] (codec.positions = "raw16", HAC's layout) or coded as a
                         set ("sorted", baseline/codec/positions.py; the anchors of every other
                         section then follow the positions' Morton order); or the exact
                         voxel-lattice coordinates, octree-coded with the voxel size ("lattice",
                         baseline/codec/lattice.py; the anchors follow the octree's leaf order)
    masks                Gaussian masks [N,K]: Bernoulli-coded with one global p
                         (codec.masks = "bernoulli", HAC's) or each anchor's K bits as one
                         symbol ("patterns", baseline/codec/masks.py)
    em.grid / em.mlp     the entropy model (binary hash grid, context MLP + grid bounds); the
                         grids hold every entry (codec.grids = "all", HAC's) or only those the
                         decoded anchors read ("used", BinaryHashGrid.used_values)
    decoder.weights      the opacity / covariance / colour MLPs
    provider.*           what the feature provider owns (its hash grids and networks, if any)
    refiner.weights      the refiner's networks
    <attribute>          each coded attribute (feat or residual, scaling, offsets), range coded

Only valid anchors (any Gaussian mask on) are stored. Network weights are rounded to the stored
precision (``codec.weight_dtype``) before anything is coded, so the encoder's probabilities and
renders are the decoder's. The reported size is the file's byte count.

Size groups (``pgs info``): ``feature`` = the provider's own coded attribute(s) and every section
the provider owns (HAC: feat; a predicting provider: its grid, networks and residual), as
predictive methods' papers split their sizes; the rest is split into anchor, scaling, offsets, hash, masks, mlps, header.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.nn as nn

from baseline import registry
from baseline.codec.container import BitstreamError, read_container_sized, write_container
from baseline.codec.format import CODING_DEFAULTS, FORMAT, GRID_CODINGS
from baseline.codec.header import check_header, digest_sections, memory_budget
from baseline.codec.masks import decode_mask_patterns, encode_mask_patterns, mask_pattern_counts
from baseline.codec.lattice import (decode_lattice, encode_lattice, lattice_coordinates,
                                    lattice_positions)
from baseline.codec.positions import decode_positions, encode_positions
from baseline.codec.rangecoder import (anchor_bounds, bernoulli_counts, decode_bernoulli,
                                       dequantize_positions, encode_bernoulli, pack_positions,
                                       quantize_positions, unpack_positions)
from baseline.codec.weights import (declare_precision, expect_precision, pack_state_dict,
                                    round_module_, unpack_state_dict)
from baseline.config import ConfigError, apply_overlay, default_config, to_dict, validate
from baseline.contracts import feature_cache
from baseline.hac.entropy import build_entropy_model
from baseline.hac.hashgrid import BinaryHashGrid
from baseline.memory import AllocationError, describe, is_allocation_failure
from baseline.scaffold.model import AnchorModel, check_bounds
MODEL_FILE = "model.pgs"      # a run folder's encoded model
CODER_FLOOR = 2.0 ** -24     # the least probability constriction's leaky quantizer gives a bin
MASK_LOGIT = 20.0      # decoded masks as logits: sigmoid(+-20) is unambiguously on / off


def _grid_modules(module: nn.Module):
    return [(n, m) for n, m in module.named_modules() if isinstance(m, BinaryHashGrid)]


def _module_sections(prefix: str, module: nn.Module, precision: str,
                     used_xyz=None) -> list[tuple[str, bytes]]:
    """Binary grids of ``module`` as Bernoulli-coded sections (with ``used_xyz``: only the
    entries those positions read), everything else as weights."""
    out = []
    grids = _grid_modules(module)
    exclude = []
    for name, g in grids:
        used = None if used_xyz is None else g.used_values(used_xyz)
        out.append((f"{prefix}.{name or 'grid'}", g.encode_bits(used)))
        exclude.append(f"{name}.grids." if name else "grids.")
    bounds = [f"{n}.{b}" if n else b for n, _ in grids for b in ("xyz_min", "xyz_max")]
    round_module_(module, precision, keep=bounds)      # bounds stay float32: they index the grid
    blob = pack_state_dict(module.state_dict(), precision, exclude=exclude, keep=bounds)
    out.append((f"{prefix}.weights", blob))
    return out


def _has_state(provider) -> bool:
    """Whether a feature provider owns networks or grids, coded as ``provider.*`` sections (the
    explicit feature table owns none: its values are a coded attribute)."""
    return any(p.numel() for p in provider.parameters()) or bool(_grid_modules(provider))


def _module_states(model) -> dict:
    """Construction state that plugged-in modules keep in the header (``codec_state()``, JSON):
    what the decoder needs besides the config, e.g. a grid layout sized during training."""
    states = {name: mod.codec_state() for name, mod in (("provider", model.provider),
                                                         ("refiner", model.refiner))
              if mod is not None}
    return {name: st for name, st in states.items() if st is not None}


def _factory(cls, cfg, state):
    """``cls(model, cfg)``, or ``cls(model, cfg, codec_state=state)`` when the file has one."""
    if cls is None:
        return None
    if state is None:
        return lambda m: cls(m, cfg)
    return lambda m: cls(m, cfg, codec_state=state)


def _load_module_sections(prefix: str, module: nn.Module, sections: dict, used_xyz=None) -> None:
    grids = _grid_modules(module)
    key = f"{prefix}.weights"
    if key not in sections:
        raise BitstreamError(f"missing section '{key}'")
    sd = unpack_state_dict(sections[key], what=f"section '{key}'")
    try:
        missing, unexpected = module.load_state_dict(sd, strict=False)
    except RuntimeError as e:
        raise BitstreamError(f"section '{key}' does not fit the model: {e}") from None
    grid_names = tuple(f"{n}.grids." if n else "grids." for n, _ in grids)
    missing = [m for m in missing if not m.startswith(grid_names)]
    if missing or unexpected:
        raise BitstreamError(f"section '{key}' does not fit the model: missing {missing}, "
                             f"unexpected {unexpected}")
    for name, g in grids:
        sec = f"{prefix}.{name or 'grid'}"
        if sec not in sections:
            raise BitstreamError(f"missing section '{sec}'")
        try:
            g.decode_bits(sections[sec], None if used_xyz is None else g.used_values(used_xyz))
        except ValueError as e:          # BitstreamError included: name the section
            raise BitstreamError(f"section '{sec}': {e}") from None


@torch.no_grad()
def encode_model(cfg, model, entropy, path: str | Path, extra_header: Optional[dict] = None,
                 scene_bounds: tuple | None = None) -> dict:
    """Write ``model`` (+ its entropy model) to ``path``; returns stats incl. per-section bytes.

    Rounds the live networks to the stored precision (in place). Refused first (nothing
    written) when its anchors, scales or offsets are non-finite or, given the scene's
    ``scene_bounds`` ``(centre [3], extent)`` (:func:`baseline.data.scene.scene_bounds`), far
    outside it (:func:`baseline.scaffold.model.check_bounds`).
    """
    check_bounds(model, f"encoding {path}", *(scene_bounds or ()))

    t0 = time.perf_counter()
    precision = cfg.codec.weight_dtype
    K = model.n_offsets
    valid = model.anchor_valid()
    idx = valid.nonzero()[:, 0]
    N = int(len(idx))
    xyz = model.xyz.detach()[idx]
    # a run trained at its 16-bit positions stores those: its box, not the coded anchors'
    lo, hi = model.position_box or anchor_bounds(xyz.cpu().numpy())
    q = quantize_positions(xyz.cpu().numpy(), lo, hi)
    coding = cfg.codec.positions
    if coding == "sorted":        # the anchors are coded in the order the positions decode in
        pos_blob, order = encode_positions(q)
        order_t = torch.from_numpy(order).to(idx.device)
        idx, q = idx[order_t], q[order]
        xyz_q = torch.from_numpy(dequantize_positions(q, lo, hi))
    elif coding == "raw16":
        pos_blob = pack_positions(q)
        xyz_q = torch.from_numpy(dequantize_positions(q, lo, hi))
    elif coding == "lattice":     # exact positions; the anchors follow the octree's order
        if not model.voxel_size:
            raise ValueError("codec.positions 'lattice' needs the model's voxel size "
                             "(model.voxel_size is not set)")
        k = lattice_coordinates(xyz.cpu().numpy(), model.voxel_size)
        pos_blob, order = encode_lattice(k, model.voxel_size)
        idx = idx[torch.from_numpy(order).to(idx.device)]
        xyz_q = torch.from_numpy(lattice_positions(k[order], model.voxel_size))
    else:
        raise ValueError(f"codec.positions: unknown coding {coding!r}")
    gmask = (torch.sigmoid(model.per_anchor["mask"].detach()[idx][..., 0]) > model.mask_threshold)
    mask_coding = cfg.codec.masks
    if mask_coding == "patterns":
        mask_blob = encode_mask_patterns(gmask.numpy().astype(np.uint8))
    elif mask_coding == "bernoulli":
        mask_blob = encode_bernoulli(gmask.numpy().astype(np.uint8))
    else:
        raise ValueError(f"codec.masks: unknown coding {mask_coding!r}")
    sections: list[tuple[str, bytes]] = [("positions", pos_blob), ("masks", mask_blob)]
    grid_coding = cfg.codec.grids
    if grid_coding not in GRID_CODINGS:
        raise ValueError(f"codec.grids: unknown coding {grid_coding!r}")
    used_xyz = xyz_q if grid_coding == "used" else None
    em = entropy.serialize(precision, used_xyz=used_xyz)   # rounds its weights first
    sections += [(f"em.{k}", v) for k, v in em.items()]
    sections += _module_sections("decoder", model.decoder, precision)
    if _has_state(model.provider):
        sections += _module_sections("provider", model.provider, precision, used_xyz)
    if model.refiner is not None:
        sections += _module_sections("refiner", model.refiner, precision)
    values = model.coded_values(idx)
    blobs, vq = entropy.compress(xyz_q, values, gmask.float(), return_values=True)
    attrs = model.coded_attributes()
    sections += [(a.name, blobs[a.name]) for a in attrs]
    provider_attrs = [a.name for a in attrs if a.name in model.provider.coded_values(idx[:0])]
    header = {
        "format": FORMAT,
        "config": to_dict(cfg),
        "n_anchors": N,
        "n_offsets": K,
        "position_bounds": [lo.tolist(), hi.tolist()],
        "attrs": [dataclasses.asdict(a) for a in attrs],
        "provider_attrs": provider_attrs,
        "module_state": _module_states(model),
        "entropy": entropy.config(),
        "weight_dtype": precision,
    }
    if coding != "raw16":         # files without the key are raw16 (all files before it existed)
        header["position_coding"] = coding
    if mask_coding != "bernoulli":        # likewise
        header["mask_coding"] = mask_coding
    if grid_coding != "all":
        header["grid_coding"] = grid_coding
    if extra_header:
        header.update(extra_header)
    header.update(digest_sections(header, sections))      # binds every section to this file
    size = write_container(path, header, sections)
    return {"bytes": size, "anchors": N, "encode_s": time.perf_counter() - t0,
            "sections": {n: len(b) for n, b in sections}, "values": vq, "xyz_q": xyz_q,
            "index": idx}


@torch.no_grad()
def rate_check(model, entropy, stats: dict) -> list[dict]:
    """The training loss's bit estimate beside the bytes :func:`encode_model` wrote.

    One row per coded attribute (the entropy model's estimate with rounding, on the anchors and
    masks the encoder coded) and per binary hash grid (the hash-bit estimate of the rate loss),
    ``{"section", "estimated_bytes", "written_bytes"}``. Call it right after ``encode_model``
    with its ``stats``: the networks are then at the stored precision, as in the file.
    """
    idx, xyz_q, written = stats["index"], stats["xyz_q"], stats["sections"]
    gmask = (torch.sigmoid(model.per_anchor["mask"].detach()[idx][..., 0]) > model.mask_threshold)
    est = entropy.estimate_bits(xyz_q, model.coded_values(idx), gmask.float())
    rows = [(name, bits) for name, bits in est.items()]
    rows += [(f"em.{name}", float(g.hash_bits())) for name, g in _grid_modules(entropy)]
    rows += [(f"provider.{name or 'grid'}", float(g.hash_bits())) for name, g in _grid_modules(model.provider)]
    return [{"section": n, "estimated_bytes": b / 8.0, "written_bytes": int(written[n])}
            for n, b in rows if n in written]


def format_rate_check(rows: list[dict]) -> str:
    lines = ["rate check: the training loss's estimate vs the bytes written",
             f"{'section':<22}{'estimated B':>14}{'written B':>12}{'written/est':>13}"]
    for r in rows:
        ratio = r["written_bytes"] / r["estimated_bytes"] if r["estimated_bytes"] > 0 else float("nan")
        lines.append(f"{r['section']:<22}{r['estimated_bytes']:>14.0f}{r['written_bytes']:>12d}{ratio:>13.4f}")
    return "\n".join(lines)


@dataclasses.dataclass
class DecodedModel:
    cfg: object
    model: object
    header: dict
    decode_s: float
    entropy: object = None          # the file's entropy model (its probabilities: coded_bits)

    @property
    def scene_path(self) -> Optional[str]:
        return self.header.get("scene")


@torch.no_grad()
def decode_model(path: str | Path, max_bytes: Optional[int] = None) -> DecodedModel:
    """Rebuild the model from a ``.pgs`` file alone.

    Every failure is one :class:`BitstreamError` naming the file and the section or header
    field: the header is checked field by field and against the sections (their keyed digests
    bind them to this file) before anything is allocated, and the planned allocation against
    ``max_bytes`` (default :func:`baseline.codec.header.memory_budget`). An allocation that
    fails all the same (a budget raised beyond the machine, an address-space limit) is one
    :class:`baseline.memory.AllocationError` naming the file, the size, the plan and budget.
    """
    plan: dict = {}
    try:
        with expect_precision(None):          # declared once the header is read
            return _decode_model(path, max_bytes, plan)
    except BitstreamError as e:
        msg = str(e)
        raise BitstreamError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except (MemoryError, RuntimeError) as e:
        if isinstance(e, AllocationError) or not is_allocation_failure(e):
            raise
        what = f"decoding {path}" + (f" ({plan['n']} anchors)" if "n" in plan else "")
        raise AllocationError(describe(what, e, plan.get("planned"), plan.get("budget"),
                                       "PGS_DECODE_MEMORY_MB sets it")) from None


def _decode_model(path, max_bytes, plan: dict) -> DecodedModel:

    t0 = time.perf_counter()
    header, sections, size = read_container_sized(path)
    facts = check_header(header, sections, size, max_bytes)
    plan.update(n=facts.n_anchors, planned=facts.planned_bytes,
                budget=memory_budget(size, max_bytes))
    declare_precision(facts.weight_dtype)
    N, K = facts.n_anchors, facts.n_offsets
    lo, hi = (np.asarray(b, dtype=np.float32) for b in facts.bounds)
    cfg_dict = dict(header["config"])
    ent_cfg = header["entropy"]
    states = dict(header.get("module_state", {}))
    cfg = default_config()
    patches = cfg_dict.pop("patches", [])
    if not isinstance(patches, list) or not all(isinstance(x, str) for x in patches):
        raise BitstreamError("header field 'config.patches': expected a list of names")
    cfg.patches = list(patches)
    try:
        apply_overlay(cfg, cfg_dict, "the header's config")
        validate(cfg)
    except ConfigError as e:
        hint = (" (is the plugin that wrote this file installed?)" if "unknown" in str(e)
                else "")
        raise BitstreamError(f"header field 'config': {e}{hint}") from None
    if cfg.model.n_offsets != K:
        raise BitstreamError(f"header field 'config.model.n_offsets' ({cfg.model.n_offsets}) "
                             f"differs from 'n_offsets' ({K})")
    try:
        prov_cls = registry.get("feature_provider", cfg.model.feature_provider)
        ref_cls = (None if cfg.model.refiner in ("", "none")
                   else registry.get("refiner", cfg.model.refiner))
    except KeyError as e:
        raise BitstreamError(f"header field 'config.model': {e.args[0] if e.args else e} "
                             f"(is the plugin that wrote this file installed?)") from None
    coding = facts.position_coding
    voxel = None
    if coding == "lattice":
        k, voxel = decode_lattice(sections["positions"], N)
        xyz = torch.from_numpy(lattice_positions(k, voxel))
    else:
        if coding == "sorted":
            q = decode_positions(sections["positions"], N)
        else:
            q = unpack_positions(sections["positions"], N)
        xyz = torch.from_numpy(dequantize_positions(q, lo, hi))
    if facts.mask_coding == "patterns":
        gm = decode_mask_patterns(sections["masks"], N, K)
    else:
        gm = decode_bernoulli(sections["masks"], expected_n=N * K, what="section 'masks'")
    gmask = torch.from_numpy(np.asarray(gm, dtype=np.float32).reshape(N, K))
    try:
        model = AnchorModel(xyz, torch.zeros(N, 6), cfg.model,
                            provider_factory=_factory(prov_cls, cfg, states.get("provider")),
                            refiner_factory=_factory(ref_cls, cfg, states.get("refiner")),
                            mask_threshold=cfg.entropy.mask_threshold)
    except (ValueError, TypeError, KeyError) as e:
        raise BitstreamError(f"header field 'module_state' does not fit the modules: {e}") from None
    model.voxel_size = voxel
    attrs = [a["name"] for a in facts.attrs]
    want = [(a.name, a.dims, a.masked) for a in model.coded_attributes()]
    if want != [(a["name"], a["dims"], a["masked"]) for a in facts.attrs]:
        raise BitstreamError(f"header field 'attrs' ({attrs}) does not match what the "
                             f"configured model codes ({[w[0] for w in want]})")
    used_xyz = xyz if facts.grid_coding == "used" else None
    overrides = {}
    if ent_cfg.get("context") == "provider":      # the context is the provider's grid
        grid = model.provider.context_grid()
        if grid is None:
            raise BitstreamError("header field 'entropy.context': the entropy model reads the "
                                 "feature provider's grid, and this file's provider has none")
        overrides["grid"] = grid
    try:
        entropy = build_entropy_model(ent_cfg, **overrides)
    except (ValueError, TypeError, KeyError) as e:
        raise BitstreamError(f"header field 'entropy' does not build a model: {e}") from None
    em = {k[3:]: v for k, v in sections.items() if k.startswith("em.")}
    entropy.load_serialized(em, used_xyz=used_xyz)
    _load_module_sections("decoder", model.decoder, sections)
    if _has_state(model.provider):
        _load_module_sections("provider", model.provider, sections, used_xyz)
    elif any(n.startswith("provider.") for n in sections):
        raise BitstreamError("provider sections in a file whose feature provider has none")
    if model.refiner is not None:
        _load_module_sections("refiner", model.refiner, sections)
        model.refiner.active = True
    elif any(n.startswith("refiner.") for n in sections):
        raise BitstreamError("refiner sections in a file whose config has no refiner")
    values = entropy.decompress(xyz, {a: sections[a] for a in attrs}, gmask, n=N)
    model.per_anchor["mask"].data = torch.where(gmask > 0, MASK_LOGIT, -MASK_LOGIT)[..., None]
    model.set_fixed_values(values)
    if feature_cache(model) is not None:
        model.provider.build_cache(xyz)
    model.eval()
    return DecodedModel(cfg=cfg, model=model, header=header, decode_s=time.perf_counter() - t0,
                        entropy=entropy)


@torch.no_grad()
def coded_bits_per_anchor(dec: DecodedModel) -> torch.Tensor:
    """[N] float64: each decoded anchor's coded attributes' information content under the
    file's own probability model (``-log2 p`` of every coded value, ``p`` from the exact path
    the range coder used, floored at the coder's 2^-24 as its leaky quantizer floors it;
    masked-off values cost nothing). Summed over the anchors it is the attribute sections'
    payload to within the range coder's overhead."""
    ent, model = dec.entropy, dec.model
    xyz = model.xyz.detach().cpu()
    n = xyz.shape[0]
    gmask = (model.gaussian_mask().detach().cpu() > 0)
    out = torch.zeros(n, dtype=torch.float64)
    ctx = ent._exact_context()
    for s in range(0, n, ent.chunk):
        e = min(n, s + ent.chunk)
        P = ent.params(xyz[s:e], exact=True, _ctx=ctx)
        for a in ent.attrs:
            mean, scale, q = (t.double() for t in P[a.name])
            x = model.fixed_values[a.name][s:e].detach().cpu().double()
            half = 0.5 * q
            p = (torch.special.ndtr((x + half - mean) / scale)
                 - torch.special.ndtr((x - half - mean) / scale)).abs()
            bits = -torch.log2(p.clamp_min(CODER_FLOOR))
            m = ent.value_mask(a, gmask[s:e], e - s)
            if m is not None:
                bits = bits * m.double()
            out[s:e] += bits.sum(dim=1)
    return out


def section_group(name: str, header: dict) -> str:
    """The size group of a section (see the module docstring)."""
    if name in header.get("provider_attrs", []) or name.startswith("provider."):
        return "feature"
    if name == "positions":
        return "anchor"
    if name in ("scaling", "offsets", "masks"):
        return name
    if name == "em.grid":
        return "hash"
    return "mlps"


def section_label(name: str, header: dict) -> str:
    """What a section holds, named by the component that owns it (``pgs info``, reports):
    ``provider.*`` / ``refiner.*`` / ``em.*`` by the registered provider, refiner and entropy
    model of the file (their ``SECTION_LABELS``, e.g. HAC's ``hac.grid``, ``hac.mlp``), ``decoder.weights`` as ``decoder``; the
    others (positions, masks, the coded attributes) by their own names."""
    if name == "decoder.weights":
        return "decoder"
    cfg = header.get("config") if isinstance(header.get("config"), dict) else {}
    model = cfg.get("model") if isinstance(cfg.get("model"), dict) else {}
    ent = header.get("entropy") if isinstance(header.get("entropy"), dict) else {}
    owners = {"provider": ("feature_provider", model.get("feature_provider")),
              "refiner": ("refiner", model.get("refiner")),
              "em": ("entropy_model", ent.get("kind"))}
    head, _, suffix = name.partition(".")
    if head not in owners or not isinstance(owners[head][1], str) or not suffix:
        return name
    kind, comp = owners[head]
    label = registry.section_labels(kind, comp).get(suffix, suffix)
    return comp if label == "" else f"{comp}.{label}"


def file_info(path: str | Path) -> dict:
    """Per-section and per-group allocation read from the file itself (its header checked as
    the decoder checks it)."""
    header, sections, total = read_container_sized(path)
    try:
        check_header(header, sections, total, max_bytes=1 << 62)   # reads, allocates nothing
    except BitstreamError as e:
        raise BitstreamError(f"{path}: {e}") from None
    rows = [{"section": n, "label": section_label(n, header), "bytes": len(b),
             "group": section_group(n, header)} for n, b in sections.items()]
    groups: dict[str, int] = {}
    for r in rows:
        groups[r["group"]] = groups.get(r["group"], 0) + r["bytes"]
    groups["header+framing"] = total - sum(r["bytes"] for r in rows)
    info = {"total_bytes": total, "sections": rows, "groups": groups,
            "n_anchors": header.get("n_anchors"),
            "header": {k: header[k] for k in ("n_anchors", "n_offsets", "weight_dtype") if k in header}}
    info["header"]["position_coding"] = header.get("position_coding",
                                                   CODING_DEFAULTS["position_coding"])
    info["header"]["mask_coding"] = header.get("mask_coding", CODING_DEFAULTS["mask_coding"])
    info["header"]["grid_coding"] = header.get("grid_coding", "all")
    n_anchors = header.get("n_anchors")
    if "positions" in sections and isinstance(n_anchors, int) and n_anchors > 0:
        info["positions"] = {"coding": info["header"]["position_coding"],
                             "bytes": len(sections["positions"]),
                             "bits_per_anchor": 8 * len(sections["positions"]) / n_anchors}
    on = None
    if "masks" in sections:              # how many neural Gaussians the decoder keeps
        counter = (mask_pattern_counts if header.get("mask_coding") == "patterns"
                   else bernoulli_counts)
        n, on = counter(sections["masks"], what="section 'masks'")
        info["masks_on"] = {"on": on, "total": n}
    info["attributes"] = coded_elements(header, sections, on)
    return info


def coded_elements(header: dict, sections: dict, masks_on: Optional[int]) -> list[dict]:
    """What each coded attribute's bytes pay for, from the file alone.

    One row per coded attribute section: ``{"section", "dims", "masked", "elements", "bytes",
    "bits_per_element"}``. ``elements`` is the number of values the entropy coder wrote: anchors x
    dims, or for a masked attribute (offsets) only the values of Gaussians whose mask is on
    (masks on x dims / n_offsets). It separates the two reasons a section can grow: more coded
    values, or more bits for each."""
    rows = []
    try:
        n_anchors, n_offsets = int(header["n_anchors"]), int(header["n_offsets"])
        attrs = list(header.get("attrs", []))
    except (KeyError, TypeError, ValueError):
        return rows
    for a in attrs:
        name, dims, masked = a.get("name"), int(a.get("dims", 0)), bool(a.get("masked", False))
        if name not in sections:
            continue
        if masked:
            if masks_on is None or n_offsets <= 0:
                continue
            elements = masks_on * dims // n_offsets
        else:
            elements = n_anchors * dims
        nbytes = len(sections[name])
        rows.append({"section": name, "dims": dims, "masked": masked, "elements": elements,
                     "bytes": nbytes,
                     "bits_per_element": 8.0 * nbytes / elements if elements else None})
    return rows


def format_info(info: dict) -> str:
    mb = 2 ** 20
    lines = [f"{'section':<22}{'group':<16}{'bytes':>12}{'MB':>10}{'share':>8}"]
    tot = info["total_bytes"]
    for r in info["sections"]:
        lines.append(f"{r.get('label', r['section']):<22}{r['group']:<16}{r['bytes']:>12}"
                     f"{r['bytes'] / mb:>10.4f}{100 * r['bytes'] / tot:>7.1f}%")
    lines.append("")
    lines.append(f"{'group':<38}{'bytes':>12}{'MB':>10}{'share':>8}")
    for g, b in sorted(info["groups"].items(), key=lambda kv: -kv[1]):
        lines.append(f"{g:<38}{b:>12}{b / mb:>10.4f}{100 * b / tot:>7.1f}%")
    lines.append(f"{'total (file size)':<38}{tot:>12}{tot / mb:>10.4f}")
    pos = info.get("positions")
    if pos:
        lines.append("")
        lines.append(f"anchor positions ({pos['coding']}): {pos['bits_per_anchor']:.2f} bits per "
                     f"anchor")
    m = info.get("masks_on")
    if m:
        lines.append("")
        lines.append(f"Gaussian masks on: {m['on']} of {m['total']} "
                     f"({100 * m['on'] / max(m['total'], 1):.1f}%; the neural Gaussians kept)")
    attrs = info.get("attributes") or []
    if attrs:
        lines.append("")
        lines.append(f"{'coded attribute':<22}{'values coded':>14}{'bytes':>12}{'bits/value':>12}")
        for a in attrs:
            bpe = "-" if a["bits_per_element"] is None else f"{a['bits_per_element']:.3f}"
            what = " (mask-on Gaussians only)" if a["masked"] else ""
            lines.append(f"{a['section']:<22}{a['elements']:>14}{a['bytes']:>12}{bpe:>12}{what}")
    return "\n".join(lines)
