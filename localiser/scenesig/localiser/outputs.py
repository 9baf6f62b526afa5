"""What ``scenesig localise`` writes, and reads back: ``trajectory.tum``, ``covariances.csv``,
``frames.csv``, ``metrics.json``.

:func:`compute_metrics` turns a :class:`scenesig.localiser.replay.ReplayResult` into the ``metrics.json`` content:
what the localiser knows (:func:`localisation_metrics`, no truth needed) and, where the run has truth,
the evaluation against it (:func:`truth_metrics`: errors across the reference path through the map's
places, see :mod:`scenesig.localiser.evaluation`); :func:`write_outputs` writes the files (and ``trajectory.png``,
:mod:`scenesig.localiser.plots`) atomically, the trajectory first; :func:`evaluate_folder` runs the evaluation on a
finished output folder (``scenesig evaluate``).  :data:`FRAMES_COLUMNS` is the one definition of ``frames.csv``'s
columns, used by its writer and its reader :func:`read_frames_csv`.
"""
from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.errors import DataError
from scenesig.surveys.io import atomic_write_text, make_dirs
from scenesig.surveys.run import read_run
from scenesig.surveys.tum import read_tum, write_tum
from scenesig.surveys.validation import csv_header

from .evaluation import ReferencePath, evaluate, summary
from .uncertainty import INFLATION

if TYPE_CHECKING:
    from .replay import ReplayResult

__all__ = ["FRAMES_COLUMNS", "TIMING_KEYS", "FALSE_FIX_M", "reference_path", "map_relative_truth", "compute_metrics",
           "write_frames_csv", "frames_csv_text", "read_frames_csv", "write_outputs", "detection_rates",
           "inlier_types", "read_output_files",
           "read_localisation"]

#: Columns of ``frames.csv`` (the errors are NaN without truth; the bounds NaN without a pose; ``integrity_alert``
#: 1 where the integrity monitor refused the frame's fix, :mod:`scenesig.localiser.integrity`).
FRAMES_COLUMNS = ("time", "place", "detections", "inliers", "localised", "lateral_error", "heading_error",
                  "distance_since_localisation", "lateral_bound_95_m", "longitudinal_bound_95_m",
                  "heading_bound_95_deg", "integrity_alert", "signature_inliers", "point_inliers")
#: the 95 % bounds (NaN without a pose)
BOUND_COLUMNS = FRAMES_COLUMNS[8:11]
#: the per-type inlier counts (which measurement types the solver used; hybrid: both), integers
_COUNT_COLUMNS = ("signature_inliers", "point_inliers")
#: the columns an output folder written before the bounds existed has (still read)
_FRAMES_REQUIRED = FRAMES_COLUMNS[:8]
#: ``metrics.json`` entries that measure the machine rather than the result (they differ between runs).
TIMING_KEYS = ("ms_per_detection", "ms_per_solve", "ms_per_odometry_update", "ms_per_retrieval", "realtime_factor",
               "wall_seconds", "cpu_seconds", "cpu_ms_per_frame")
#: Accepted localisations further than this from the truth are ``false_fixes`` (metres).
FALSE_FIX_M = 5.0


def reference_path(store: MapStore) -> ReferencePath:
    """The reference path: the map's places in order, closed if the route is a loop."""
    ids = sorted(store.places)
    poses = np.stack([store.places[i].T_world_place for i in ids])
    if len(ids) > 2 and ids[-1] in store.places[ids[0]].neighbours:
        poses = np.concatenate([poses, poses[:1]])
    return ReferencePath(poses)


def map_relative_truth(store: MapStore, truth_poses: np.ndarray) -> np.ndarray | None:
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


