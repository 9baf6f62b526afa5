"""Every frame's uncertainty: 95 % bounds from the pose graph's marginals, and ``covariances.csv``.

The localiser's pose graph (:mod:`scenesig.localiser.posegraph`) holds, at every frame, the marginal covariance of
the vehicle pose given the odometry and the map's localisations (the Gaussian approximation GTSAM's
smoother keeps; McManus et al. 2015, §3.3.2).  This module turns it into what a user of the
localisation reads:

* :func:`planar_covariances` -- the covariance of the planar pose ``(x, y, yaw)`` in the world (map)
  frame, the three quantities a ground vehicle localises: GTSAM's ``Pose3`` marginal is in the vehicle
  frame, rotation first; a translation perturbation ``δt`` moves the world position by ``R δt`` and a
  rotation perturbation about the vehicle's z axis is, on a near-level road, a change of yaw.
* :func:`frame_bounds` -- per frame, ``lateral_bound_95_m`` (across the reference path through the map's
  places, the direction the evaluation's lateral error is measured in, :mod:`scenesig.localiser.evaluation`),
  ``longitudinal_bound_95_m`` (along it) and ``heading_bound_95_deg``: ``z · k · σ`` with
  ``z = 1.96`` (the two-sided 95 % quantile of a normal error) and ``k`` the one inflation factor
  :data:`INFLATION` (see below).  The bounds are relative to the map: the marginal says how well the
  localiser knows its pose in the map's frame; the map's own georeferencing error is not in it.
* ``covariances.csv`` beside ``trajectory.tum`` (written by
  :meth:`scenesig.surveys.localisation.Localisation.write`): one row per pose of the trajectory, ``time, xx, xy, xyaw, yy, yyaw, yawyaw`` -- the upper triangle of the planar 3x3
  covariance in the world frame, in m², m·rad and rad², already inflated by ``k²`` (so it is the
  covariance the bounds come from).  The TUM file itself stays plain (evo reads it).
* :func:`innovation_variance` -- what the marginal leaves out.  The localiser adds to the marginal an
  isotropic planar variance ``(f · ē)²``, ``ē`` the mean planar innovation (how far the detections'
  pose lay from the odometry's prediction) of its last :data:`INNOVATION_WINDOW` localisations and ``f``
  :data:`INNOVATION_FACTOR`.  The marginal only knows the noise models; when successive fixes keep
  disagreeing with the prediction by a metre (a first fix that was off, snow), the pose is not known to
  centimetres whatever the information says.  This is covariance matching, the adaptive estimator's
  check of its stated noise against the innovations it sees (Mehra 1972, "Approaches to adaptive
  filtering"), reduced to one scale: ``k`` then inflates the sum.

**Calibration** (``docs/integrity.md``, "Uncertainty" and "Calibrated on many worlds").  The raw marginal is
a model's statement: the odometry noise model, the solver's information and the Huber prior all shape it.
Whether the stated bounds are honest is measured on data that is not reported: :data:`INFLATION`,
:data:`INNOVATION_WINDOW` and :data:`INNOVATION_FACTOR` were chosen together on the right-map runs of 24
simulated calibration worlds (``scenesig bench integrity --calibrate --choose``): per window, factor and
share of the runs, the smallest inflation with which that share has ``bound_coverage_95`` >= 0.9; kept only if,
chosen on random halves of the worlds, it gives 95 % of the other half's runs that coverage in 97.5 % of the
halvings; of those, the one with the smallest median bound.  The evaluation worlds are the reported hold-out
set.
"""
from __future__ import annotations

import numpy as np

from scenesig.surveys.localisation import (  # noqa: F401  (re-exported: the files are the localisation's)
    BOUND_COLUMNS,
    COVARIANCE_COLUMNS,
    read_covariances_csv,
)

from .evaluation import reference_path

__all__ = ["Z_95", "INFLATION", "INNOVATION_WINDOW", "INNOVATION_FACTOR", "innovation_variance", "BOUND_COLUMNS",
           "COVARIANCE_COLUMNS", "planar_covariances", "frame_bounds", "bounds_from_result", "read_covariances_csv"]

