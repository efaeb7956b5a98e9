"""Typed configuration: paper defaults (SPEC.md), TOML patches applied in order, ``--set`` overrides.

The config is a tree of dataclasses. Baseline sections are fixed fields of :class:`Config`;
plugins contribute extra sections by registering a dataclass under registry kind
``config_section`` (e.g. ``predict``), which then appear as ``cfg.ext["predict"]`` and may be set
from patches as ``[predict]``.

Iteration milestones are written at the paper's scale (30k iterations, ``train.schedule_base``)
and converted with :meth:`TrainConfig.at`, so changing ``train.iterations`` (the ``cpu`` preset
does) scales every milestone proportionally.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from baseline.fileio import read_text_bounded

PATCH_DIR = Path(__file__).resolve().parent.parent / "patches"


class ConfigError(ValueError):
    """A bad config key, value or patch; the message names the key and the source."""


@dataclass
class DataConfig:
    resolution: int = -1          # -1: original size capped at 1600 px wide; N: divide by N
    images: str = ""              # image folder override (e.g. "images_8"); "" = automatic
    eval: bool = True             # hold out every `test_every`-th view for testing
    test_every: int = 8
    background: str = "black"     # "black" or "white"
    near: float = 0.2             # near plane: anchors and Gaussians at view-space z <= near are
                                  # culled (Scaffold-GS / HAC: 0.2 in prefilter and rasterizer)
    random_init_points: int = 10000
    random_init_extent: float = 1.3
    cache_dir: str = ""           # "" = beside the scene (or ~/.cache/pgs when read-only)


@dataclass
class ModelConfig:
    feature_provider: str = "explicit"   # registry kind feature_provider
    refiner: str = "none"                # registry kind refiner ("none" = no refiner)
    feat_dim: int = 50
    n_offsets: int = 10
    hidden: int = 50
    voxel_size: float = 0.01             # 0: automatic (SPEC.md section 2; the reference also
    #                                      reads a negative size so: refused here as a typo)
    update_init_factor: int = 16         # NeRF-Synthetic: 4
    update_hierarchy_factor: int = 4
    update_depth: int = 3
    use_distance: bool = True            # HAC: view direction + distance (54 inputs)


@dataclass
class DensifyConfig:
    stat_from: int = 500                 # accumulate statistics for stat_from < it < update_until
    update_from: int = 1500
    update_until: int = 15000
    update_interval: int = 100
    skip_from: int = 3000                # HAC skips adjustments in [skip_from, skip_until)
    skip_until: int = 4000
    grad_threshold: float = 0.0002
    success_threshold: float = 0.8       # grow: count > interval*st*0.5; prune: count > interval*st
    min_opacity: float = 0.005
    # Reference quirk: when level 0 adds no anchor, levels 1-2 are skipped. False = always try
    # every level (our default, see baseline/scaffold/densify.py).
    reference_level_skip: bool = False
    # Reference quirk: log-scaling[:, 3:] clamped to <= 0.05 at each adjustment (< 0: off).
    prune_clamp_log_scaling: float = 0.05
    # Keep applying that clamp every update_interval after update_until, to the end of training.
    # The reference stops with the adjustments (15k of 30k); after that nothing bounds the
    # scale multipliers, and on the synthetic scene at 30k they grew to exp(7.5) and drew
    # streaks across training views (see README, "late divergence"). Off by default (faithful).
    clamp_scaling_to_end: bool = False
    # Reference quirk: it grows and prunes before its optimizer step and replaces every
    # per-anchor parameter (feature or residual, offsets, scaling, masks) doing so, so Adam skips
    # them at every adjustment (~125 steps: 0.4% of 30k, 2% of the cpu preset's 6k); only the
    # networks move. True = do the same; False = every step updates them (our default; the
    # skip is a side effect of how the reference rebuilds its tensors).
    reference_skip_update: bool = False


@dataclass
class LRConfig:
    offset_init: float = 0.01            # x scene extent
    offset_final: float = 0.0001
    feature: float = 0.0075
    scaling: float = 0.007
    mlp_opacity_init: float = 0.002
    mlp_opacity_final: float = 0.00002
    mlp_cov: float = 0.004
    mlp_color_init: float = 0.008
    mlp_color_final: float = 0.00005
    mask_init: float = 0.01              # x scene extent
    mask_final: float = 0.0001
    # HAC++ mask training (entropy.mask_training = "hacpp"): the final mask lr is
    # min(mask_final_per_mlambda x lambda / 1e-3, mask_final_cap) x extent (cap 0: none);
    # HAC++'s Tanks&Temples value 1e-4, the dataset patches set the others
    mask_final_per_mlambda: float = 0.0001
    mask_final_cap: float = 0.0
    # x schedule_base / iterations: a mask logit must travel a fixed distance (init 1 -> below
    # logit(0.01) = -4.6) to switch a Gaussian off, and Adam moves it at most ~lr per step, so a
    # short schedule at the paper's lr cannot switch off what the paper's can (patch masks-lr-scaled)
    mask_schedule_scaled: bool = False
    grid_init: float = 0.005
    grid_final: float = 0.00001
    context_init: float = 0.005
    context_final: float = 0.00001
    channel_init: float = 0.005          # HAC++'s channel context networks
    channel_final: float = 0.0005


@dataclass
class TrainConfig:
    iterations: int = 30000
    schedule_base: int = 30000           # milestones below/elsewhere are given at this scale
    seed: int = 0
    lambda_dssim: float = 0.2
    lambda_volume: float = 0.01
    threads: int = 0                     # 0 = all cores (at most OMP_NUM_THREADS when set)
    device: str = "auto"                 # auto (cuda when torch sees a GPU) | cpu | cuda | cuda:N
    rasterizer: str = "auto"             # auto | cpu | gsplat | reference
    hooks: list[str] = field(default_factory=lambda: ["scaffold_densify", "hac_phases"])
    checkpoint_every: int = 5000         # paper-scale iterations; 0 = only at the end
    log_every: int = 10
    save_test_renders: bool = True
    # also log the training curves to TensorBoard in RUN/tb/ (the optional tensorboard package:
    # pip install -e .[tensorboard]); logging only, so not part of a run's identity (hash)
    tensorboard: bool = False

    def at(self, paper_iteration: int) -> int:
        """Milestone ``paper_iteration`` (given for ``schedule_base`` iterations) scaled to this run."""
        return int(round(paper_iteration * self.iterations / self.schedule_base))


@dataclass
class GridConfig:
    resolutions_3d: list[int] = field(default_factory=lambda: [18, 24, 33, 44, 59, 80, 108, 148,
                                                               201, 275, 376, 514])
    log2_table_3d: int = 13
    resolutions_2d: list[int] = field(default_factory=lambda: [130, 258, 514, 1026])
    log2_table_2d: int = 15
    n_features: int = 4
    auto: bool = False                   # size tables and top levels from the anchor count


@dataclass
class EntropyConfig:
    model: str = "hac"                   # registry kind entropy_model: hac | factorized
    lmbda: float = 0.004                 # 0.004 low rate, 0.0005 high rate
    noise_from: int = 3000
    context_from: int = 10000
    mask_lambda: float = 0.0005
    mask_threshold: float = 0.01
    rate_sample: float = 0.05
    # What the decoder sees in training once values are quantized: "noise" (HAC: x + U(-.5,.5) Q)
    # or "ste" (the rounded values of evaluation, straight-through gradient; the rate is still
    # estimated with noise). With "noise" the decoder learns to use information below the step
    # that rounding deletes (baseline/hac/quant.py ste_round_q; patch quant-ste).
    decoder_quant: str = "noise"
    # The rate's denominator V: sum(sampled bits) / (n_sampled * V) and hash bits / (N * V).
    # 0 = the method's own coded values per anchor, as HAC's code computes it (HAC 86: feat 50 +
    # scaling 6 + offsets 30; Predict-GS 61: residual 25 + 6 + 30, so one lambda weighs each
    # Predict-GS bit 86/61 = 1.41x more). N > 0 divides every method by N (86: a bit weighs the
    # same for both). lambda only moves a method along its own curve: compare methods by
    # BD-rate, never at equal lambda.
    rate_values_per_anchor: int = 0
    # how the Gaussian masks train: "hac" (the mask loss; the rate on visible valid anchors) or
    # "hacpp" (HAC++: the rate alone, over all anchors, masks applied after the opacity
    # selection; baseline/train/masks.py, patch masks-hacpp)
    mask_training: str = "hac"
    context_hidden: int = 100
    position_bits: int = 16
    grid: GridConfig = field(default_factory=GridConfig)


POSITION_CODINGS = ("raw16", "sorted", "lattice")
MASK_CODINGS = ("bernoulli", "patterns")
GRID_CODINGS = ("all", "used")


@dataclass
class CodecConfig:
    weight_dtype: str = "float32"        # float32 | float16
    # anchor positions in the file: raw16 (HAC's and the paper's 48 bits per anchor) | sorted
    # (the same 16-bit values coded losslessly as a set: baseline/codec/positions.py) | lattice
    # (the integer voxel coordinates, octree-coded, decoded bit for bit: baseline/codec/lattice.py)
    positions: str = "raw16"
    # Gaussian masks: bernoulli (HAC's: one global probability) | patterns (each anchor's K bits
    # as one symbol, the file's own histogram: baseline/codec/masks.py)
    masks: str = "bernoulli"
    # binary hash grids (HAC's context grid, Predict-GS's SFP): all (every entry, HAC's) | used
    # (only the entries some decoded anchor reads; the decoder derives them from the positions)
    grids: str = "all"


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    lr: LRConfig = field(default_factory=LRConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    entropy: EntropyConfig = field(default_factory=EntropyConfig)
    codec: CodecConfig = field(default_factory=CodecConfig)
    patches: list[str] = field(default_factory=list)   # names of the applied patches, in order
    ext: dict[str, Any] = field(default_factory=dict)  # plugin sections

    def section(self, name: str) -> Any:
        if name in self.ext:
            return self.ext[name]
        return getattr(self, name)


def default_config() -> Config:
    """Paper defaults, with every registered plugin section at its defaults."""
    from baseline import registry

    cfg = Config()
    registry.ensure_loaded()
    for name in registry.names("config_section"):
        cfg.ext[name] = registry.get("config_section", name)()
    return cfg


# ----------------------------------------------------------------------------------- merging
def _check_value(value: Any, tp: Any, key: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    where = f"'{key}' in {source}"
    if origin in (list, tuple):
        (inner,) = typing.get_args(tp)[:1] or (Any,)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__} {value!r}")
        return [_check_value(v, inner, f"{key}[{i}]", source) for i, v in enumerate(value)]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {type(value).__name__} {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {type(value).__name__} {value!r}")
        return value
    return value


def _merge_into(obj: Any, overlay: dict, prefix: str, source: str) -> None:
    hints = typing.get_type_hints(type(obj))
    names = {f.name for f in dataclasses.fields(obj)}
    for k, v in overlay.items():
        key = f"{prefix}{k}"
        if k not in names or k in ("patches", "ext"):
            raise ConfigError(f"unknown config key '{key}' in {source}; "
                              f"known keys here: {', '.join(sorted(names - {'patches', 'ext'}))}")
        cur = getattr(obj, k)
        if dataclasses.is_dataclass(cur):
            if not isinstance(v, dict):
                raise ConfigError(f"'{key}' in {source} is a section; write it as [{key}]")
            _merge_into(cur, v, key + ".", source)
        else:
            setattr(obj, k, _check_value(v, hints[k], key, source))


def apply_overlay(cfg: Config, overlay: dict, source: str) -> None:
    """Merge a nested dict (a parsed TOML patch) into ``cfg``; errors name the key and source."""
    base = {f.name for f in dataclasses.fields(cfg)} - {"patches", "ext"}
    for sec, body in overlay.items():
        if sec in cfg.ext:
            if not isinstance(body, dict):
                raise ConfigError(f"'{sec}' in {source} is a section; write it as [{sec}]")
            _merge_into(cfg.ext[sec], body, sec + ".", source)
        elif sec in base:
            _merge_into(cfg, {sec: body}, "", source)
        else:
            known = sorted(base | set(cfg.ext))
            raise ConfigError(f"unknown config section '{sec}' in {source}; known sections: "
                              f"{', '.join(known)} (plugin sections exist only when the plugin "
                              f"is installed)")


def resolve_patch(name: str) -> Path:
    """A patch by name (``patches/NAME.toml``) or by path."""
    p = Path(name)
    if p.suffix == ".toml" and p.exists():
        return p
    cand = PATCH_DIR / f"{name}.toml"
    if cand.exists():
        return cand
    avail = ", ".join(sorted(q.stem for q in PATCH_DIR.glob("*.toml")))
    raise ConfigError(f"unknown patch '{name}': no file {p} and no {cand}; available patches: {avail}")


def load_patch(name: str) -> tuple[Path, dict]:
    path = resolve_patch(name)
    try:
        data = tomllib.loads(read_text_bounded(path, "a config patch"))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"patch {path} is not valid TOML: {e}") from None
    return path, data


def parse_set(expr: str) -> dict:
    """``section.key=value`` (value parsed as TOML, bare words as strings) -> nested dict."""
    if "=" not in expr:
        raise ConfigError(f"--set '{expr}': expected section.key=value")
    key, raw = expr.split("=", 1)
    key = key.strip()
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    parts = key.split(".")
    if len(parts) < 2:
        raise ConfigError(f"--set '{expr}': the key must name a section, e.g. train.iterations")
    out: dict = {}
    cur = out
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
    cur[parts[-1]] = value
    return out


def build_config(patches: list[str] = (), sets: list[str] = ()) -> Config:
    """Defaults, then each patch in order, then each ``--set``."""
    cfg = default_config()
    for name in patches:
        path, data = load_patch(name)
        # A patch may pull in other patches first: `include = ["cpu"]`.
        for inc in data.pop("include", []):
            sub = build_config([inc])
            apply_overlay(cfg, to_dict(sub, drop_meta=True, only_changed_from=default_config()),
                          f"patch {resolve_patch(inc)} (included by {path})")
            cfg.patches.extend(sub.patches)
        apply_overlay(cfg, data, f"patch {path}")
        cfg.patches.append(path.stem if path.parent == PATCH_DIR else str(path))
    for s in sets:
        apply_overlay(cfg, parse_set(s), f"--set {s}")
    validate(cfg)
    return cfg


INF = float("inf")
# Numeric ranges of the baseline's keys: (section, key) -> (low, high), inclusive; a list key
# checks each element. Every float key must also be finite. Plugin sections declare their own
# as a ``RANGES = {key: (low, high)}`` class attribute of their dataclass. The caps keep every
# allocation a config (or a file's header, which carries one) can ask for bounded.
RANGES = {
    ("data", "resolution"): (-1, 1 << 16), ("data", "test_every"): (1, 1 << 20),
    ("data", "random_init_points"): (1, 1 << 26), ("data", "random_init_extent"): (1e-9, 1e9),
    ("data", "near"): (1e-9, 1e9),
    ("model", "feat_dim"): (1, 1024), ("model", "n_offsets"): (1, 64),
    ("model", "hidden"): (1, 4096), ("model", "voxel_size"): (-1e9, 1e9),
    ("model", "update_init_factor"): (1, 1 << 16), ("model", "update_hierarchy_factor"): (1, 1 << 10),
    ("model", "update_depth"): (1, 16),
    ("densify", "stat_from"): (0, 1 << 31), ("densify", "update_from"): (0, 1 << 31),
    ("densify", "update_until"): (0, 1 << 31), ("densify", "update_interval"): (1, 1 << 31),
    ("densify", "skip_from"): (0, 1 << 31), ("densify", "skip_until"): (0, 1 << 31),
    ("densify", "grad_threshold"): (0, 1e9), ("densify", "success_threshold"): (0, 1e9),
    ("densify", "min_opacity"): (0, 1), ("densify", "prune_clamp_log_scaling"): (-1e9, 1e9),
    ("train", "iterations"): (1, 1 << 31), ("train", "schedule_base"): (1, 1 << 31),
    ("train", "seed"): (0, (1 << 63) - 1), ("train", "lambda_dssim"): (0, 1),
    ("train", "lambda_volume"): (0, 1e9), ("train", "threads"): (0, 1 << 16),
    ("train", "checkpoint_every"): (0, 1 << 31), ("train", "log_every"): (1, 1 << 31),
    ("grid", "resolutions_3d"): (2, 1 << 16), ("grid", "resolutions_2d"): (2, 1 << 16),
    ("grid", "log2_table_3d"): (1, 24), ("grid", "log2_table_2d"): (1, 24),
    ("grid", "n_features"): (1, 16),
    ("entropy", "lmbda"): (0, 1e9), ("entropy", "noise_from"): (0, 1 << 31),
    ("entropy", "context_from"): (0, 1 << 31), ("entropy", "mask_lambda"): (0, 1e9),
    ("entropy", "mask_threshold"): (1e-12, 1 - 1e-12), ("entropy", "rate_sample"): (1e-12, 1),
    ("entropy", "context_hidden"): (1, 4096), ("entropy", "position_bits"): (1, 16),
    ("entropy", "rate_values_per_anchor"): (0, 1 << 20),
}
RANGES.update({("lr", f.name): (0, 1e3) for f in dataclasses.fields(LRConfig)
               if f.type in (float, "float")})
MAX_GRID_LEVELS = 32


def _check_ranges(obj: Any, section: str, ranges: dict) -> None:
    """Types are checked on merge; here: finiteness of floats and the declared ranges."""
    import math

    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        key = f"{section}.{f.name}"
        if dataclasses.is_dataclass(v):
            _check_ranges(v, key, {k[1]: r for k, r in RANGES.items() if k[0] == f.name})
            continue
        vals = v if isinstance(v, list) else [v]
        if isinstance(v, list) and f.name.startswith("resolutions") and len(v) > MAX_GRID_LEVELS:
            raise ConfigError(f"{key}: at most {MAX_GRID_LEVELS} levels, got {len(v)}")
        for x in vals:
            if isinstance(x, float) and not math.isfinite(x):
                raise ConfigError(f"{key} must be finite, got {x}")
        rng = ranges.get(f.name)
        if rng is None:
            continue
        lo, hi = rng
        for x in vals:
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                continue
            if not lo <= x <= hi:
                raise ConfigError(f"{key} = {x} is out of range [{lo}, {hi}]")


def validate(cfg: Config) -> None:
    """Ranges and finiteness of every numeric key (:data:`RANGES`, plugin ``RANGES``), then the
    keys with a fixed set of values. Errors name the key."""
    for f in dataclasses.fields(cfg):
        if f.name in ("patches", "ext"):
            continue
        _check_ranges(getattr(cfg, f.name), f.name,
                      {k[1]: r for k, r in RANGES.items() if k[0] == f.name})
    for name, sec in cfg.ext.items():
        if dataclasses.is_dataclass(sec):
            _check_ranges(sec, name, dict(getattr(type(sec), "RANGES", {})))
    if cfg.train.iterations <= 0:
        raise ConfigError("train.iterations must be positive")
    v = cfg.model.voxel_size
    if v != 0 and not 1e-6 <= v <= 1e6:
        raise ConfigError(f"model.voxel_size = {v}: give 0 (automatic: from the points' "
                          f"nearest-neighbour spacing) or a voxel size in [1e-6, 1e6] scene units")
    if cfg.data.background not in ("black", "white"):
        raise ConfigError(f"data.background must be 'black' or 'white', got '{cfg.data.background}'")
    dev = cfg.train.device
    if not (dev in ("auto", "cpu", "cuda") or re.fullmatch(r"cuda:\d+", dev)):
        raise ConfigError(f"train.device must be auto, cpu, cuda or cuda:N, got '{dev}'")
    if cfg.entropy.mask_training not in ("hac", "hacpp"):
        raise ConfigError(f"entropy.mask_training must be 'hac' or 'hacpp', got "
                          f"'{cfg.entropy.mask_training}'")
    if cfg.entropy.decoder_quant not in ("noise", "ste"):
        raise ConfigError(f"entropy.decoder_quant must be 'noise' or 'ste', got "
                          f"'{cfg.entropy.decoder_quant}'")
    if cfg.codec.weight_dtype not in ("float32", "float16"):
        raise ConfigError(f"codec.weight_dtype must be float32 or float16, got '{cfg.codec.weight_dtype}'")
    if cfg.codec.positions not in POSITION_CODINGS:
        raise ConfigError(f"codec.positions must be one of {', '.join(POSITION_CODINGS)}, "
                          f"got '{cfg.codec.positions}'")
    if cfg.codec.masks not in MASK_CODINGS:
        raise ConfigError(f"codec.masks must be one of {', '.join(MASK_CODINGS)}, "
                          f"got '{cfg.codec.masks}'")
    if cfg.codec.grids not in GRID_CODINGS:
        raise ConfigError(f"codec.grids must be one of {', '.join(GRID_CODINGS)}, "
                          f"got '{cfg.codec.grids}'")


# ----------------------------------------------------------------------------- serialization
def to_dict(cfg: Config, drop_meta: bool = False, only_changed_from: Config | None = None) -> dict:
    d = dataclasses.asdict(cfg)
    ext = {k: dataclasses.asdict(v) for k, v in cfg.ext.items()}
    d.pop("ext")
    d.update(ext)
    if drop_meta:
        d.pop("patches")
    if only_changed_from is not None:
        ref = to_dict(only_changed_from, drop_meta=True)
        d = _diff(d, ref)
    return d


def _diff(d: dict, ref: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            sub = _diff(v, ref.get(k, {}))
            if sub:
                out[k] = sub
        elif ref.get(k) != v:
            out[k] = v
    return out


def to_toml(cfg: Config) -> str:
    import tomli_w

    d = to_dict(cfg)
    patches = d.pop("patches")
    head = f"# merged config; patches applied in order: {patches}\npatches = {json.dumps(patches)}\n\n"
    return head + tomli_w.dumps(d)


def from_toml(path: str | Path) -> Config:
    """Re-read a merged config written by :func:`to_toml` (a run folder's config.toml)."""
    try:
        data = tomllib.loads(read_text_bounded(path, "a run's config"))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path} is not valid TOML: {e}") from None
    cfg = default_config()
    cfg.patches = list(data.pop("patches", []))
    apply_overlay(cfg, data, f"config {path}")
    return cfg