def compute_metrics(result: ReplayResult, store: MapStore, max_path_distance_m: float | None = None):
    """``metrics.json`` content and the evaluation behind it (per-frame errors, or NaN without truth).

    Two parts, so a localisation needs no truth (a vehicle localising has none).

    **What the localiser knows** (:func:`localisation_metrics`, always): ``method``, ``run``,
    ``conditions``, ``localised_fraction``, ``failures`` (oracle resets), ``failures_per_km``,
    ``blind_fraction_over_20m``, ``distance_m`` (along the truth where there is one, else along the
    odometry: :func:`odometry_distances`); localising without INS/GPS: ``oracle``, ``oracle_reads``,
    ``first_fix_m``, ``relocalisations``, ``relocalise_m``; the times that let the evaluation run on its
    own later (``reset_times``, ``first_fix_time``, ``relocalisation_times``); the uncertainty
    ``lateral_bound_95_m_median`` (:mod:`scenesig.localiser.uncertainty`); timings ``ms_per_detection``,
    ``ms_per_solve``, ``ms_per_odometry_update``, ``ms_per_retrieval`` (global search only),
    ``realtime_factor`` (data duration / wall time of the replay), ``wall_seconds``; bookkeeping
    ``mode``, ``every``, ``duration_s``, ``frames``, ``detector_frames``, ``localisations``,
    ``truth_source``, ``map``, ``map_id`` and ``map_generation`` (the map's identity and lifelong
    generation, :mod:`scenesig.mapping.identity`), ``run_path`` (the run folder, for ``scenesig map update``);
    detection rates ``detections_per_frame_mean`` and ``inliers_per_detection_mean``
    (:func:`detection_rates`); ``frames_corrupt`` and ``corrupt_frames`` (frames skipped: image truncated
    or corrupt); ``method_config`` (the method's settings); ``settings`` (every setting of the replay,
    resolved: ``replay``, ``localiser``, ``posegraph``, ``integrity``, ``method``, and ``relocalise`` without
    INS/GPS -- :func:`scenesig.localiser.replay.resolve_config`); the integrity monitor's ``integrity_alerts``,
    ``integrity_alert_frames`` and ``integrity_alert_list`` (:mod:`scenesig.localiser.integrity`) and the camera
    check's ``camera_check`` (:mod:`scenesig.mapping.camera_check`); and in real-time mode ``frames_dropped``,
    ``frames_detected``, ``odometry_queue_max``, ``odometry_coalesced`` and ``lag_max_s``.

    **The evaluation against truth** (:func:`truth_metrics`, only where the run has ``truth.tum``, else
    ``groundtruth.tum``: ``truth_source``; ``"none"`` without either, and then none of these keys):
    ``lateral_error_m`` and ``heading_error_deg`` (``{"median", "mean", "p95"}`` of absolute errors,
    lateral = across the reference path through the map's places; :mod:`scenesig.localiser.evaluation`),
    ``frames_evaluated``, ``false_fixes``; where the map records its places' truth (simulated maps)
    ``lateral_error_map_m``, ``heading_error_map_deg`` (relative to the map, see
    :func:`map_relative_truth`) and ``map_georeference_error_m``; ``bound_coverage_95`` and
    ``bound_coverage_95_all`` (:func:`bound_coverage`).  The same function runs on a finished output
    folder: :func:`evaluate_folder` (``scenesig evaluate``).
    """
    truth = run_truth(result.run)
    metrics = localisation_metrics(result, store, None if truth is None else truth[:2])
    if truth is None:
        return metrics, _odometry_evaluation(result)
    tm, ev = truth_metrics(result, store, *truth, max_path_distance_m=max_path_distance_m)
    return merge_truth_metrics(metrics, tm), ev


#: ``metrics.json`` keys that exist only with truth (:func:`truth_metrics`); dropped before a re-evaluation.
TRUTH_KEYS = ("lateral_error_m", "heading_error_deg", "frames_evaluated", "false_fixes", "lateral_error_map_m",
              "heading_error_map_deg", "map_georeference_error_m", "bound_coverage_95", "bound_coverage_95_all")


def run_truth(run):
    """``(times, poses, source)`` of the run's truth -- ``truth.tum``, else ``groundtruth.tum`` -- or None."""
    if getattr(run, "truth_times", None) is not None:
        return run.truth_times, run.truth_poses, "truth"
    if getattr(run, "groundtruth_times", None) is not None:
        return run.groundtruth_times, run.groundtruth_poses, "groundtruth"
    return None


def odometry_distances(run, times) -> np.ndarray:
    """Cumulative distance (m) travelled along the run's odometry at ``times`` (the localiser's own
    measure of distance, used for the coverage figures where there is no truth)."""
    from scenesig.surveys.geometry import interpolate_poses

    from .evaluation import travelled

    P = interpolate_poses(run.odometry_times, run.odometry_poses, np.clip(times, run.odometry_times[0],
                                                                          run.odometry_times[-1]))
    return travelled(np.asarray(P).reshape(-1, 4, 4)[:, :3, 3])


def _odometry_evaluation(result):
    """The :class:`EvaluationResult` without truth: distances along the odometry, errors NaN."""
    from .evaluation import EvaluationResult, blind_distances

    n = len(result.times)
    dist = odometry_distances(result.run, result.times) if n else np.zeros(0)
    return EvaluationResult({}, np.full(n, np.nan), np.full(n, np.nan),
                            blind_distances(dist, np.asarray(result.localised, bool)), dist)


