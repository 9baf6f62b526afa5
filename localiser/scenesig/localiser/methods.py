"""Weak localisers: their interface and the method registry (McManus et al. 2015, §3.3).

A *weak localiser* (McManus et al. 2015, §3.3.1) is any method that, given a live image, a place and a motion prior,
returns a localisation constraint or nothing.  :class:`WeakLocaliser` is that interface, split into
``detect`` (image -> observation, the detector thread) and ``solve`` (observation -> :class:`Measurement`,
the solver thread) so the real-time replay can run them concurrently; ``measure`` chains them.
:class:`MotionPrior` is what the localiser block (:class:`scenesig.localiser.pipeline.Localiser`) hands a method
for one frame, :class:`Measurement` what the method answers.

The registry names the methods: :func:`register_method`, :func:`available_methods`, :func:`make_method`.
Scene signatures (:mod:`scenesig.localiser.signature_method`), point features (:mod:`scenesig.localiser.pointmethod`)
and the hybrid (:mod:`scenesig.localiser.hybrid`) register themselves; the registry imports each module by
name on first use, so this module imports none of them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import Camera, invert

from .solver import LocalisationConstraint

__all__ = ["MotionPrior", "Measurement", "WeakLocaliser", "register_method", "make_method", "available_methods",
           "method_settings"]


# ------------------------------------------------------------------------------------------------
# data passed between the blocks
# ------------------------------------------------------------------------------------------------
@dataclass
class MotionPrior:
    """What the localiser tells the detector and solver for one frame.

    Attributes
    ----------
    t : time of the frame.
    T_world_vehicle : (4,4) snapped estimate at ``t`` (the motion prior T̂).
    covariance : (6,6) its covariance P_x (GTSAM Pose3 convention, vehicle frame), floored.
    place : the nearest place (index); ``T_world_place`` its pose.
    next_place : the place ahead (to prefetch), or None.
    lost : True when the estimate is not good enough to search around predicted projections.
    distance_since_localisation : odometry distance since the last localisation or reset (m).
    max_classifiers : global localisation's verification budget per place (methods may ignore it).
    """

    t: float
    T_world_vehicle: np.ndarray
    covariance: np.ndarray
    place: int
    T_world_place: np.ndarray
    next_place: int | None
    lost: bool
    distance_since_localisation: float
    max_classifiers: int | None = None   # a whole-image search may run only this many (the best) classifiers

    @property
    def T_place_vehicle(self) -> np.ndarray:
        """The prior in the place frame (what the solver and the detector windows use)."""
        return invert(self.T_world_place) @ self.T_world_vehicle


@dataclass
class Measurement:
    """A weak localiser's answer for one frame: a constraint or none, with counts and timings."""

    constraint: LocalisationConstraint | None
    detections: int = 0
    inliers: int = 0
    reason: str | None = None
    ms_detect: float = 0.0
    ms_solve: float = 0.0
    solved: bool = False          # the solver ran (enough detections to try)
    extra: dict = field(default_factory=dict)

    @classmethod
    def coerce(cls, result) -> "Measurement":
        """A Measurement from what a method returned: a Measurement, a bare constraint, or None."""
        if isinstance(result, Measurement):
            return result
        if result is None:
            return cls(None, reason="no_measurement")
        if isinstance(result, LocalisationConstraint):
            return cls(result, reason=None, solved=True)
        raise TypeError(f"a weak localiser must return a Measurement, a LocalisationConstraint or None, "
                        f"got {type(result).__name__}")


