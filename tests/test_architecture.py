"""The layout and the import contract (pyproject.toml, docs/architecture.md "Layout"): one import identity per
file, no links, ``lint-imports`` passes and no layer imports itself in a cycle.

Each folder of the design card is a source root of the ``scenesig`` package (``mapping/scenesig/mapping/build.py``
is ``scenesig.mapping.build``, ``scenesig/scenesig/api.py`` is ``scenesig.api``).  The editable install links
every file into one package folder (``build/__editable__.*/scenesig``), which Python and a bare ``lint-imports``
both read.
"""
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
APP_ROOT = ROOT / "scenesig"                 # the application layer's source root


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _package_dirs() -> dict[str, str]:
    return _pyproject()["tool"]["setuptools"]["package-dir"]


def _app_modules() -> set[str]:
    """The application layer: scenesig's own modules and subpackages (everything but the mapped layers)."""
    layers = {name.split(".", 1)[1] for name in _package_dirs() if "." in name}
    own = {p.stem for p in (APP_ROOT / "scenesig").glob("*.py") if p.stem not in {"__init__", "__main__"}}
    own |= {p.parent.name for p in (APP_ROOT / "scenesig").glob("*/__init__.py")}
    return own - layers


def _layer_roots() -> dict[str, Path]:
    """``{layer: its source root}`` from package-dir (``"scenesig.mapping" = "mapping/scenesig/mapping"``)."""
    return {name.split(".", 1)[1]: ROOT / folder.split("/", 1)[0]
            for name, folder in _package_dirs().items() if "." in name}


def test_every_layer_folder_is_a_source_root_installed_under_scenesig():
    """A top-level folder holding ``scenesig/<layer>/`` must be mapped as ``<layer>/scenesig/<layer>``, the
    application layer as ``scenesig/scenesig``; no top-level folder is itself a package (it would be a second
    import name, and would hide the installed package from the repository root)."""
    dirs = _package_dirs()
    assert dirs["scenesig"] == "scenesig/scenesig"
    for folder in sorted({p.relative_to(ROOT).parts[0] for p in ROOT.glob("*/scenesig/*/__init__.py")} - {"scenesig"}):
        assert dirs.get(f"scenesig.{folder}") == f"{folder}/scenesig/{folder}", \
            f'map "scenesig.{folder}" = "{folder}/scenesig/{folder}" in [tool.setuptools.package-dir]'
    stray = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))
    assert stray == [], f"folders importable under their own name from the checkout: {stray}"


def test_no_module_outside_its_source_root():
    """A module left in a layer folder's old place (``localiser/session.py``) is not importable as
    ``scenesig.localiser.session``: move it under ``localiser/scenesig/localiser/`` (``git mv``)."""
    packages = {root: root / "scenesig" / layer for layer, root in _layer_roots().items()}
    packages[APP_ROOT] = APP_ROOT / "scenesig"
    stray = sorted(str(p.relative_to(ROOT)) for root, package in packages.items() for p in root.rglob("*")
                   if p.is_file() and "__pycache__" not in p.parts and not p.is_relative_to(package))
    assert not stray, f"files outside their layer's source root (<layer>/scenesig/<layer>/): {stray}"


