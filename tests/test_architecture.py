"""The import contract (pyproject.toml [tool.importlinter], docs/architecture.md) holds: ``lint-imports``.

Installed, the layers are subpackages of ``scenesig`` while their folders stay at the top of the
repository (``[tool.setuptools.package-dir]``).  In the checkout, ``scenesig/<layer>`` is a symbolic link
to the layer's folder, so the repository root reads as the installed package: ``lint-imports`` run there
(as a developer would) analyses every layer.
"""
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_dirs() -> dict[str, str]:
    return _pyproject()["tool"]["setuptools"]["package-dir"]


def _app_modules() -> set[str]:
    """The application layer: scenesig's own modules and subpackages (everything but the mapped layers)."""
    layers = {name.split(".", 1)[1] for name in _package_dirs() if "." in name}
    own = {p.stem for p in (ROOT / "scenesig").glob("*.py") if p.stem not in {"__init__", "__main__"}}
    own |= {p.parent.name for p in (ROOT / "scenesig").glob("*/__init__.py")}
    return own - layers


def test_every_top_level_package_is_installed_under_scenesig():
    """A new top-level folder with an __init__.py (e.g. aerial/) must be mapped, not silently left out."""
    mapped = set(_package_dirs().values())
    folders = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert folders <= mapped, f"map {sorted(folders - mapped)} in [tool.setuptools.package-dir]"


def test_every_application_module_is_forbidden_to_the_layers():
    contract = next(c for c in _pyproject()["tool"]["importlinter"]["contracts"]
                    if c["name"].startswith("The layers do not import"))
    listed = {m.removeprefix("scenesig.") for m in contract["forbidden_modules"]}
    assert _app_modules() == listed, (
        f"application modules {sorted(_app_modules() ^ listed)} missing from (or stale in) the contract")


def test_every_layer_is_linked_into_the_package():
    """``scenesig/<layer>`` links to the layer's folder, as package-dir maps it (else lint-imports and a
    run from the checkout would not see the layer)."""
    for name, folder in _package_dirs().items():
        if "." in name:
            link = ROOT / "scenesig" / name.split(".", 1)[1]
            assert link.is_symlink() and link.resolve() == (ROOT / folder).resolve(), \
                f"scenesig/{link.name} must be a symbolic link to ../{folder}"


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
