"""The configuration's schema: paper defaults (docs/method.md), ranges, validation.

The config is a tree of dataclasses. Baseline sections are fixed fields of :class:`Config`;
plugins contribute extra sections by registering a dataclass under registry kind
``config_section``, which then appear as ``cfg.ext[name]`` and may be set from patches as
``[name]``. Every section, the baseline's and a plugin's alike, declares the numeric ranges of
its keys as a class attribute ``RANGES = {key: (low, high)}`` (inclusive; a list key checks each
element); :func:`validate` checks them and the finiteness of every float, so every allocation a
config (or a file's header, which carries one) can ask for stays bounded.

Iteration milestones are written at the paper's scale (30k iterations, ``train.schedule_base``)
and converted with :meth:`TrainConfig.at`, so changing ``train.iterations`` (the ``cpu`` preset
does) scales every milestone proportionally.
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

from baseline import registry
from baseline.codec.format import GRID_CODINGS, MASK_CODINGS, MAX_GRID_LEVELS, POSITION_CODINGS


class ConfigError(ValueError):
    """A bad config key, value or patch; the message names the key and the source."""


@dataclass
class DataConfig:
    # numeric ranges (inclusive; a list key checks each element), checked by validate()
    RANGES: ClassVar[dict] = {
        "resolution": (-1, 1 << 16), "test_every": (1, 1 << 20), "random_init_points": (1, 1 << 26),
        "random_init_extent": (1e-9, 1e9), "near": (1e-9, 1e9)}
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
    RANGES: ClassVar[dict] = {
        "feat_dim": (1, 1024), "n_offsets": (1, 64), "hidden": (1, 4096), "voxel_size": (-1e9, 1e9),
        "update_init_factor": (1, 1 << 16), "update_hierarchy_factor": (1, 1 << 10),
        "update_depth": (1, 16)}
    feature_provider: str = "explicit"   # registry kind feature_provider
    refiner: str = "none"                # registry kind refiner ("none" = no refiner)
    feat_dim: int = 50
    n_offsets: int = 10
    hidden: int = 50
    voxel_size: float = 0.01             # 0: automatic (docs/method.md section 2; the reference also
    #                                      reads a negative size so: refused here as a typo)
    update_init_factor: int = 16         # NeRF-Synthetic: 4
    update_hierarchy_factor: int = 4
    update_depth: int = 3
    use_distance: bool = True            # HAC: view direction + distance (54 inputs)


@dataclass
class DensifyConfig:
    RANGES: ClassVar[dict] = {
        "stat_from": (0, 1 << 31), "update_from": (0, 1 << 31), "update_until": (0, 1 << 31),
        "update_interval": (1, 1 << 31), "skip_from": (0, 1 << 31), "skip_until": (0, 1 << 31),
        "grad_threshold": (0, 1e9), "success_threshold": (0, 1e9), "min_opacity": (0, 1),
        "prune_clamp_log_scaling": (-1e9, 1e9)}
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
    RANGES: ClassVar[dict] = {}          # every float key, set below the class
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
    # a mask training that scales the final mask lr with the rate (entropy.mask_training
    # strategies that read them): min(mask_final_per_mlambda x lambda / 1e-3, mask_final_cap) x
    # extent (cap 0: none); Tanks&Temples' value 1e-4, the dataset patches set the others
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
    channel_init: float = 0.005          # an entropy model's channel context networks (ctx.*)
    channel_final: float = 0.0005


# every learning rate in [0, 1e3]
LRConfig.RANGES = {f.name: (0, 1e3) for f in dataclasses.fields(LRConfig)
                   if f.type in (float, "float")}


@dataclass
class TrainConfig:
    RANGES: ClassVar[dict] = {
        "iterations": (1, 1 << 31), "schedule_base": (1, 1 << 31), "seed": (0, (1 << 63) - 1),
        "lambda_dssim": (0, 1), "lambda_volume": (0, 1e9), "threads": (0, 1 << 16),
        "checkpoint_every": (0, 1 << 31), "log_every": (1, 1 << 31)}
    iterations: int = 30000
    schedule_base: int = 30000           # milestones below/elsewhere are given at this scale
    seed: int = 0
    lambda_dssim: float = 0.2
    lambda_volume: float = 0.01
    threads: int = 0                     # 0 = all cores (at most OMP_NUM_THREADS when set)
    device: str = "auto"                 # auto (cuda when torch sees a GPU) | cpu | cuda | cuda:N
    rasterizer: str = "auto"             # auto | cpu | gsplat | reference
    hooks: list[str] = field(default_factory=lambda: ["scaffold_densify", "hac_phases"])
    # where HAC's phases put the anchors in training: coded (the positions the file will store:
    # 16-bit over the anchor box, as HAC's get_anchor, with the box taken at the start and again
    # when the context starts; exact voxel-lattice positions with codec.positions = lattice) |
    # float (the stored floats; the decoder then draws the anchors up to half a 16-bit step
    # away: -0.07 dB on truck, docs/RESULTS.md "Anchor positions in training")
    positions: str = "coded"
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
    RANGES: ClassVar[dict] = {
        "resolutions_3d": (2, 1 << 16), "resolutions_2d": (2, 1 << 16), "log2_table_3d": (1, 24),
        "log2_table_2d": (1, 24), "n_features": (1, 16)}
    resolutions_3d: list[int] = field(default_factory=lambda: [18, 24, 33, 44, 59, 80, 108, 148,
                                                               201, 275, 376, 514])
    log2_table_3d: int = 13
    resolutions_2d: list[int] = field(default_factory=lambda: [130, 258, 514, 1026])
    log2_table_2d: int = 15
    n_features: int = 4
    auto: bool = False                   # size tables and top levels from the anchor count


@dataclass
class EntropyConfig:
    RANGES: ClassVar[dict] = {
        "lmbda": (0, 1e9), "noise_from": (0, 1 << 31), "context_from": (0, 1 << 31),
        "mask_lambda": (0, 1e9), "mask_threshold": (1e-12, 1 - 1e-12), "rate_sample": (1e-12, 1),
        "context_hidden": (1, 4096), "position_bits": (1, 16),
        "rate_values_per_anchor": (0, 1 << 20), "hash_values_per_anchor": (0, 1 << 20)}
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
    # scaling 6 + offsets 30; a method coding fewer values per anchor weighs each of its bits
    # more at one lambda). N > 0 divides every method by N (86: a bit weighs the same for all).
    # lambda only moves a method along its own curve: compare methods by BD-rate, never at
    # equal lambda.
    rate_values_per_anchor: int = 0
    # The hash bits' denominator alone: hash bits / (N * H). 0 = the V above. HAC's code divides
    # them by its feature's 50 + scaling 6 + offsets 3K (86 at K = 10) whatever the coded
    # attributes are, so a method that codes fewer values per anchor (a residual in place of the
    # feature) but keeps HAC's 50-dim decoder input would weigh its tables' bits as HAC does
    # with H = 86, while V gives them the weight of its own coded values.
    hash_values_per_anchor: int = 0
    # Where a hash-grid entropy model ("hac", "hacpp") reads its positional context: "own" (a grid
    # of its own, trained by the rate, stored in the file) or "provider" (the feature
    # provider's grid, e.g. a Spatial Feature Pool, read with its gradient stopped: the context
    # MLP adapts to it, the provider's tables train for the image alone; no second grid to
    # query, train or store). No published method does the latter.
    context: str = "own"
    # how the Gaussian masks train (registry kind mask_training, baseline/train/masks.py):
    # "hac" (the mask loss; the rate on visible valid anchors) or another registered strategy
    mask_training: str = "hac"
    context_hidden: int = 100
    position_bits: int = 16
    grid: GridConfig = field(default_factory=GridConfig)



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
    # binary hash grids (HAC's context grid, a provider's grids): all (every entry, HAC's) | used
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
    cfg = Config()
    registry.ensure_loaded()
    for name in registry.names("config_section"):
        cfg.ext[name] = registry.get("config_section", name)()
    return cfg


def _check_ranges(obj: Any, section: str) -> None:
    """Types are checked on merge; here: finiteness of floats and the section's RANGES."""
    ranges = dict(getattr(type(obj), "RANGES", {}))
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        key = f"{section}.{f.name}"
        if dataclasses.is_dataclass(v):
            _check_ranges(v, key)
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


