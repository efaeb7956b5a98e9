"""Patches: TOML overlays of the configuration, applied in order, then ``--set`` overrides.

A patch is ``NAME.toml`` in the baseline's folder (:data:`PATCH_DIR`) or in a folder a plugin
registered (registry kind ``patch_dir``), or any ``.toml`` file given by path. Besides the
config sections it sets, a shipped patch declares, as top-level keys:

* ``kind``: one of :data:`PATCH_KINDS` (how ``pgs config --list`` groups it);
* ``description``: one line;
* ``label`` (optional): what reports call a method the patch selects (as tables and legends show it);
* ``survey`` (dataset patches): the 3DGS compression survey's name of the dataset;
* ``include`` (optional): patches applied first.

A method is a registered :class:`~baseline.contracts.MethodSpec` (a plugin's) or a patch of
kind ``method`` (:func:`method_specs`).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import tomllib
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w

from baseline import registry
from baseline.config.schema import Config, ConfigError, default_config, to_dict, validate
from baseline.contracts import MethodSpec
from baseline.fileio import read_text_bounded

PATCH_DIR = Path(__file__).resolve().parent.parent / "patches"
# what a patch does, in the order `pgs config --list` shows them
PATCH_KINDS = {"preset": "schedules and machines", "dataset": "a dataset's protocol",
               "method": "a method of its own", "rate": "rate points",
               "ablation": "a method with a part removed or swapped",
               "codec": "how the file is coded; no effect on training",
               "lever": "one setting changed, to measure what it does"}
META_KEYS = ("kind", "description", "label", "survey")


@dataclass(frozen=True)
class PatchInfo:
    """What a shipped patch declares of itself (its top-level keys)."""

    name: str
    path: Path
    kind: str
    description: str
    label: str | None = None
    survey: str | None = None


def patch_dirs() -> list[Path]:
    """Where patch names are looked up: the baseline's folder, then each plugin's."""
    return [PATCH_DIR] + [d for d in registry.patch_dirs() if d != PATCH_DIR]


def resolve_patch(name: str) -> Path:
    """A patch by name (``NAME.toml`` in a patch folder) or by path."""
    p = Path(name)
    if p.suffix == ".toml" and p.exists():
        return p
    dirs = patch_dirs()
    for d in dirs:
        cand = d / f"{name}.toml"
        if cand.exists():
            return cand
    avail = ", ".join(sorted(patch_infos()))
    raise ConfigError(f"unknown patch '{name}': no file {p} and no {name}.toml in "
                      f"{', '.join(str(d) for d in dirs)}; available patches: {avail}")


def _read_patch(path: Path) -> dict:
    try:
        return tomllib.loads(read_text_bounded(path, "a config patch"))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"patch {path} is not valid TOML: {e}") from None


def load_patch(name: str) -> tuple[Path, dict]:
    """The patch's path and the config it sets (``include`` kept; its own keys dropped)."""
    path = resolve_patch(name)
    data = _read_patch(path)
    for k in META_KEYS:
        data.pop(k, None)
    return path, data


def patch_name(path: Path) -> str:
    """How a run's config names an applied patch: by name when it is a shipped one."""
    return path.stem if path.parent.resolve() in {d.resolve() for d in patch_dirs()} else str(path)


@functools.cache
def _infos(dirs: tuple[Path, ...]) -> dict[str, PatchInfo]:
    out: dict[str, PatchInfo] = {}
    for d in dirs:
        for path in sorted(d.glob("*.toml")):
            if path.stem in out:
                continue                    # the first folder's patch of a name wins
            data = _read_patch(path)
            out[path.stem] = PatchInfo(path.stem, path, str(data.get("kind", "")),
                                       str(data.get("description", "")), data.get("label"),
                                       data.get("survey"))
    return out


def patch_infos() -> dict[str, PatchInfo]:
    """Every shipped patch (the baseline's and the plugins'), by name."""
    return _infos(tuple(patch_dirs()))


def method_specs() -> dict[str, MethodSpec]:
    """Every method users can name: the registered specs, and each patch of kind ``method``
    (its label and description taken from the file)."""
    specs = {name: MethodSpec(name, info.label or name, info.description, (name,))
             for name, info in patch_infos().items() if info.kind == "method"}
    specs.update(registry.methods())
    return specs


def patch_labels() -> dict[str, str]:
    """What reports call the methods and named variants: every patch's declared label, then
    every method spec's."""
    labels = {name: info.label for name, info in patch_infos().items() if info.label}
    labels.update({name: spec.label for name, spec in method_specs().items()})
    return labels


def format_patch_list() -> str:
    """The shipped patches grouped by kind, one line each (``pgs config --list``)."""
    infos = patch_infos()
    w = max((len(n) for n in infos), default=0)
    out = []
    for kind, what in PATCH_KINDS.items():
        names = sorted(n for n, i in infos.items() if i.kind == kind)
        if names:
            out.append(f"{kind} ({what}):")
            out += [f"  {n.ljust(w)}  {infos[n].description}" for n in names]
    return "\n".join(out)


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


def build_config(patches: Sequence[str] = (), sets: Sequence[str] = ()) -> Config:
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
        cfg.patches.append(patch_name(path))
    for s in sets:
        apply_overlay(cfg, parse_set(s), f"--set {s}")
    validate(cfg)
    return cfg


def to_toml(cfg: Config) -> str:
    """The merged config as a run folder's ``config.toml``."""
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