def localisation_metrics(result: ReplayResult, store: MapStore, truth=None) -> dict:
    """The part of ``metrics.json`` that needs no truth (see :func:`compute_metrics`).  ``truth``
    ``(times, poses)``, where given, only measures the distances (else the odometry does)."""
    from scenesig.surveys.geometry import interpolate_poses

    from .evaluation import coverage_metrics, travelled
    from .uncertainty import bounds_from_result

    run = result.run
    tm = result.timings
    n = len(result.times)
    if truth is not None and n:
        dist = travelled(interpolate_poses(truth[0], truth[1], result.times).reshape(-1, 4, 4)[:, :3, 3])
    else:
        dist = odometry_distances(run, result.times) if n else np.zeros(0)
    cov = coverage_metrics(dist, result.localised, result.resets)
    if not np.asarray(result.valid, bool).all():
        # without INS/GPS the coverage counts from the first fix on (before it there is no pose)
        v = np.asarray(result.valid, bool)
        if v.sum() >= 2:
            cov = coverage_metrics(dist[v], result.localised[v], result.resets[v])
        else:
            cov = {"localised_fraction": 0.0, "failures": int(result.failures), "failures_per_km": None,
                   "blind_fraction_over_20m": None, "distance_m": float(dist[-1]) if n else 0.0}
    bounds = bounds_from_result(result, store)
    metrics = {
        "method": result.method,
        "run": run.name,
        "conditions": list(run.conditions),
        "localised_fraction": cov["localised_fraction"],
        "failures": int(result.failures),
        "failures_per_km": cov["failures_per_km"],
        "blind_fraction_over_20m": cov["blind_fraction_over_20m"],
        **_oracle_metrics(result, dist),
        "lateral_bound_95_m_median": _median(bounds["lateral_bound_95_m"][np.asarray(result.localised, bool)]),
        "bound_inflation": INFLATION,     # the calibrated factor on the marginal's sigmas (localiser.uncertainty)
        "ms_per_detection": tm.get("ms_per_detection"),
        "ms_per_solve": tm.get("ms_per_solve"),
        "ms_per_odometry_update": tm.get("ms_per_odometry_update"),
        "ms_per_retrieval": tm.get("ms_per_retrieval"),
        "realtime_factor": tm.get("realtime_factor"),
        "wall_seconds": tm.get("wall_seconds"),
        "cpu_seconds": tm.get("cpu_seconds"),
        "cpu_ms_per_frame": tm.get("cpu_ms_per_frame"),
        "mode": result.mode,
        "every": result.every,
        "distance_m": cov["distance_m"],
        "duration_s": tm.get("duration_s"),
        "frames": int(n),
        "detector_frames": int(result.detector_ran.sum()),
        "localisations": int(result.localised.sum()),
        **detection_rates(result.detections[result.detector_ran], result.inliers[result.detector_ran]),
        **inlier_types(result),
        "truth_source": "none",
        "map": str(store.root),
        # frames whose image failed strict decoding (truncated or corrupt): skipped, odometry went on
        "frames_corrupt": len(result.corrupt),
        "corrupt_frames": [run.frame_files[i] for i in result.corrupt] if run.frame_files else [],
        "method_config": result.method_config,
        # every setting behind the result, resolved: replay, localiser, pose graph, method (+ relocaliser)
        "settings": getattr(result, "settings", None) or {},
        "map_id": store.map_id,
        "map_generation": int(store.generation),
        "run_path": str(Path(run.root).resolve()) if run.root is not None else None,
        # what the evaluation needs besides frames.csv and trajectory.tum, so it can run on its own later
        "reset_times": [float(t) for t in result.reset_times],
        "first_fix_time": None if result.first_fix_time is None else float(result.first_fix_time),
        "relocalisation_times": [[float(a), float(b)] for a, b in result.relocalisations],
    }
    for k in ("frames_dropped", "frames_detected", "odometry_queue_max", "odometry_coalesced", "lag_max_s"):
        if k in tm:
            metrics[k] = tm[k]
    flags = getattr(result, "integrity_alert", None)
    metrics["integrity_alerts"] = len(getattr(result, "integrity_alerts", None) or [])
    metrics["integrity_alert_frames"] = int(np.sum(flags)) if flags is not None else 0
    if getattr(result, "integrity_alerts", None):
        metrics["integrity_alert_list"] = result.integrity_alerts[:20]   # localiser.integrity.Alert
    if getattr(result, "camera_check", None) is not None:
        metrics["camera_check"] = result.camera_check     # mapping.camera_check.assess, before the replay
    return metrics


