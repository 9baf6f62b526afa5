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


def test_architecture_doc_names_every_module_and_benchmark():
    """docs/architecture.md is the newcomer's map: every module of every package (a sub-package by its
    folder, e.g. ``sim/``) and every benchmark of ``scenesig bench`` must be named there."""
    from pathlib import Path

    from scenesig.commands.bench import BENCHMARKS

    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = []
    for pkg in ("surveys", "signatures", "mapping", "localiser", "aerial", "scenesig"):
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root / pkg)
            if path.name in ("__init__.py", "__main__.py"):
                continue
            if len(rel.parts) > 1:              # a sub-package: its folder named is enough
                if f"`{rel.parts[0]}/`" not in doc:
                    missing.append(f"{pkg}/{rel.parts[0]}/")
            elif f"`{path.name}`" not in doc and f"{pkg}.{path.stem}" not in doc:
                missing.append(f"{pkg}/{path.name}")
    missing += [f"benchmark {name}" for name in BENCHMARKS if f"`{name}`" not in doc]
    assert not missing, f"docs/architecture.md does not name: {sorted(set(missing))}"
