"""scenesig: the application layer -- the ``scenesig`` command line, the demo, the report, the experiments,
and the front door of the library:

* :func:`scenesig.build_map` -- survey runs -> a map (the build summary);
* :func:`scenesig.localise` -- a map and a run -> a :class:`scenesig.api.Localisation` in memory (times,
  poses, the per-frame table, ``metrics``, ``write(dir)``);
* :func:`scenesig.compare` -- a map, runs and methods -> one row of metrics per run and method;
* :class:`scenesig.Session` -- the online localiser, frame by frame (odometry, GNSS, images as arrays);
* :class:`scenesig.Map` -- ``Map.open(path)``: a map's layers, places, identity, settings and build summary.

They are imported on first use (``import scenesig`` stays light).  The library packages below
(``localiser`` → ``mapping`` → ``signatures`` → ``surveys``) expose plain functions and never import this
package; see ``docs/architecture.md`` and ``docs/api.md``.
"""
from __future__ import annotations

from pathlib import Path as _Path

__all__ = ["build_map", "localise", "compare", "Map", "Session"]

# Each library layer is a source root of this package in the checkout (``mapping/scenesig/mapping/build.py``
# is ``scenesig.mapping.build``; the application layer's root is the repository itself).  Installed from a
# wheel every subpackage sits in this folder and nothing is added; in the checkout (``python -m scenesig``,
# pytest, an editable install) the layer roots are appended to ``__path__`` in place, so that the package's
# spec (what grimp and ``importlib.util.find_spec`` read) lists them too.
_LAYERS = ("surveys", "signatures", "mapping", "localiser", "aerial", "benchmarks")
_CHECKOUT = _Path(__file__).resolve().parent.parent
if (_CHECKOUT / "pyproject.toml").is_file():
    __path__.extend(str(_CHECKOUT / layer / "scenesig") for layer in _LAYERS
                    if (_CHECKOUT / layer / "scenesig" / layer / "__init__.py").is_file()
                    and str(_CHECKOUT / layer / "scenesig") not in __path__)


def __getattr__(name):
    if name == "Map":
        from scenesig.maps import Map

        return Map
    if name == "Session":
        from scenesig.session import Session

        return Session
    if name in __all__:
        from scenesig import api

        return getattr(api, name)
    raise AttributeError(f"module 'scenesig' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
