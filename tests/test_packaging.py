"""One namespace: only ``scenesig`` is importable at top level, from an editable install and from a wheel.

The layers' folders stay at the top of the repository, each a source root of the package
(``[tool.setuptools.package-dir]`` maps ``scenesig.mapping`` to ``mapping/scenesig/mapping`` and so on); these
tests check what a user gets when they install it: every module once, from the files of the checkout.
"""
import os
import shutil
import subprocess
import sys
import tomllib
import venv
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("surveys", "signatures", "mapping", "localiser", "aerial", "benchmarks")


def _run(args, cwd, **kw):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}   # what a user's shell has
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=600, env=env, **kw)


def _package_dirs() -> dict[str, str]:
    """``[tool.setuptools.package-dir]``: each package and its folder in the checkout."""
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]


def _packaging_copy(tmp_path: Path) -> Path:
    """The checkout's packaging inputs (``pyproject.toml``, ``README.md`` and every source root of
    ``[tool.setuptools.package-dir]``) copied to ``tmp_path/checkout``.  Installing or building from the checkout
    itself rebuilds its ``build/`` folder -- the editable install's link tree, which every other test process
    and ``scenesig`` subprocess of a parallel suite imports from (pytest-xdist, ``-n 2``): a test installing
    from it broke another's ``scenesig build-map`` mid-import.  The copy has the same files and configuration."""
    dst = (tmp_path / "checkout").resolve()
    dst.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dst / name)
    for top in sorted({Path(folder).parts[0] for folder in _package_dirs().values()}):
        shutil.copytree(ROOT / top, dst / top, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "build"))
    return dst


def _checkout_modules() -> list[str]:
    """The package's files as the wheel should hold them: ``scenesig/<path under the package's folder>``."""
    dirs = _package_dirs()
    out = []
    for name, folder in dirs.items():
        prefix = Path(*name.split("."))
        nested = [Path(f) for n, f in dirs.items() if n != name and n.startswith(name + ".")]
        for p in (ROOT / folder).rglob("*.py"):
            if "__pycache__" in p.parts or any((ROOT / f) in p.parents for f in nested):
                continue
            out.append(str(prefix / p.relative_to(ROOT / folder)))
    return sorted(out)


def test_editable_install_imports_the_checkout(tmp_path):
    """``pip install -e .`` in a fresh environment: the package and every layer come from the checkout's
    files (of a copy of its packaging inputs, :func:`_packaging_copy`; each layer from its folder's source
    root, through the links of the editable install's one package folder), a bare ``lint-imports`` sees every
    layer, and the console script runs."""
    src = _packaging_copy(tmp_path)
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)
    py = env_dir / "bin" / "python"
    proc = _run([str(py), "-m", "pip", "install", "-q", "--no-deps", "-e", str(src)], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    code = ("import pathlib, scenesig, scenesig.mapping.store as s, scenesig.surveys.importers.kitti_raw as k; "
            "assert callable(scenesig.build_map) and len(scenesig.__path__) == 1; "
            "[print(pathlib.Path(m.__file__).resolve()) for m in (scenesig, s, k)]")
    for cwd in (tmp_path, src):              # the repository root's scenesig/ folder does not hide it
        proc = _run([str(py), "-c", code], cwd=cwd)
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == [str(src / "scenesig" / "scenesig" / "__init__.py"),
                                   str(src / "mapping" / "scenesig" / "mapping" / "store.py"),
                                   str(src / "surveys" / "scenesig" / "surveys" / "importers" / "kitti_raw.py")]
    proc = _run([str(env_dir / "bin" / "scenesig"), "config", "show"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lint = "import sys; from importlinter.cli import lint_imports_command as c; sys.argv[1:] = ['--no-cache']; c()"
    proc = _run([str(py), "-c", lint], cwd=src)
    assert proc.returncode == 0 and " 0 broken" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-2000:]


def test_every_package_folder_is_listed():
    """A new subpackage must be listed in [tool.setuptools] packages, or the wheel would leave it out."""
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {v: k for k, v in conf["package-dir"].items()}
    found = set()
    for folder, name in folders.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((name, *rel)))
    assert found == set(conf["packages"]), f"packages to list or drop: {sorted(found ^ set(conf['packages']))}"


def test_only_scenesig_is_importable_outside_the_checkout(tmp_path):
    code = ("import importlib.util, json; "
            f"print(json.dumps({{m: importlib.util.find_spec(m) is not None for m in {LAYERS!r}}}))")
    proc = _run([sys.executable, "-c", code], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert '"mapping": false' in proc.stdout and "true" not in proc.stdout, proc.stdout
    proc = _run([sys.executable, "-c", "import scenesig.mapping.store, scenesig.benchmarks.heading"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr


def test_a_users_benchmarks_folder_does_not_shadow_ours(tmp_path):
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "__init__.py").write_text("raise SystemExit('the user folder was imported')\n")
    (tmp_path / "benchmarks" / "heading.py").write_text("raise SystemExit('the user folder was imported')\n")
    proc = _run([sys.executable, "-m", "scenesig", "bench", "heading", "--help"], cwd=tmp_path)
    assert proc.returncode == 0 and "user folder" not in proc.stdout + proc.stderr, proc.stdout + proc.stderr


def test_wheel_holds_only_scenesig_and_runs(tmp_path):
    """A built wheel: nothing but ``scenesig/`` (with the package data); installed, the CLI runs."""
    src = _packaging_copy(tmp_path)
    wheels = tmp_path / "wheels"
    proc = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src)], cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (wheel,) = wheels.glob("scenesig-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/", 1)[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"scenesig"}, sorted(tops)
    assert "scenesig/signatures/data/hog_background.npz" in names
    assert "scenesig/benchmarks/heading.py" in names and "scenesig/mapping/build.py" in names
    # every module of the checkout once, at its import path (nothing left out, nothing twice)
    assert sorted(n for n in names if n.endswith(".py")) == _checkout_modules()
    # a fresh environment that sees this machine's dependencies but not this checkout's editable install
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)
    py = env_dir / "bin" / "python"
    proc = _run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    exe = str(env_dir / "bin" / "scenesig")
    api = ("import scenesig, scenesig.mapping.build as b, scenesig.signatures.whiten as w; "
           "assert all(callable(f) for f in (scenesig.build_map, scenesig.localise, scenesig.compare)); "
           "w.load_background(); print(b.__file__)")
    for args in ([exe, "--help"], [exe, "bench", "--help"], [exe, "config", "show"], [str(py), "-c", api]):
        proc = _run(args, cwd=tmp_path)
        assert proc.returncode == 0, (args, proc.stderr[-2000:])
    assert str(env_dir) in proc.stdout, proc.stdout   # the wheel's copy, not the checkout's