# What one config trains to, as a version. A change of the training code that makes the same
# config train differently (not float order) bumps it; it is part of every run's config hash, so
# a run folder or archived record of another version is never reused or mixed as if trained by
# this code, and every results.json and report names it.
#   1: up to 2026-11-26.
#   2: HAC's rate as its reference code trains it: the offsets' bits weighted by the
#      straight-through float Gaussian mask (the rate trains the masks), the sampled bits x the
#      share of valid visible anchors (mask_anchor_rate), the context grid normalised by the
#      widened anchor bounds; near plane 0.2 in prefilter and rasterizer (data.near).
TRAINING_SEMANTICS = 2
TRAINING_SEMANTICS_NOTES = {
    1: "before HAC's mask-training rate (boolean-masked offset bits, no mask_anchor_rate, raw "
       "context bounds, near 0.01)",
    2: "HAC's reference rate: straight-through float mask on the offsets' bits, mask_anchor_rate, "
       "widened context bounds; near 0.2",
}


def semantics_note(version) -> str:
    """``"2 (what it means)"`` for a report's protocol."""
    try:
        v = int(version)
    except (TypeError, ValueError):
        return str(version)
    return f"{v} ({TRAINING_SEMANTICS_NOTES.get(v, 'unknown to this code')})"


# Where a run executes and what it logs, not what it computes: left out of the config hash, so
# the same settings trained on the CPU or on a GPU, with or without a TensorBoard log, are one
# run (each run records its device and rasterizer backend in results.json, and reports print
# them in their protocol).
EXECUTION_KEYS = (("train", "device"), ("train", "tensorboard"))