# ------------------------------------------------------------------------------------------------
# the method interface
# ------------------------------------------------------------------------------------------------
class WeakLocaliser:
    """Interface of a weak localiser (McManus et al. 2015, §3.3.1): image + place + motion prior -> constraint or none.

    Implement either :meth:`measure` alone (a single-stage method: then :meth:`detect` does all the
    work and :meth:`solve` passes its answer on), or :meth:`detect` and :meth:`solve` (two stages,
    which the real-time replay runs in the detector and solver threads).

    Attributes
    ----------
    name : method name (``metrics.json``'s ``method``).
    color : True if the method wants BGR images, False for gray.
    """

    name = "weak"
    color = False

    def method_config(self) -> dict:
        """The settings that produce this method's results (``metrics.json``'s ``method_config``)."""
        return {"method": self.name}

    def prefetch(self, place: int | None) -> None:
        """Prepare a place that is coming up (e.g. decode its bank in the background)."""

    def prepare(self, image: np.ndarray):
        """The part of detection that needs the image only -- neither the place nor the prior.

        The replay may call it on another thread, ahead of :meth:`detect` (e.g. point-feature
        extraction for the next frame while the current one is solved), and then passes its result
        to :meth:`detect` in place of the image; :meth:`detect` must accept both.  Default: nothing
        to do (the image itself).
        """
        return image

    def detect(self, image: np.ndarray, place: int, prior: MotionPrior):
        """Detector stage: image -> observation (anything :meth:`solve` understands)."""
        if type(self).measure is WeakLocaliser.measure:
            raise NotImplementedError(f"{type(self).__name__} must implement measure() or detect() and solve()")
        return self.measure(image, place, prior)

    def solve(self, observation, place: int, prior: MotionPrior) -> Measurement | LocalisationConstraint | None:
        """Solver stage: observation -> :class:`Measurement` (a single-stage method's detect already answered)."""
        return observation

    def measure(self, image: np.ndarray, place: int, prior: MotionPrior) -> Measurement | LocalisationConstraint | None:
        """Both stages: a localisation constraint (in a :class:`Measurement`), or None."""
        if type(self).detect is WeakLocaliser.detect:
            raise NotImplementedError(f"{type(self).__name__} must implement measure() or detect() and solve()")
        return self.solve(self.detect(image, place, prior), place, prior)

    def close(self) -> None:
        """Release threads and caches."""


_METHODS: dict[str, Callable] = {}
# Methods provided by other modules, imported on first use (they call register_method).  The
# scene-signature method is one of them (scenesig.localiser.signature_method imports this module, so it
# registers itself rather than being imported here); scenesig.localiser.pipeline imports it eagerly.
_LAZY = {"signatures": "scenesig.localiser.signature_method"}
_LAZY.update({name: "scenesig.localiser.pointmethod" for name in ("orb", "sift", "xfeat", "orb-all", "sift-all", "xfeat-all")})
_LAZY.update({name: "scenesig.localiser.hybrid" for name in ("hybrid", "hybrid-orb", "hybrid-sift-all", "hybrid-orb-all")})


_SETTINGS: dict[str, Callable] = {}


def register_method(name: str, factory: Callable, settings: Callable | None = None) -> None:
    """Make ``factory(store, camera, T_vehicle_camera, config) -> WeakLocaliser`` available as ``name``.

    ``settings(config) -> dict`` resolves the method's every setting from ``config`` (its overrides),
    raising ``ValueError`` on a key the method does not have: what ``scenesig config show`` and
    ``metrics.json`` report.  Without it the method's settings are reported as given.
    """
    _METHODS[name] = factory
    if settings is None:
        _SETTINGS.pop(name, None)
    else:
        _SETTINGS[name] = settings


def available_methods() -> list[str]:
    return sorted(set(_METHODS) | set(_LAZY))


def _load(name: str) -> None:
    if name not in _METHODS and name in _LAZY:
        import importlib

        importlib.import_module(_LAZY[name])


def make_method(name: str, store: MapStore, camera: Camera, T_vehicle_camera, config: dict | None = None) -> WeakLocaliser:
    """Instantiate a registered method (``signatures``, ``orb``, ``sift``, ...)."""
    _load(name)
    if name not in _METHODS:
        raise ValueError(f"unknown method {name!r}; available: {available_methods()}")
    return _METHODS[name](store, camera, T_vehicle_camera, config)


def method_settings(name: str, config: dict | None = None) -> dict:
    """The resolved settings of method ``name`` (its registered ``settings`` resolver applied to
    ``config``); a method registered without one, or a name not registered (a localiser object
    passed to the replay directly), gets its overrides back as given."""
    _load(name)
    resolve = _SETTINGS.get(name)
    return resolve(config) if resolve is not None else dict(config or {})
