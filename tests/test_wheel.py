"""The built wheel holds every file the toolkit reads at run time: every shipped patch (the
baseline's and the plugin's), the codec's table, and the plugin's entry point. Built offline
(no build isolation: setuptools from the test environment) from a copy of the sources, so a
stale ``build/`` folder of the checkout cannot add or hide a file."""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("baseline", "predict_plugin")


def _run_time_files() -> set[str]:
    """Package files other than Python sources that the code opens (docs excluded)."""
    out = set()
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*"):
            if p.is_file() and p.suffix in (".toml", ".npy") and "__pycache__" not in p.parts:
                out.add(p.relative_to(ROOT).as_posix())
    return out


@pytest.mark.slow
def test_wheel_holds_every_patch_and_data_file(tmp_path):
    pytest.importorskip("setuptools")
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "--no-index", "-q", "-w", str(tmp_path / "dist"), str(src)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        entry_points = next(z.read(n).decode() for n in names if n.endswith("entry_points.txt"))
    wanted = _run_time_files()
    assert {"baseline/codec/phi_table.npy", "baseline/patches/cpu.toml",
            "predict_plugin/patches/predict-gs.toml"} <= wanted
    assert sorted(wanted - names) == []
    sources = {p.relative_to(ROOT).as_posix() for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if "__pycache__" not in p.parts}
    assert sorted(sources - names) == []
    assert "predict = predict_plugin:register" in entry_points
    assert "pgs = baseline.cli:main" in entry_points
