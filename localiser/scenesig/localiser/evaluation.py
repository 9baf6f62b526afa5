"""Localisation metrics against exact truth (McManus et al. 2015, §4.3-4.4).

* **Lateral error** -- across the reference path: the signed component of ``p_est - p_truth`` along
  the path's left normal (in the ground plane) at the path point nearest the truth; positive means
  the estimate is left of the truth.  **Heading error** -- ``yaw_est - yaw_truth`` wrapped to
  (-180°, 180°].  Each is summarised as ``{"median", "mean", "p95"}`` of absolute values.
* **Blind distance** ``b(s)`` -- distance travelled since the last localisation, along the truth.
  Before the first localisation it is the distance from the start: a replay starts from a known
  pose (the oracle seed), and the failure rule counts its 20 m from there too -- after 5 m of
  driving nothing can be "more than 20 m blind".  An oracle *reset* after a failure, by contrast, is
  not a localisation: the blind distance keeps growing through it, so failures cost blind distance.
  A run that never localises over L metres scores ``10/L`` localised and ``(L-20)/L`` blind.  Frame ``i``'s localisation happens at the end of the segment ``[s_{i-1}, s_i]``, over
  which ``b`` grows linearly; the distance-weighted shares below are integrated exactly.
* ``localised_fraction`` -- share of distance with ``b <= 10 m`` (within 10 m after a localisation,
  one place spacing); ``blind_fraction_over_20m`` -- share with ``b > 20 m``.
* ``failures`` -- the localiser's rule (§4.3): more than 20 m on dead reckoning since the last
  localisation *or reset* is a failure, after which the system is reset and the count restarts.
  Counted from the flags here, or taken from the pipeline's per-frame ``resets`` if given;
  ``failures_per_km`` divides by the distance travelled.
* :func:`dead_reckoning_curve` -- for Fig. 25: P(travelling more than d blind), distance-weighted
  (so its value at 20 m is ``blind_fraction_over_20m``) or per blind stretch.

What the errors are measured against comes from the map: :func:`reference_path` (its places in order)
and :func:`map_relative_truth` (the truth carried into the map's frame).  The other functions take arrays;
the metrics of a localised run are :mod:`scenesig.localiser.outputs`'s.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from scenesig.surveys.geometry import interpolate_poses, yaw_of

from .failure import FAILURE_DISTANCE_M, is_failure

__all__ = ["ReferencePath", "reference_path", "map_relative_truth", "lateral_heading_errors", "blind_distances", "coverage_metrics",
           "dead_reckoning_curve", "summary", "evaluate", "EvaluationResult", "travelled"]


class ReferencePath:
    """The reference path as a polyline in the ground (x-y) plane.

    Parameters
    ----------
    path : (M,4,4) poses (e.g. the map places' ``T_world_place`` or the reference run's truth) or
        (M,2|3) positions, in driving order; M >= 2.
    """

    def __init__(self, path: np.ndarray):
        path = np.asarray(path, dtype=float)
        if path.ndim == 3 and path.shape[1:] == (4, 4):
            xy = path[:, :2, 3]
        elif path.ndim == 2 and path.shape[1] in (2, 3):
            xy = path[:, :2]
        else:
            raise ValueError(f"path must be (M,4,4) poses or (M,2|3) positions, got {path.shape}")
        if not np.all(np.isfinite(xy)):
            raise ValueError("path contains non-finite values")
        # Drop repeated vertices: a zero-length segment has no tangent.
        keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9])
        xy = xy[keep]
        if len(xy) < 2:
            raise ValueError("path needs at least 2 distinct positions")
        self.xy = xy
        self._tree = cKDTree(xy)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest path points of (N,2|3) points.

        Returns
        -------
        foot : (N,2) nearest point on the polyline.
        left : (N,2) unit left normal of the path there.
        distance : (N,) distance of each point from the path.
        """
        P = np.atleast_2d(np.asarray(points, dtype=float))[:, :2]
        M = len(self.xy)
        k = min(4, M)
        _, idx = self._tree.query(P, k=k)
        idx = idx.reshape(len(P), k)
        best_d = np.full(len(P), np.inf)
        foot = np.zeros_like(P)
        tangent = np.zeros_like(P)
        # The nearest segment ends at one of the nearest vertices: check the segments on both sides.
        for col in range(k):
            for off in (-1, 0):
                a_i = np.clip(idx[:, col] + off, 0, M - 2)
                a, b = self.xy[a_i], self.xy[a_i + 1]
                ab = b - a
                u = np.clip(np.einsum("ij,ij->i", P - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
                f = a + u[:, None] * ab
                d = np.linalg.norm(P - f, axis=1)
                better = d < best_d - 1e-12
                best_d[better] = d[better]
                foot[better] = f[better]
                tangent[better] = ab[better] / np.linalg.norm(ab[better], axis=1, keepdims=True)
        left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
        return foot, left, best_d


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return -((-np.asarray(a) + 180.0) % 360.0 - 180.0)


def lateral_heading_errors(est_poses: np.ndarray, truth_poses: np.ndarray, path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed lateral (m) and heading (deg) errors of estimates against truth at the same times.

    Parameters
    ----------
    est_poses, truth_poses : (N,4,4) ``T_world_vehicle``.
    path : :class:`ReferencePath` or what its constructor takes.

    Returns
    -------
    lateral_m : (N,) ``(p_est - p_truth) · left normal of the path at the truth's nearest point``.
    heading_deg : (N,) ``yaw_est - yaw_truth`` wrapped to (-180, 180].
    path_distance_m : (N,) distance of the truth from the path (to exclude off-map stretches).
    """
    est = np.asarray(est_poses, dtype=float)
    tru = np.asarray(truth_poses, dtype=float)
    if est.shape != tru.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"est_poses and truth_poses must both be (N,4,4), got {est.shape} and {tru.shape}")
    ref = path if isinstance(path, ReferencePath) else ReferencePath(path)
    _, left, dist = ref.project(tru[:, :3, 3])
    lateral = np.einsum("ij,ij->i", est[:, :2, 3] - tru[:, :2, 3], left)
    heading = _wrap_deg(np.degrees(yaw_of(est) - yaw_of(tru)))
    return lateral, heading, dist


def travelled(positions: np.ndarray) -> np.ndarray:
    """Cumulative distance (m) along (N,3) positions, starting at 0."""
    P = np.asarray(positions, dtype=float)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])


def _check_flags(distances, localised, resets=None):
    s = np.asarray(distances, dtype=float)
    loc = np.asarray(localised, dtype=bool)
    if s.ndim != 1 or loc.shape != s.shape:
        raise ValueError(f"distances and localised must be 1-D of equal length, got {s.shape} and {loc.shape}")
    if len(s) and (not np.all(np.isfinite(s)) or np.any(np.diff(s) < 0)):
        raise ValueError("distances must be finite and non-decreasing (cumulative distance travelled)")
    if resets is not None:
        resets = np.asarray(resets, dtype=bool)
        if resets.shape != s.shape:
            raise ValueError(f"resets must match distances, got {resets.shape} and {s.shape}")
    return s, loc, resets


def blind_distances(distances, localised) -> np.ndarray:
    """Distance since the last localisation at each frame (0 at a localised frame; before the first,
    the distance since the start)."""
    s, loc, _ = _check_flags(distances, localised)
    if not len(s):
        return s.copy()
    last = np.where(loc, s, -np.inf)
    last[0] = s[0]                      # the start pose is known (oracle seed)
    return s - np.maximum.accumulate(last)


def _over(b_prev: np.ndarray, step: np.ndarray, d) -> np.ndarray:
    """Length of each segment over which the blind distance (b_prev -> b_prev + step) exceeds d.

    A scalar ``d`` gives (N,); an array (G,) gives (G, N).
    """
    d = np.asarray(d, dtype=float)
    if d.ndim:
        d = d[:, None]
    return np.clip(b_prev + step - d, 0.0, step)


def coverage_metrics(distances, localised, resets=None, failure_distance_m: float = FAILURE_DISTANCE_M,
                     localised_within_m: float = 10.0, blind_over_m: float = FAILURE_DISTANCE_M) -> dict:
    """``localised_fraction``, ``failures``, ``failures_per_km``, ``blind_fraction_over_20m``.

    Parameters
    ----------
    distances : (N,) cumulative distance travelled at each frame (m).
    localised : (N,) True where a localisation was accepted at that frame.
    resets : (N,) True where the pipeline reset from the oracle; if None the failures are counted
        by applying the rule to ``localised``.
    """
    s, loc, resets = _check_flags(distances, localised, resets)
    total = float(s[-1] - s[0]) if len(s) else 0.0
    if len(s) >= 2:
        b = blind_distances(s, loc)
        step = np.diff(s)
        b_prev = b[:-1]
        within = float((step - _over(b_prev, step, localised_within_m)).sum())
        over = float(_over(b_prev, step, blind_over_m).sum())
    else:
        within = over = 0.0
    if resets is not None:
        failures = int(resets.sum())
    else:
        failures, c = 0, 0.0
        for i in range(1, len(s)):
            c += s[i] - s[i - 1]
            if is_failure(c, failure_distance_m):
                failures += 1
                c = 0.0
            if loc[i]:
                c = 0.0
    return {
        # shares of a distance, summed segment by segment: rounding can land a hair outside [0, 1]
        "localised_fraction": _fraction(within, total),
        "failures": failures,
        "failures_per_km": failures / (total / 1000.0) if total > 0 else None,
        "blind_fraction_over_20m": _fraction(over, total),
        "distance_m": total,
    }


def _fraction(part: float, total: float) -> float | None:
    """``part / total`` clamped to [0, 1] (None without a total)."""
    return float(min(1.0, max(0.0, part / total))) if total > 0 else None


def dead_reckoning_curve(distances, localised, d_grid, weighting: str = "distance") -> np.ndarray:
    """P(travelling more than d blind) for each d in ``d_grid`` (Fig. 25).

    ``weighting="distance"``: share of the distance travelled that lies more than d past the last
    localisation (equals ``blind_fraction_over_20m`` at d = 20).  ``weighting="stretch"``: share of
    blind stretches (start -> first localisation, between localisations, last -> end) longer than d.
    """
    s, loc, _ = _check_flags(distances, localised)
    d_grid = np.asarray(d_grid, dtype=float)
    if len(s) < 2 or s[-1] == s[0]:
        return np.full(d_grid.shape, np.nan)
    if weighting == "distance":
        b = blind_distances(s, loc)
        step = np.diff(s)
        return _over(b[:-1], step, d_grid).sum(axis=-1) / (s[-1] - s[0])
    if weighting == "stretch":
        marks = np.concatenate([[s[0]], s[loc], [s[-1]]])
        lengths = np.diff(marks)
        # A localisation on the first or last frame leaves no stretch before / after it.
        lengths = lengths[int(loc[0]):len(lengths) - int(loc[-1])]
        if not len(lengths):
            return np.zeros(d_grid.shape)
        return (lengths[None, :] > d_grid[:, None]).mean(axis=1)
    raise ValueError(f"weighting must be 'distance' or 'stretch', got {weighting!r}")


def summary(values) -> dict:
    """``{"median", "mean", "p95"}`` of absolute finite values (None when there are none)."""
    v = np.abs(np.asarray(values, dtype=float))
    v = v[np.isfinite(v)]
    if not len(v):
        return {"median": None, "mean": None, "p95": None}
    return {"median": float(np.median(v)), "mean": float(np.mean(v)), "p95": float(np.percentile(v, 95))}


@dataclass
class EvaluationResult:
    """Metrics (``metrics.json`` fields) and the per-frame series behind them (``frames.csv``)."""

    metrics: dict
    lateral_m: np.ndarray           # signed, NaN where not evaluated
    heading_deg: np.ndarray         # signed, NaN where not evaluated
    blind_m: np.ndarray             # distance since the last localisation (or the start)
    distance_m: np.ndarray          # cumulative distance travelled (truth)


def evaluate(times, est_poses, truth_times, truth_poses, path, localised, resets=None,
             max_path_distance_m: float | None = None) -> EvaluationResult:
    """All metrics of one localised run.

    Parameters
    ----------
    times : (N,) frame times of the estimates.
    est_poses : (N,4,4) estimated ``T_world_vehicle``.
    truth_times, truth_poses : exact truth; interpolated (SLERP) at ``times``.  Frames outside the
        truth's time span are not evaluated.
    path : reference path (:class:`ReferencePath`, (M,4,4) poses or (M,2|3) positions).
    localised : (N,) per-frame localisation flags.
    resets : (N,) per-frame oracle-reset flags from the pipeline (optional; see :func:`coverage_metrics`).
    max_path_distance_m : frames whose truth is further than this from the path are left out of the
        error statistics (the paper reports errors on mapped segments only); None keeps all.
    """
    times = np.asarray(times, dtype=float)
    est = np.asarray(est_poses, dtype=float)
    tt = np.asarray(truth_times, dtype=float)
    if est.shape != (len(times), 4, 4):
        raise ValueError(f"est_poses must be ({len(times)},4,4) to match times, got {est.shape}")
    if len(tt) == 0:
        raise ValueError("truth is empty")
    truth = interpolate_poses(tt, truth_poses, times).reshape(-1, 4, 4)
    lateral, heading, pdist = lateral_heading_errors(est, truth, path)
    valid = (times >= tt[0] - 1e-9) & (times <= tt[-1] + 1e-9)
    if max_path_distance_m is not None:
        valid &= pdist <= max_path_distance_m
    lateral = np.where(valid, lateral, np.nan)
    heading = np.where(valid, heading, np.nan)
    dist = travelled(truth[:, :3, 3])
    cov = coverage_metrics(dist, localised, resets)
    metrics = {"lateral_error_m": summary(lateral), "heading_error_deg": summary(heading),
               "localised_fraction": cov["localised_fraction"], "failures": cov["failures"],
               "failures_per_km": cov["failures_per_km"],
               "blind_fraction_over_20m": cov["blind_fraction_over_20m"],
               "distance_m": cov["distance_m"], "frames_evaluated": int(valid.sum())}
    return EvaluationResult(metrics, lateral, heading, blind_distances(dist, localised), dist)


def reference_path(store) -> ReferencePath:
    """The reference path: the map's places in order, closed if the route is a loop."""
    ids = sorted(store.places)
    poses = np.stack([store.places[i].T_world_place for i in ids])
    if len(ids) > 2 and ids[-1] in store.places[ids[0]].neighbours:
        poses = np.concatenate([poses, poses[:1]])
    return ReferencePath(poses)


def map_relative_truth(store, truth_poses: np.ndarray) -> np.ndarray | None:
    """Truth expressed in the map's frame, or None when the map does not record its places' truth.

    The map's frame is realised by the training runs' INS (combined per place by
    :mod:`scenesig.mapping.georef`), whose error (metres, for a GPS-aided INS) every place carries.  A simulated map records each place's exact pose (``extra["T_truth_place"]``),
    so a true pose can be carried into the map frame through the nearest place:
    ``T_world_place · T_truth_place⁻¹ · T_truth``.  Errors against that are the localiser's own;
    errors against the raw truth add the map's georeferencing error, which no localiser can remove.
    """
    ids = sorted(store.places)
    if not ids or any("T_truth_place" not in store.places[i].extra for i in ids):
        return None
    Tw = np.stack([store.places[i].T_world_place for i in ids])
    Tt = np.stack([np.asarray(store.places[i].extra["T_truth_place"], float) for i in ids])
    P = np.asarray(truth_poses, float).reshape(-1, 4, 4)
    near = np.argmin(np.linalg.norm(P[:, None, :3, 3] - Tt[None, :, :3, 3], axis=2), axis=1)
    corr = Tw @ np.linalg.inv(Tt)             # (K,4,4) truth -> map frame at each place
    return corr[near] @ P