def inlier_types(result) -> dict:
    """Which measurement types the solver used: per detector frame the mean signature and point-feature
    inliers (``signature_inliers_mean``, ``point_inliers_mean``) and the accepted localisations that kept
    at least ``4`` signature / ``12`` point inliers (``localisations_with_signatures``,
    ``localisations_with_points``; the signature and point methods' acceptance counts)."""
    ran = np.asarray(result.detector_ran, bool)
    loc = np.asarray(result.localised, bool)
    s = np.asarray(result.signature_inliers, float)
    p = np.asarray(result.point_inliers, float)
    return {"signature_inliers_mean": float(s[ran].mean()) if ran.any() else None,
            "point_inliers_mean": float(p[ran].mean()) if ran.any() else None,
            "localisations_with_signatures": int((loc & (s >= 4)).sum()),
            "localisations_with_points": int((loc & (p >= 12)).sum())}


def _median(v) -> float | None:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else None


def truth_metrics(result, store: MapStore, truth_times, truth_poses, source: str,
                  max_path_distance_m: float | None = None):
    """The evaluation against truth (see :func:`compute_metrics`): ``(metrics, EvaluationResult)``.

    ``result`` needs ``times``, ``poses``, ``valid``, ``localised``, ``resets``, ``failures``, ``oracle``,
    ``first_fix_time``, ``relocalisations`` and ``lateral_bound_95_m`` (or ``covariances``) -- a
    :class:`scenesig.localiser.replay.ReplayResult`, or the same read back from an output folder.
    """
    from .uncertainty import bounds_from_result

    ev = _evaluate_valid(result, truth_times, truth_poses, store, max_path_distance_m)
    m = ev.metrics
    out = {"lateral_error_m": m["lateral_error_m"], "heading_error_deg": m["heading_error_deg"],
           "localised_fraction": m["localised_fraction"], "failures_per_km": m["failures_per_km"],
           "blind_fraction_over_20m": m["blind_fraction_over_20m"], "distance_m": m["distance_m"],
           "frames_evaluated": m["frames_evaluated"]}
    tmap = map_relative_truth(store, truth_poses) if source == "truth" else None
    lat_rel = ev.lateral_m           # lateral error relative to the map, else to the truth
    if tmap is not None:
        evm = _evaluate_valid(result, truth_times, tmap, store, max_path_distance_m)
        lat_rel = evm.lateral_m
        # the map's own error: its places against their truth
        ids = sorted(store.places)
        off = [np.linalg.norm(store.places[i].T_world_place[:2, 3] - np.asarray(store.places[i].extra["T_truth_place"])[:2, 3])
               for i in ids]
        out.update({"lateral_error_map_m": evm.metrics["lateral_error_m"],
                    "heading_error_map_deg": evm.metrics["heading_error_deg"],
                    "map_georeference_error_m": summary(off)})
    out.update(_no_oracle_metrics(result, ev, truth_times, truth_poses if tmap is None else tmap))
    bound = bounds_from_result(result, store)["lateral_bound_95_m"]
    out.update(bound_coverage(lat_rel, bound, result.localised))
    out["truth_source"] = source
    return out, ev


def bound_coverage(lateral_error, lateral_bound, localised) -> dict:
    """``bound_coverage_95``: the share of localised frames (an accepted fix, an error and a bound) whose
    absolute lateral error is within their ``lateral_bound_95_m``; ``bound_coverage_95_all``: the same
    over every frame with a pose, fixes and dead reckoning alike.  None where no frame counts."""
    e = np.abs(np.asarray(lateral_error, float))
    b = np.asarray(lateral_bound, float)
    ok = np.isfinite(e) & np.isfinite(b)
    loc = ok & np.asarray(localised, bool)

    def share(mask):
        return clamp_fraction(float((e[mask] <= b[mask]).mean())) if mask.any() else None

    return {"bound_coverage_95": share(loc), "bound_coverage_95_all": share(ok)}


def clamp_fraction(x):
    """A fraction (share of something) clamped to [0, 1] -- rounding in a ratio of sums can land a hair
    outside; None stays None."""
    return None if x is None else float(min(1.0, max(0.0, x)))


