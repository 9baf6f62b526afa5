"""``scenesig.Session``: the online localiser of :mod:`scenesig.localiser.session` with the front door's settings
presets (:mod:`scenesig.presets`), as :func:`scenesig.localise` takes them.

::

    import scenesig

    s = scenesig.Session("maps/demo", camera, T_vehicle_camera, method="signatures", oracle="gnss")
    s.add_gnss(t, T_world_vehicle); s.add_odometry(t, T_increment)
    fix = s.add_image(t, image)         # Fix (pose, 6x6 covariance, lateral bound, place, inliers) or None

See ``docs/api.md``, "Session".
"""
from __future__ import annotations

from scenesig.localiser.session import STATES, Estimate, Fix, FrameReport, Session as _Session
from scenesig.presets import apply_preset

__all__ = ["Session", "Fix", "Estimate", "FrameReport", "STATES"]


class Session(_Session):
    """:class:`scenesig.localiser.session.Session` (every parameter and method), the map also as a
    :class:`scenesig.Map`, taking ``preset``: a settings
    preset (:data:`scenesig.presets.PRESETS`) of the ``localise`` stage under ``config`` (the caller's win).
    The replay-only settings of that stage (``prefetch``, ``odometry_queue``, ``max_path_distance_m``,
    ``oracle``) have no meaning online and are refused by name."""

    def __init__(self, map, camera, T_vehicle_camera, method="signatures", oracle=None, config: dict | None = None,
                 preset: str | None = None, retrieval=None):
        from scenesig.maps import Map

        if isinstance(map, Map):        # the front door's map object: its open store
            map = map.store
        super().__init__(map, camera, T_vehicle_camera, method=method, oracle=oracle,
                         config=apply_preset("localise", config, preset), retrieval=retrieval)
