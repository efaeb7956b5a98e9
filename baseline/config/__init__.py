"""Typed configuration: the schema (:mod:`.schema`), patches and ``--set`` (:mod:`.patches`),
and a run's identity (:mod:`.identity`)."""
from baseline.codec.format import GRID_CODINGS, MASK_CODINGS, POSITION_CODINGS
from baseline.config.identity import (COMPONENT_KEYS, EXECUTION_KEYS, LATER_KEYS,
                                      SAVING_KEYS, TRAINING_SEMANTICS, TRAINING_SEMANTICS_NOTES,
                                      component_semantics, config_hash, semantics_label,
                                      semantics_note)
from baseline.config.patches import (PATCH_DIR, PATCH_KINDS, PatchInfo, apply_overlay,
                                     build_config, format_patch_list, from_toml, load_patch,
                                     method_specs, parse_set, patch_dirs, patch_infos,
                                     patch_labels, resolve_patch, to_toml)
from baseline.config.schema import (CodecConfig, Config, ConfigError, DataConfig, DensifyConfig,
                                    EntropyConfig, GridConfig, LRConfig, ModelConfig,
                                    TrainConfig, default_config, to_dict, validate)

__all__ = ["COMPONENT_KEYS", "EXECUTION_KEYS", "GRID_CODINGS", "LATER_KEYS", "MASK_CODINGS",
           "PATCH_DIR", "PATCH_KINDS", "POSITION_CODINGS", "SAVING_KEYS", "TRAINING_SEMANTICS",
           "TRAINING_SEMANTICS_NOTES", "CodecConfig", "Config", "ConfigError", "DataConfig",
           "DensifyConfig", "EntropyConfig", "GridConfig", "LRConfig", "ModelConfig", "PatchInfo",
           "TrainConfig", "apply_overlay", "build_config", "component_semantics", "config_hash",
           "default_config", "format_patch_list", "from_toml", "load_patch", "method_specs",
           "parse_set", "patch_dirs", "patch_infos", "patch_labels", "resolve_patch",
           "semantics_label", "semantics_note", "to_dict", "to_toml", "validate"]