def merge_truth_metrics(metrics: dict, truth: dict) -> dict:
    """``metrics`` (:func:`localisation_metrics`, any earlier evaluation dropped) with ``truth``
    (:func:`truth_metrics`): the errors right after ``conditions``, the refined distances in place."""
    base = {k: v for k, v in metrics.items() if k not in TRUTH_KEYS}
    head = {k: base.pop(k) for k in ("method", "run", "conditions") if k in base}
    errors = {k: truth[k] for k in ("lateral_error_m", "heading_error_deg") if k in truth}
    out = {**head, **errors, **base}
    for k, v in truth.items():
        if k not in errors:
            out[k] = v
    return out


def detection_rates(detections, inliers) -> dict:
    """``detections_per_frame_mean`` (detections per detector frame) and ``inliers_per_detection_mean``
    (inliers of the pose solve per detection, pooled over those frames: total inliers / total
    detections; None without detections) of the frames the detector ran on."""
    d = np.asarray(detections, dtype=float)
    k = np.asarray(inliers, dtype=float)
    return {"detections_per_frame_mean": float(d.mean()) if d.size else None,
            "inliers_per_detection_mean": float(k.sum() / d.sum()) if d.sum() > 0 else None}


def _evaluate_valid(result: ReplayResult, truth_times, truth_poses, store: MapStore, max_path_distance_m):
    """:func:`scenesig.localiser.evaluation.evaluate` over the frames with a world pose (all of them with an oracle;
    from the first fix on without one), its per-frame series put back on every frame (NaN elsewhere)."""
    from scenesig.surveys.geometry import interpolate_poses

    from .evaluation import EvaluationResult, travelled

    v = np.asarray(result.valid, bool)
    if v.all():
        return evaluate(result.times, result.poses, truth_times, truth_poses, reference_path(store), result.localised,
                        result.resets, max_path_distance_m=max_path_distance_m)
    n = len(result.times)
    dist = travelled(interpolate_poses(truth_times, truth_poses, result.times).reshape(-1, 4, 4)[:, :3, 3])
    lat, hd, blind = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    if v.sum() >= 2:
        ev = evaluate(result.times[v], result.poses[v], truth_times, truth_poses, reference_path(store),
                      result.localised[v], result.resets[v], max_path_distance_m=max_path_distance_m)
        lat[v], hd[v], blind[v] = ev.lateral_m, ev.heading_deg, ev.blind_m
        metrics = ev.metrics
    else:   # never localised: nothing to evaluate but the distance driven
        metrics = {"lateral_error_m": summary([]), "heading_error_deg": summary([]), "localised_fraction": 0.0,
                   "failures": int(result.failures), "failures_per_km": None, "blind_fraction_over_20m": None,
                   "distance_m": float(dist[-1]) if n else 0.0, "frames_evaluated": 0}
    return EvaluationResult(metrics, lat, hd, blind, dist)


def _oracle_metrics(result, dist) -> dict:
    """``oracle``, ``oracle_reads``, ``first_fix_m``, ``relocalisations``, ``relocalise_m`` from the
    cumulative distance ``dist`` at each frame (along the truth, else the odometry)."""
    s = np.asarray(dist, float)

    def at(t):
        return float(np.interp(t, result.times, s)) if len(s) else 0.0

    first = None
    if result.oracle == "ins":
        first = 0.0
    elif result.first_fix_time is not None:
        first = at(result.first_fix_time) - (float(s[0]) if len(s) else 0.0)
    found = [at(b) - at(a) for a, b in result.relocalisations]
    rel = summary(found)
    return {"oracle": result.oracle, "oracle_reads": int(result.oracle_reads), "first_fix_m": first,
            "relocalisations": len(found),
            "relocalise_m": {"median": rel["median"], "max": float(max(found)) if found else None}}


def _no_oracle_metrics(result, ev, truth_times, truth_poses) -> dict:
    """``first_fix_m``, ``relocalise_m`` along the truth and ``false_fixes``.

    Distances are along the truth (``ev.distance_m``, from the first frame); a false fix is an accepted
    localisation whose estimate is more than :data:`FALSE_FIX_M` from the truth (relative to the map
    where the map records its places' truth, so the map's own georeferencing error does not count).
    """
    from scenesig.surveys.geometry import interpolate_poses

    m = _oracle_metrics(result, ev.distance_m)
    loc = np.asarray(result.localised, bool) & np.asarray(result.valid, bool)
    false = 0
    if loc.any():
        truth = interpolate_poses(truth_times, truth_poses, result.times[loc]).reshape(-1, 4, 4)
        err = np.linalg.norm(result.poses[loc][:, :2, 3] - truth[:, :2, 3], axis=1)
        false = int((err > FALSE_FIX_M).sum())
    return {"first_fix_m": m["first_fix_m"], "relocalise_m": m["relocalise_m"], "false_fixes": false}


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.6f}"


