"""The import contract (pyproject.toml [tool.importlinter], docs/architecture.md) holds: ``lint-imports``."""
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]


def test_every_top_level_package_is_in_the_contract():
    """A new top-level package (e.g. aerial/) must be analysed, not silently left out."""
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    missing = packages - set(_config()["root_packages"]) - {"tests"}
    assert not missing, f"add {sorted(missing)} to [tool.importlinter] root_packages in pyproject.toml"


def test_lint_imports_passes():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).with_name("lint-imports"))
    if not Path(exe).exists():
        pytest.fail("lint-imports not found: install the test extras (pip install -e '.[test]')")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}   # this checkout, not an installed copy
    proc = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0 and " 0 broken" in proc.stdout, proc.stdout[-4000:] + proc.stderr[-2000:]