# Options added after runs were finished and archived, with the default that reproduces those
# runs: left out of the hash while at that default, so adding an option does not orphan every
# finished run (and its archived records) under a new hash.
LATER_KEYS = {("lr", "mask_schedule_scaled"): False,
              ("densify", "clamp_scaling_to_end"): False,
              ("entropy", "decoder_quant"): "noise",
              ("codec", "positions"): "raw16",
              ("codec", "masks"): "bernoulli",
              ("codec", "grids"): "all",
              ("data", "near"): 0.2,
              ("lr", "channel_init"): 0.005,
              ("lr", "mask_final_per_mlambda"): 0.0001,
              ("lr", "mask_final_cap"): 0.0,
              ("entropy", "mask_training"): "hac",
              ("lr", "channel_final"): 0.0005,
              ("entropy", "rate_values_per_anchor"): 0,
              ("predict", "fusion_init"): "zero",
              ("predict", "grid_init"): "random",
              ("predict", "box"): "extent",
              ("predict", "box_quantile"): 0.01,
              ("predict", "residual_grow"): "zero",
              ("densify", "reference_skip_update"): False}

# Options that only one component reads, added or given new defaults after runs of configs
# without that component were archived: left out of the hash of a config that does not select
# the component (its value cannot change what such a config trains).
COMPONENT_KEYS = {("predict", "fusion_init"): ("feature_provider", "sfp"),
                  ("predict", "grid_init"): ("feature_provider", "sfp"),
                  ("predict", "residual_grow"): ("feature_provider", "sfp")}