def write_frames_csv(path: Path, result: ReplayResult, ev, bounds: dict | None = None) -> None:
    """``frames.csv`` (:data:`FRAMES_COLUMNS`): per frame the replay's record, the errors of ``ev`` (NaN
    without truth) and the 95 % bounds (:mod:`scenesig.localiser.uncertainty`)."""
    atomic_write_text(path, frames_csv_text(result, ev, bounds))


def frames_csv_text(result: ReplayResult, ev, bounds: dict | None = None) -> str:
    """The text of ``frames.csv`` (see :func:`write_frames_csv`)."""
    n = len(result.times)
    b = bounds or {}
    cols = [b.get(c, np.full(n, np.nan)) for c in BOUND_COLUMNS]
    flag = getattr(result, "integrity_alert", None)
    if flag is None:
        flag = b.get("integrity_alert")
    counts = [np.zeros(n) if flag is None else np.nan_to_num(np.asarray(flag, float)),
              *(np.asarray(getattr(result, c), float) for c in _COUNT_COLUMNS)]
    lines = [",".join(FRAMES_COLUMNS)]
    for i, t in enumerate(result.times):
        lines.append(",".join([f"{t:.6f}", str(int(result.places[i])), str(int(result.detections[i])),
                               str(int(result.inliers[i])), str(int(result.localised[i])),
                               _fmt(ev.lateral_m[i]), _fmt(ev.heading_deg[i]),
                               _fmt(result.distance_since_localisation[i]), *(_fmt(c[i]) for c in cols),
                               *(str(int(c[i])) if np.isfinite(c[i]) else "0" for c in counts)]))
    return "\n".join(lines) + "\n"