def _one_of(key: str, value: str, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{key} must be one of {', '.join(allowed)}, got '{value}'")


def validate(cfg: Config) -> None:
    """Ranges and finiteness of every numeric key (each section's ``RANGES``), then the keys
    with a fixed set of values. Errors name the key."""
    for f in dataclasses.fields(cfg):
        if f.name not in ("patches", "ext"):
            _check_ranges(getattr(cfg, f.name), f.name)
    for name, sec in cfg.ext.items():
        if dataclasses.is_dataclass(sec):
            _check_ranges(sec, name)
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
    _one_of("entropy.mask_training", cfg.entropy.mask_training, registry.names("mask_training"))
    _one_of("entropy.context", cfg.entropy.context, ("own", "provider"))
    if cfg.entropy.decoder_quant not in ("noise", "ste"):
        raise ConfigError(f"entropy.decoder_quant must be 'noise' or 'ste', got "
                          f"'{cfg.entropy.decoder_quant}'")
    if cfg.codec.weight_dtype not in ("float32", "float16"):
        raise ConfigError(f"codec.weight_dtype must be float32 or float16, got '{cfg.codec.weight_dtype}'")
    _one_of("codec.positions", cfg.codec.positions, POSITION_CODINGS)
    _one_of("train.positions", cfg.train.positions, ("coded", "float"))
    _one_of("codec.masks", cfg.codec.masks, MASK_CODINGS)
    _one_of("codec.grids", cfg.codec.grids, GRID_CODINGS)


def to_dict(cfg: Config, drop_meta: bool = False, only_changed_from: Config | None = None) -> dict:
    """The config as nested dicts (plugin sections beside the baseline's); ``drop_meta``: without
    the applied patches' names; ``only_changed_from``: only what differs from that config."""
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
