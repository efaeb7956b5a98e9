"""Named components looked up from the config, and plugin discovery.

Kinds of components (extend freely):
    ``feature_provider``  per-anchor features for the decoder MLPs (baseline: ``explicit``)
    ``refiner``           additive corrections of decoded Gaussians (baseline: ``none``)
    ``entropy_model``     rate model + coder of the coded attributes (``hac``, ``factorized``)
    ``hooks``             training hook sets (``scaffold_densify``, ``hac_phases``, ...)
    ``mask_training``     how the Gaussian masks train (``hac``, ``hacpp``)
    ``executor``          where a benchmark's runs execute (``local``, ``ray``)
    ``rasterizer``        rasterizer backends (``cpu``, ``gsplat``, ``reference``)
    ``config_section``    extra config dataclasses contributed by plugins (section name -> class)

Plugins are Python packages exposing an entry point in the ``pgs.plugins`` group whose target
is a callable ``register(registry_module)``; :func:`load_plugins` calls each once.
"""
from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any, Callable, Dict

_REGISTRY: Dict[str, Dict[str, Any]] = {}
_BUILTINS_LOADED = False
_PLUGINS_LOADED = False
ENTRY_POINT_GROUP = "pgs.plugins"

# Modules of the baseline that register components on import.
_BUILTIN_MODULES = (
    "baseline.render",
    "baseline.scaffold",
    "baseline.hac",
    "baseline.train",
    "baseline.eval.executors",
)


class UnknownComponentError(KeyError):
    """A component name that nothing registered."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0])


def register(kind: str, name: str, obj: Any = None, *, replace: bool = False):
    """Register ``obj`` as component ``name`` of ``kind``; usable as a decorator."""

    def _do(o: Any) -> Any:
        table = _REGISTRY.setdefault(kind, {})
        if name in table and table[name] is not o and not replace:
            raise ValueError(f"{kind} '{name}' is already registered by {table[name]!r}")
        table[name] = o
        return o

    return _do(obj) if obj is not None else _do


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
    """The class behind a registered component: a lazily imported one (an object with a
    ``resolve()`` method, as plugins register them) is imported now."""
    obj = get(kind, name)
    return obj.resolve() if hasattr(obj, "resolve") else obj


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
    import sys

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        fn: Callable = ep.load()
        fn(sys.modules[__name__])
        _LOADED_PLUGINS.append(ep.name)
    return list(_LOADED_PLUGINS)


_LOADED_PLUGINS: list[str] = []


def ensure_loaded() -> None:
    load_builtins()
    load_plugins()