def component_semantics(cfg: Config) -> dict[str, int]:
    """The training-semantics versions of the registered components ``cfg`` selects (feature
    provider, refiner, hooks, entropy model, mask training) that declare one above 1 (class
    attribute ``TRAINING_SEMANTICS``): ``{"kind.name": version}``. A component bumps its own
    version when it trains differently from the same config, so that only the runs that use it
    get new hashes (a Predict-GS change leaves HAC's finished runs valid)."""
    from baseline import registry

    registry.ensure_loaded()
    chosen = [("feature_provider", cfg.model.feature_provider), ("refiner", cfg.model.refiner),
              ("entropy_model", cfg.entropy.model), ("mask_training", cfg.entropy.mask_training)]
    chosen += [("hooks", h) for h in cfg.train.hooks]
    out = {}
    for kind, name in chosen:
        try:
            cls = registry.component_class(kind, name)
        except (KeyError, ImportError, AttributeError):
            continue
        v = int(getattr(cls, "TRAINING_SEMANTICS", 1) or 1)
        if v > 1:
            out[f"{kind}.{name}"] = v
    return out


def semantics_label(cfg_or_components) -> str:
    """``"2"`` or ``"2; feature_provider.sfp 2"``: the version a run was trained under."""
    comps = (cfg_or_components if isinstance(cfg_or_components, dict)
             else component_semantics(cfg_or_components))
    return "; ".join([str(TRAINING_SEMANTICS)] + [f"{k} {v}" for k, v in sorted(comps.items())])


def config_hash(cfg: Config, semantics: int = TRAINING_SEMANTICS) -> str:
    """A short stable hash of the merged config and the training-semantics version (used to
    reuse finished runs), with the versions of the components it selects
    (:func:`component_semantics`) when any is above 1. ``semantics=1`` gives the hashes runs of
    version 1 were stored under (that version was not hashed)."""
    d = to_dict(cfg, drop_meta=True)
    if semantics != 1:
        d["training_semantics"] = int(semantics)
        comps = component_semantics(cfg)
        if comps:
            d["component_semantics"] = comps
    for sec, key in EXECUTION_KEYS:
        d[sec].pop(key, None)
    for (sec, key), (field, name) in COMPONENT_KEYS.items():
        if getattr(cfg.model, field) != name and sec in d:
            d[sec].pop(key, None)
    for (sec, key), default in LATER_KEYS.items():
        if sec in d and key in d[sec] and d[sec][key] == default:
            del d[sec][key]
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]