def test_no_symbolic_links_are_tracked():
    listed = subprocess.run(["git", "ls-files", "-s"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    links = [line.split("\t", 1)[1] for line in listed.stdout.splitlines() if line.startswith("120000")]
    assert not links, f"symbolic links in the repository: {links}"


def test_one_import_identity_per_file():
    """From the repository root every module's file is the file at its path under its source root, and the
    layer folders are not packages of their own (``import mapping.store`` fails)."""
    code = r"""
import importlib, json, pkgutil, sys
import scenesig
out = {"scenesig": scenesig.__file__}
for m in pkgutil.walk_packages(scenesig.__path__, "scenesig."):
    if not m.name.endswith("__main__"):
        out[m.name] = importlib.import_module(m.name).__file__
bad = []
for name in ("mapping.store", "surveys.run", "benchmarks.heading", "scenesig.scenesig"):
    try:
        importlib.import_module(name)
        bad.append(name)
    except ImportError:
        pass
print(json.dumps({"files": out, "importable": bad}))
"""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.splitlines()[-1])
    assert got["importable"] == [], f"second import names from the repository root: {got['importable']}"
    roots = _layer_roots()
    for name, file in got["files"].items():
        parts = name.split(".")
        root = roots.get(parts[1], APP_ROOT) if len(parts) > 1 else APP_ROOT
        rel = Path(file).resolve().relative_to(root)
        expected = Path(*parts, "__init__.py") if rel.name == "__init__.py" else Path(*parts).with_suffix(".py")
        assert rel == expected, f"{name} is {file}, not {root / expected}"
    on_disk = {p.resolve() for root in {APP_ROOT, *_layer_roots().values()}
               for p in (root / "scenesig").rglob("*.py") if p.name != "__main__.py"}
    found = {Path(f).resolve() for f in got["files"].values()}
    assert not on_disk - found, (f"modules of the checkout the installed package lacks (a new file: run "
                                 f"`pip install -e .` again to link it): {sorted(map(str, on_disk - found))}")
    assert not found - on_disk, f"modules imported from outside the checkout: {sorted(map(str, found - on_disk))}"


def test_every_application_module_is_forbidden_to_the_layers():
    contract = next(c for c in _pyproject()["tool"]["importlinter"]["contracts"]
                    if c["name"].startswith("The layers do not import"))
    listed = {m.removeprefix("scenesig.") for m in contract["forbidden_modules"]}
    assert _app_modules() == listed, (
        f"application modules {sorted(_app_modules() ^ listed)} missing from (or stale in) the contract")


def test_lint_imports_passes():
    """``.ci/lint imports`` (a bare ``lint-imports``): the contract, over every layer (grimp sees them all, not
    just the application layer's)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}   # what a user's shell has
    proc = subprocess.run(["bash", str(ROOT / ".ci" / "lint"), "imports"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, env=env)
    assert proc.returncode == 0 and " 0 broken" in proc.stdout, proc.stdout[-4000:] + proc.stderr[-2000:]
    analysed = int(proc.stdout.split("Analyzed ", 1)[1].split(" files", 1)[0])
    assert analysed > 150, f"lint-imports saw {analysed} files: not every layer"


def _graph():
    grimp = pytest.importorskip("grimp", reason="grimp comes with import-linter (the test extras)")
    return grimp.build_graph("scenesig", cache_dir=None)


def _cycles(graph, package: str) -> list[list[str]]:
    """Strongly connected components (more than one module) of the imports among ``package``'s modules."""
    mods = sorted(m for m in graph.modules if m == package or m.startswith(package + "."))
    edges = {m: sorted(d for d in graph.find_modules_directly_imported_by(m) if d in mods) for m in mods}
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):                       # Tarjan's algorithm (recursion depth <= the layer's module count)
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for m in mods:
        if m not in index:
            visit(m)
    return out


def test_cycle_finder_finds_a_cycle():
    class G:
        modules = {"p", "p.a", "p.b", "p.c"}

        @staticmethod
        def find_modules_directly_imported_by(m):
            return {"p.a": {"p.b"}, "p.b": {"p.a", "p.c"}}.get(m, set())

    assert _cycles(G, "p") == [["p.a", "p.b"]]


def test_no_import_cycle_inside_a_layer():
    """No module of a layer imports itself through others of the same layer (a package's ``__init__``
    included): a cycle means the modules cannot be read, tested or moved one at a time."""
    graph = _graph()
    found = {layer: _cycles(graph, f"scenesig.{layer}") for layer in _layer_roots()}
    found = {layer: c for layer, c in found.items() if c}
    assert not found, f"import cycles inside a layer: {found}"


def test_architecture_doc_names_every_module_and_benchmark():
    """docs/architecture.md is the newcomer's map: every module of every package (a sub-package by its
    folder, e.g. ``sim/``) and every benchmark of ``scenesig bench`` must be named there."""
    from pathlib import Path

    from scenesig.commands.bench import BENCHMARKS

    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = []
    folders = {layer: root / layer / "scenesig" / layer for layer in _layer_roots() if layer != "benchmarks"}
    for pkg, folder in {**folders, "scenesig": APP_ROOT / "scenesig"}.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder)
            if path.name in ("__init__.py", "__main__.py"):
                continue
            if len(rel.parts) > 1:              # a sub-package: its folder named is enough
                if f"`{rel.parts[0]}/`" not in doc:
                    missing.append(f"{pkg}/{rel.parts[0]}/")
            elif f"`{path.name}`" not in doc and f"{pkg}.{path.stem}" not in doc:
                missing.append(f"{pkg}/{path.name}")
    missing += [f"benchmark {name}" for name in BENCHMARKS if f"`{name}`" not in doc]
    assert not missing, f"docs/architecture.md does not name: {sorted(set(missing))}"
