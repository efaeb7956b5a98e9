"""Registry lookups and plugin discovery through the pgs.plugins entry point."""
import subprocess
import sys

import pytest

from baseline import registry


def test_unknown_component_lists_registered():
    with pytest.raises(registry.UnknownComponentError) as e:
        registry.get("feature_provider", "nope")
    msg = str(e.value)
    assert "unknown feature_provider 'nope'" in msg and "explicit" in msg


def test_plugin_discovered_through_entry_point():
    from importlib.metadata import entry_points

    eps = [ep.name for ep in entry_points(group=registry.ENTRY_POINT_GROUP)]
    assert "predict" in eps, "the project must be installed (pip install -e .) for entry points"
    registry.ensure_loaded()
    assert "predict" in registry.names("config_section")


def test_duplicate_registration_refused():
    registry.register("test_kind", "x", object)
    with pytest.raises(ValueError, match="already registered"):
        registry.register("test_kind", "x", int)


def test_baseline_never_imports_predict_plugin():
    code = ("import sys, baseline.registry as r, baseline.config, baseline.cli;"
            "r.load_builtins();"
            "bad=[m for m in sys.modules if m.startswith('predict_plugin')];"
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_baseline_source_has_no_plugin_import():
    from pathlib import Path

    root = Path(registry.__file__).parent
    for f in root.rglob("*.py"):
        text = f.read_text()
        assert "import predict_plugin" not in text and "from predict_plugin" not in text, f