def read_frames_csv(path) -> dict:
    """``frames.csv`` as ``{column: (N,) float array}``; a :class:`DataError` naming the file and line when
    a column of :data:`FRAMES_COLUMNS` is missing or a value is not a number (the bound columns may be
    missing: outputs written before they existed)."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = csv_header(reader, path, _FRAMES_REQUIRED)
            cols = {h: [] for h in header}
            for ln, row in enumerate(reader, start=2):
                if not row:
                    continue
                if len(row) != len(header):
                    raise DataError(path, f"expected {len(header)} values, got {len(row)}", line=ln)
                for h, v in zip(header, row):
                    try:
                        cols[h].append(float(v))
                    except ValueError:
                        raise DataError(path, f"column {h!r}: {v!r} is not a number", line=ln) from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None
    return {h: np.asarray(v, dtype=float) for h, v in cols.items()}


def write_outputs(result: ReplayResult, store: MapStore, out, max_path_distance_m: float | None = None,
                  figure: bool = True) -> dict:
    """Write trajectory.tum, covariances.csv, frames.csv, metrics.json (and trajectory.png) into ``out``;
    return the metrics.

    What the localiser produced is written whether or not the run has truth -- the trajectory first,
    and it never depends on the truth; where there is truth the evaluation (:func:`compute_metrics`)
    fills the errors in.
    """
    from .uncertainty import bounds_from_result, write_covariances_csv

    out = Path(out)
    make_dirs(out)
    # without INS/GPS there is no pose before the first fix: those frames have none
    v = np.asarray(result.valid, bool)
    write_tum(out / "trajectory.tum", result.times[v], result.poses[v])
    bounds = bounds_from_result(result, store)
    write_covariances_csv(out / "covariances.csv", result.times[v], result.planar_covariances[v])
    metrics, ev = compute_metrics(result, store, max_path_distance_m)
    write_frames_csv(out / "frames.csv", result, ev, bounds)
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    if figure:
        from .plots import plot_trajectory

        plot_trajectory(out / "trajectory.png", result, store, ev, metrics)
    return metrics


def read_output_files(folder):
    """``(metrics, frames, times, poses)`` of a localise output folder: ``metrics.json`` (a dict with at
    least ``method`` and ``run``), ``frames.csv`` (:func:`read_frames_csv`) and ``trajectory.tum``
    (one pose per frame, at the frames' times; with ``--oracle none`` the frames before the first fix have
    no pose and get NaN); DataError naming the file if one is missing or wrong."""
    folder = Path(folder)
    mpath = folder / "metrics.json"
    if not mpath.is_file():
        raise DataError(mpath, "missing: not a `scenesig localise` output folder")
    try:
        metrics = json.loads(mpath.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataError(mpath, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    if not isinstance(metrics, dict) or "method" not in metrics or "run" not in metrics:
        raise DataError(mpath, "expected an object with at least 'method' and 'run'")
    fpath = folder / "frames.csv"
    if not fpath.is_file():
        raise DataError(fpath, "missing")
    frames = read_frames_csv(fpath)
    tpath = folder / "trajectory.tum"
    if not tpath.is_file():
        raise DataError(tpath, "missing")
    if metrics.get("oracle") == "none" and not any(
            ln.strip() and not ln.lstrip().startswith("#") for ln in tpath.read_text(encoding="utf-8").splitlines()):
        times, poses = np.zeros(0), np.zeros((0, 4, 4))     # never localised: no pose at all
    else:
        times, poses = read_tum(tpath)
    n = len(frames["time"])
    if len(times) != n and metrics.get("oracle") != "none":
        raise DataError(tpath, f"{len(times)} poses but frames.csv has {n} frames")
    if len(times) != n:
        # without INS/GPS there is no pose before the first fix, nor after the integrity monitor dropped
        # one (localiser.integrity): the trajectory holds the frames that have a pose
        ft = np.asarray(frames["time"], float)
        k = np.clip(np.searchsorted(ft, times - 1e-3), 0, max(n - 1, 0))
        if len(times) > n or (len(times) and (np.max(np.abs(ft[k] - times)) > 1e-3 or np.any(np.diff(k) <= 0))):
            raise DataError(tpath, f"its {len(times)} poses are not at frames of frames.csv's {n}")
        full = np.full((n, 4, 4), np.nan)
        full[k] = poses.reshape(-1, 4, 4)
        poses, times = full, ft
    if n and np.max(np.abs(times - frames["time"])) > 1e-3:
        raise DataError(tpath, "times differ from frames.csv's")
    return metrics, frames, times, poses


def read_localisation(folder, search=()):
    """Read a ``scenesig localise`` output back as a :class:`scenesig.mapping.update.Localisation` (for ``scenesig
    map update``); the run is found by ``metrics.json``'s ``run_path``, else by its name beside it or in
    the folders ``search``.  DataError naming the file if something is missing or inconsistent."""
    from scenesig.mapping.update import Localisation, find_run

    folder = Path(folder)
    mpath = folder / "metrics.json"
    metrics, frames, times, poses = read_output_files(folder)
    if metrics["method"] != "signatures":
        raise DataError(mpath, f"method is {metrics['method']!r}: only a scene-signature localisation tells "
                               f"where the map's signatures were weak")
    tpath = folder / "trajectory.tum"
    # the run: where the localisation read it, else by name beside it or in ``search``
    hint = Path(metrics["run_path"]) if metrics.get("run_path") else None
    search = ([hint.parent] if hint is not None else []) + [Path(d) for d in search]
    run = read_run(find_run(metrics["run"], [hint], search))
    if run.name != metrics["run"]:
        raise DataError(mpath, f"names run {metrics['run']!r} but {run.root} holds run {run.name!r}")
    n = len(run.frame_times)
    if len(times) != n:
        raise DataError(tpath, f"{len(times)} poses for run {run.name!r} of {n} frames: not this run's localisation")
    if not np.allclose(times, run.frame_times, atol=1e-5):
        raise DataError(tpath, f"timestamps are not those of run {run.name!r}'s frames")
    h = hashlib.sha256()
    for name in ("metrics.json", "trajectory.tum", "frames.csv"):
        data = (folder / name).read_bytes()
        if name == "metrics.json":  # the machine-dependent parts (timings, paths) are not inputs
            data = json.dumps({k: v for k, v in metrics.items() if k not in (*TIMING_KEYS, "map", "run_path")},
                              sort_keys=True).encode()
        h.update(hashlib.sha256(data).digest())
    return Localisation(folder, metrics, times, np.asarray(poses).reshape(-1, 4, 4), frames, run, h.hexdigest())


class _Track:
    """A localisation read back from its output folder, shaped as :func:`truth_metrics` and
    :func:`scenesig.localiser.plots.plot_trajectory` read a :class:`scenesig.localiser.replay.ReplayResult`."""

    def __init__(self, metrics: dict, frames: dict, times, poses, run):
        n = len(times)
        self.run = run
        self.method = metrics["method"]
        self.times = np.asarray(times, float)
        self.poses = np.asarray(poses, float).reshape(-1, 4, 4)
        self.valid = np.isfinite(self.poses[:, :3, 3]).all(axis=1)
        self.localised = np.asarray(frames["localised"]) > 0
        self.places = frames["place"].astype(int)
        self.detections = frames["detections"].astype(int)
        self.inliers = frames["inliers"].astype(int)
        self.distance_since_localisation = frames["distance_since_localisation"]
        self.resets = np.zeros(n, dtype=bool)
        for tr in metrics.get("reset_times") or []:     # as the replay marks them
            self.resets[min(int(np.searchsorted(self.times, tr, side="right")), n - 1)] = True
        self.failures = int(metrics.get("failures", 0))
        self.oracle = metrics.get("oracle", "ins")
        self.oracle_reads = int(metrics.get("oracle_reads", 0))
        self.first_fix_time = metrics.get("first_fix_time")
        self.relocalisations = [tuple(p) for p in metrics.get("relocalisation_times") or []]
        self.bounds = {c: frames.get(c, np.full(n, np.nan)) for c in BOUND_COLUMNS}
        self.integrity_alert = frames.get("integrity_alert", np.zeros(n))
        self.integrity_alerts = list(metrics.get("integrity_alert_list") or [])
        self.signature_inliers = frames.get("signature_inliers", np.zeros(n)).astype(int)
        self.point_inliers = frames.get("point_inliers", np.zeros(n)).astype(int)


def evaluate_folder(folder, truth=None, map_root=None, max_path_distance_m: float | None = None,
                    figure: bool = True) -> dict:
    """Evaluate a finished ``scenesig localise`` output against truth (``scenesig evaluate``): fill in
    ``metrics.json``'s error keys (:func:`truth_metrics`; an earlier evaluation is replaced) and
    ``frames.csv``'s error columns, redraw ``trajectory.png``; return the metrics.

    Parameters
    ----------
    folder : the output folder (``trajectory.tum``, ``frames.csv``, ``metrics.json``).
    truth : a TUM file of the run's exact truth; default: the run's ``truth.tum`` (else
        ``groundtruth.tum``) in the run folder ``metrics.json`` names (``run_path``).
    map_root : the map (default: ``metrics.json``'s ``map``); it must be the map the localisation was
        made against (``map_id``).
    """
    from dataclasses import replace
    from types import SimpleNamespace

    folder = Path(folder)
    mpath = folder / "metrics.json"
    metrics, frames, times, poses = read_output_files(folder)
    if map_root is None and not metrics.get("map"):
        raise DataError(mpath, "names no map: give the map")
    store = MapStore.open(map_root if map_root is not None else metrics["map"])
    if metrics.get("map_id") and metrics["map_id"] != store.map_id:
        raise DataError(mpath, f"was made against map {metrics['map_id']}, but {store.root} is map {store.map_id}")
    run = None
    if metrics.get("run_path") and Path(metrics["run_path"]).is_dir():
        run = read_run(metrics["run_path"], check_images=False)
    if truth is not None:
        tt, tp = read_tum(truth)
        source = "groundtruth" if Path(truth).name == "groundtruth.tum" else "truth"
        run = replace(run, truth_times=tt, truth_poses=tp) if run is not None else None
    else:
        found = run_truth(run) if run is not None else None
        if found is None:
            where = metrics.get("run_path") or "the run folder"
            raise DataError(mpath, f"no truth to evaluate against: {where} has no truth.tum or groundtruth.tum; "
                                   f"give one with --truth FILE")
        tt, tp, source = found
    if run is None:     # the run folder is gone: what the figure needs of it
        run = SimpleNamespace(name=metrics["run"], conditions=metrics.get("conditions", []), truth_times=tt,
                              truth_poses=tp, groundtruth_times=None, groundtruth_poses=None, root=None)
    track = _Track(metrics, frames, times, poses, run)
    tm, ev = truth_metrics(track, store, tt, tp, source, max_path_distance_m)
    metrics = merge_truth_metrics(metrics, tm)
    write_frames_csv(folder / "frames.csv", track, ev, track.bounds)
    atomic_write_text(mpath, json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    if figure:
        from .plots import plot_trajectory

        plot_trajectory(folder / "trajectory.png", track, store, ev, metrics)
    return metrics
