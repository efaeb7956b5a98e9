"""Hash-grid layouts: the constructor options of a :class:`~baseline.hac.hashgrid.BinaryHashGrid`
from a config, and the check of a layout a file header carries (each component checks its own
header fields: an entropy model's grid, a feature provider's)."""
from __future__ import annotations

from typing import Any

from baseline.codec.fields import (dict_field, header_error, int_field, list_field, num_field,
                                   str_field, unknown_keys)
from baseline.codec.format import MAX_GRID_FEATURES, MAX_GRID_LEVELS, MAX_GRID_LOG2, MAX_GRID_RES
from baseline.hac.hashgrid import auto_grid_layout, level_rows

GRID_KEYS = {"resolutions_3d", "log2_table_3d", "resolutions_2d", "log2_table_2d", "n_features",
             "planes", "init_range", "oob"}


def grid_options(gcfg, n_anchors: int) -> dict:
    """BinaryHashGrid constructor arguments from a GridConfig (``auto``: sized from the anchors)."""
    if gcfg.auto:
        return dict(auto_grid_layout(n_anchors), n_features=gcfg.n_features)
    return dict(resolutions_3d=tuple(gcfg.resolutions_3d), log2_table_3d=gcfg.log2_table_3d,
                resolutions_2d=tuple(gcfg.resolutions_2d), log2_table_2d=gcfg.log2_table_2d,
                n_features=gcfg.n_features)


def check_grid_options(g: Any, key: str) -> int:
    """A header's BinaryHashGrid layout under ``key``; returns its table entries (rows x
    features) so the caller can plan the allocation."""
    g = dict_field(g, key)
    unknown_keys(g, GRID_KEYS, key, "grid option")
    r3 = [int_field(r, f"{key}.resolutions_3d", 2, MAX_GRID_RES)
          for r in list_field(g.get("resolutions_3d", []), f"{key}.resolutions_3d",
                              MAX_GRID_LEVELS)]
    r2 = [int_field(r, f"{key}.resolutions_2d", 2, MAX_GRID_RES)
          for r in list_field(g.get("resolutions_2d", []), f"{key}.resolutions_2d",
                              MAX_GRID_LEVELS)]
    l3 = int_field(g.get("log2_table_3d", 13), f"{key}.log2_table_3d", 1, MAX_GRID_LOG2)
    l2 = int_field(g.get("log2_table_2d", 15), f"{key}.log2_table_2d", 1, MAX_GRID_LOG2)
    nf = int_field(g.get("n_features", 4), f"{key}.n_features", 1, MAX_GRID_FEATURES)
    planes = [str_field(p, f"{key}.planes", ("xy", "xz", "yz"))
              for p in list_field(g.get("planes", ["xy", "xz", "yz"]), f"{key}.planes", 3)]
    if len(set(planes)) != len(planes):
        raise header_error(f"{key}.planes", "a plane is listed twice")
    if "init_range" in g:
        num_field(g["init_range"], f"{key}.init_range", 0, 1e3)
    if "oob" in g:
        str_field(g["oob"], f"{key}.oob", ("per_grid", "all"))
    if not r3 and not (r2 and planes):
        raise header_error(key, "a grid needs at least one 3D level or one plane level")
    rows = sum(level_rows(r, 3, l3) for r in r3) + len(planes) * sum(level_rows(r, 2, l2)
                                                                       for r in r2)
    return rows * nf
