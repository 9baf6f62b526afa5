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

__all__ = ["build_map", "localise", "compare", "Map", "Session"]


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
