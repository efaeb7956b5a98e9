"""Named components looked up from the config, methods, patch folders, and plugin discovery.

Kinds of components (their contracts: :mod:`baseline.contracts`; extend freely):
    ``feature_provider``  per-anchor features for the decoder MLPs (baseline: ``explicit``)
    ``refiner``           additive corrections of decoded Gaussians (baseline: ``none``)
    ``entropy_model``     rate model + coder of the coded attributes (``hac``, ``factorized``, ...)
    ``hooks``             training hook sets (``scaffold_densify``, ``hac_phases``, ...)
    ``mask_training``     how the Gaussian masks train (``hac``, ...)
    ``executor``          where a benchmark's runs execute (``local``, ``ray``)
    ``rasterizer``        rasterizer backends (``cpu``, ``gsplat``, ``reference``)
    ``config_section``    extra config dataclasses contributed by plugins (section name -> class)
    ``method``            :class:`~baseline.contracts.MethodSpec` of a method users name
    ``patch_dir``         a folder of TOML patches (``--patch NAME`` looks in every one)

Plugins are Python packages exposing an entry point in the ``pgs.plugins`` group whose target
is a callable ``register(registry_module)``; :func:`load_plugins` calls each once. A plugin
registers a component whose module needs the baseline's compiled pieces as
``lazy("package.module", "Name")``: it is imported when first used.
"""
from __future__ import annotations

import importlib
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from baseline.contracts import MethodSpec

_REGISTRY: dict[str, dict[str, Any]] = {}
_BUILTINS_LOADED = False
_PLUGINS_LOADED = False
_LOADED_PLUGINS: list[str] = []
ENTRY_POINT_GROUP = "pgs.plugins"

# Modules of the baseline that register components on import.
_BUILTIN_MODULES = (
    "baseline.render",
    "baseline.scaffold",
    "baseline.hac",
    "baseline.train",
    "baseline.experiment.executors",
)


class UnknownComponentError(KeyError):
    """A component name that nothing registered."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


class LazyComponent:
    """A component class imported on first use: calling it builds an instance, and
    :func:`component_class` resolves it to the class itself."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name
        self.__qualname__ = f"{module}.{name}"

    def resolve(self) -> Any:
        return getattr(importlib.import_module(self.module), self.name)

    def __call__(self, *args, **kwargs):
        return self.resolve()(*args, **kwargs)

    def __repr__(self) -> str:
        return f"lazy({self.module!r}, {self.name!r})"


def lazy(module: str, name: str) -> LazyComponent:
    return LazyComponent(module, name)


def register(kind: str, name: str, obj: Any = None, *, replace: bool = False):
    """Register ``obj`` as component ``name`` of ``kind``; usable as a decorator."""

    def _do(o: Any) -> Any:
        table = _REGISTRY.setdefault(kind, {})
        if name in table and table[name] is not o and not replace:
            raise ValueError(f"{kind} '{name}' is already registered by {table[name]!r}")
        table[name] = o
        return o

    return _do(obj) if obj is not None else _do


def register_method(spec: MethodSpec) -> MethodSpec:
    """Register a method users name (its label in every table, its patches)."""
    return register("method", spec.name, spec)


def register_patch_dir(name: str, folder: str | Path) -> None:
    """Register a folder of TOML patches under ``name`` (a plugin's own patches)."""
    register("patch_dir", name, Path(folder).resolve())


def get(kind: str, name: str) -> Any:
    """Look up a registered component; an unknown name lists the registered ones."""
    ensure_loaded()
    table = _REGISTRY.get(kind, {})
    if name not in table:
        known = ", ".join(sorted(table)) or "none"
        raise UnknownComponentError(
            f"unknown {kind} '{name}'; registered {kind} components: {known}")
    return table[name]


def component_class(kind: str, name: str) -> Any:
    """The class behind a registered component (a :class:`LazyComponent` is imported now)."""
    obj = get(kind, name)
    return obj.resolve() if isinstance(obj, LazyComponent) else obj


def section_labels(kind: str, name: str) -> dict:
    """A component's names for its bitstream sections (class attribute ``SECTION_LABELS``,
    section suffix -> what it holds; "" = the component itself): ``{}`` when it declares none
    or is not registered here."""
    try:
        return dict(getattr(component_class(kind, name), "SECTION_LABELS", {}) or {})
    except (KeyError, ImportError, AttributeError):
        return {}


def names(kind: str) -> list[str]:
    ensure_loaded()
    return sorted(_REGISTRY.get(kind, {}))


def methods() -> dict[str, MethodSpec]:
    """Every registered method spec, by name."""
    ensure_loaded()
    return dict(_REGISTRY.get("method", {}))


def patch_dirs() -> list[Path]:
    """The patch folders plugins registered, by name (the baseline's own is
    :data:`baseline.config.PATCH_DIR`)."""
    ensure_loaded()
    table = _REGISTRY.get("patch_dir", {})
    return [table[k] for k in sorted(table)]


def load_builtins() -> None:
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    for mod in _BUILTIN_MODULES:
        importlib.import_module(mod)


def load_plugins() -> list[str]:
    """Discover and register every installed plugin of the ``pgs.plugins`` group once.

    Returns the names of the entry points loaded.
    """
    global _PLUGINS_LOADED
    if _PLUGINS_LOADED:
        return list(_LOADED_PLUGINS)
    _PLUGINS_LOADED = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        ep.load()(sys.modules[__name__])
        _LOADED_PLUGINS.append(ep.name)
    return list(_LOADED_PLUGINS)


def ensure_loaded() -> None:
    load_builtins()
    load_plugins()