#: two-sided 95 % quantile of a normal distribution
Z_95 = 1.959963984540054
#: the inflation of the standard deviations (see the module docstring, "Calibration"): the raw marginal,
#: with the innovation term below, is overconfident.  Chosen with :data:`INNOVATION_WINDOW` and
#: :data:`INNOVATION_FACTOR` on the 119 right-map runs of 24 calibration worlds (``scenesig bench integrity
#: --seeds 1000-1011,2072-2083 --calibrate --choose --wrong-partners 4``; never reported), localised with a
#: standing vehicle's frames counted as one view (the localiser's ``view_baseline_m``): among the
#: settings with which a share of the runs has bound_coverage_95 >= 0.9 that holds out at >= 95 % in 97.5 %
#: of random halvings of the worlds, the smallest median bound (docs/integrity-history.md, "Sixth calibration";
#: before: 3.9 with a 10-localisation window and factor 0.2 while every standing frame entered the graph,
#: 1.1 with 20 and 0.8, 2.15 with 10 and 0.5, 8.25 on the marginal alone, 5.2 from four demo runs)
INFLATION = 1.75
#: localisations whose planar innovations are averaged into the bound's innovation term (1 s at 5 Hz)
INNOVATION_WINDOW = 5
#: the innovation term's standard deviation per metre of mean innovation (before ``INFLATION``)
INNOVATION_FACTOR = 0.5


def innovation_variance(innovations_m, factor: float = INNOVATION_FACTOR) -> float:
    """The planar variance (m², before the inflation) the localiser adds to the marginal's ``x`` and ``y``:
    ``(factor · mean(innovations_m))²`` over the recent localisations' planar innovations; 0 without any."""
    v = np.asarray(innovations_m, float)
    v = v[np.isfinite(v)]
    return float((factor * v.mean()) ** 2) if v.size else 0.0


def planar_covariances(poses: np.ndarray, covariances: np.ndarray, inflation: float = INFLATION) -> np.ndarray:
    """(N,3,3) covariances of ``(x, y, yaw)`` in the world frame from (N,6,6) ``Pose3`` marginals.

    Parameters
    ----------
    poses : (N,4,4) ``T_world_vehicle``.
    covariances : (N,6,6) marginals in the vehicle frame, GTSAM order ``(rx, ry, rz, tx, ty, tz)``.
    inflation : factor on the standard deviations (``inflation²`` on the covariance).
    """
    T = np.asarray(poses, float).reshape(-1, 4, 4)
    C = np.asarray(covariances, float).reshape(-1, 6, 6)
    R = T[:, :3, :3]
    # J maps the vehicle-frame perturbation (rot, trans) to (x, y, yaw) in the world
    J = np.zeros((len(T), 3, 6))
    J[:, :2, 3:] = R[:, :2, :]
    J[:, 2, :3] = R[:, 2, :]             # world z component of the rotation vector: yaw
    P = J @ C @ np.transpose(J, (0, 2, 1))
    return 0.5 * (P + np.transpose(P, (0, 2, 1))) * float(inflation) ** 2


def frame_bounds(poses: np.ndarray, planar: np.ndarray, path) -> dict:
    """``{column: (N,)}`` of :data:`BOUND_COLUMNS` from (N,3,3) planar covariances (already inflated).

    ``path`` is the reference path (:class:`scenesig.localiser.evaluation.ReferencePath`): lateral is along its
    left normal at the point nearest each estimate, longitudinal along its tangent.  NaN where a
    frame has no pose.
    """
    T = np.asarray(poses, float).reshape(-1, 4, 4)
    P = np.asarray(planar, float).reshape(-1, 3, 3)
    n = len(T)
    out = {c: np.full(n, np.nan) for c in BOUND_COLUMNS}
    ok = np.isfinite(T[:, :2, 3]).all(axis=1) & np.isfinite(P.reshape(n, -1)).all(axis=1)
    if not ok.any():
        return out
    _, left, _ = path.project(T[ok, :3, 3])
    tangent = np.stack([left[:, 1], -left[:, 0]], axis=1)
    Pxy = P[ok, :2, :2]
    var_lat = np.einsum("ni,nij,nj->n", left, Pxy, left)
    var_lon = np.einsum("ni,nij,nj->n", tangent, Pxy, tangent)
    out["lateral_bound_95_m"][ok] = Z_95 * np.sqrt(np.maximum(var_lat, 0.0))
    out["longitudinal_bound_95_m"][ok] = Z_95 * np.sqrt(np.maximum(var_lon, 0.0))
    out["heading_bound_95_deg"][ok] = np.degrees(Z_95 * np.sqrt(np.maximum(P[ok, 2, 2], 0.0)))
    return out


def bounds_from_result(loc, store) -> dict:
    """The 95 % bounds of a :class:`scenesig.surveys.localisation.Localisation`: computed once from the pose
    graph's marginals (kept in its per-frame table and ``planar_covariances``), else those its folder
    recorded; NaN throughout where neither is known."""
    if loc.planar_covariances is None:
        n = len(loc.times)
        if loc.covariances is None:
            loc.planar_covariances = np.full((n, 3, 3), np.nan)
        else:
            planar = planar_covariances(loc.poses, loc.covariances)
            loc.frames = {**loc.frames, **frame_bounds(loc.poses, planar, reference_path(store))}
            loc.planar_covariances = planar
    return loc.bounds
