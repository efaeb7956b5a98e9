"""A run's identity: the training-semantics version and the config hash that names its folder.

A run folder or archived record is reused only by a config of the same hash, so what enters the
hash decides which finished runs a command finds: the merged config (less where a run executes
and what it logs), the training-semantics versions, and no option added later while it is at
the default that reproduces the runs finished before it existed.
"""
from __future__ import annotations

import hashlib
import json

from baseline import registry
from baseline.config.schema import Config, to_dict

# What one config trains to, as a version. A change of the training code that makes the same
# config train differently (not float order) bumps it; it is part of every run's config hash, so
# a run folder or archived record of another version is never reused or mixed as if trained by
# this code, and every results.json and report names it.
#   1: up to 2026-11-26.
#   2: HAC's rate as its reference code trains it: the offsets' bits weighted by the
#      straight-through float Gaussian mask (the rate trains the masks), the sampled bits x the
#      share of valid visible anchors (mask_anchor_rate), the context grid normalised by the
#      widened anchor bounds; near plane 0.2 in prefilter and rasterizer (data.near).
#   3: HAC's anchor positions in training (train.positions = "coded"): the 16-bit positions
#      the file stores, over the anchor box taken at the start and with the context's
#      (configs with lattice-coded positions, HAC++'s, train as at 2).
TRAINING_SEMANTICS = 3
TRAINING_SEMANTICS_NOTES = {
    1: "before HAC's mask-training rate (boolean-masked offset bits, no mask_anchor_rate, raw "
       "context bounds, near 0.01)",
    2: "HAC's reference rate: straight-through float mask on the offsets' bits, mask_anchor_rate, "
       "widened context bounds; near 0.2",
    3: "HAC's 16-bit anchor positions in training (the file's), over the box of the start and "
       "of the context",
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

# How often a run saves its state: no training setting either (a checkpoint is written and the
# step goes on unchanged), but runs were hashed with it at its default, so the hash reads that
# default whatever the value is (a long run may save more often and keep its folder).
SAVING_KEYS = {("train", "checkpoint_every"): 5000}


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
              ("entropy", "hash_values_per_anchor"): 0,
              ("densify", "reference_skip_update"): False,
              ("entropy", "context"): "own",
              ("train", "positions"): "float"}

# Options that only one component reads, added or given new defaults after runs of configs
# without that component were archived: left out of the hash of a config that does not select
# the component (its value cannot change what such a config trains): (section, key) -> (model
# field, component name). The baseline has none; a plugin section declares its own, and its
# later keys, as class attributes ``COMPONENT_KEYS = {key: (field, name)}`` and
# ``LATER_KEYS = {key: default}``.
COMPONENT_KEYS: dict[tuple[str, str], tuple[str, str]] = {}


def _section_keys(cfg: Config, attr: str, own: dict) -> dict:
    """The baseline's (section, key) table ``own`` and what each plugin section declares under
    class attribute ``attr``."""
    out = dict(own)
    for name, sec in cfg.ext.items():
        out.update({(name, k): v for k, v in getattr(type(sec), attr, {}).items()})
    return out


def component_semantics(cfg: Config) -> dict[str, int]:
    """The training-semantics versions of the registered components ``cfg`` selects (feature
    provider, refiner, hooks, entropy model, mask training) that declare one above 1 (class
    attribute ``TRAINING_SEMANTICS``): ``{"kind.name": version}``. A component bumps its own
    version when it trains differently from the same config, so that only the runs that use it
    get new hashes (a plugin's change leaves HAC's finished runs valid)."""
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
    for (sec, key), default in SAVING_KEYS.items():
        if key in d.get(sec, {}):
            d[sec][key] = default
    for (sec, key), (field, name) in _section_keys(cfg, "COMPONENT_KEYS", COMPONENT_KEYS).items():
        if getattr(cfg.model, field) != name and sec in d:
            d[sec].pop(key, None)
    for (sec, key), default in _section_keys(cfg, "LATER_KEYS", LATER_KEYS).items():
        if sec in d and key in d[sec] and d[sec][key] == default:
            del d[sec][key]
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:12]
