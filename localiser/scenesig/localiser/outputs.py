"""What ``scenesig localise`` computes from a localised run for its files: the metrics and the errors.

The run is a :class:`scenesig.surveys.localisation.Localisation` (arrays and metrics; it writes and reads
``trajectory.tum``, ``covariances.csv``, ``frames.csv``, ``metrics.json`` itself).  Here:
:func:`compute_metrics` turns it into the ``metrics.json`` content: what the localiser knows
(:func:`localisation_metrics`, no truth needed) and, where the run has truth, the evaluation against it
(:func:`truth_metrics`: errors across the reference path through the map's places, see
:mod:`scenesig.localiser.evaluation`); :func:`evaluate_localisation` puts the metrics, the per-frame errors and
the 95 % bounds into the localisation; :func:`write_outputs` does that and writes the files (and
``trajectory.png``, :mod:`scenesig.localiser.plots`); :func:`evaluate_folder` runs the evaluation on a
finished output folder (``scenesig evaluate``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.surveys.errors import DataError
from scenesig.surveys.localisation import (  # noqa: F401  (re-exported: the files' one definition)
    BOUND_COLUMNS,
    FRAMES_COLUMNS,
    TIMING_KEYS,
    Localisation,
    read_frames_csv,
)
from scenesig.surveys.run import read_run
from scenesig.surveys.tum import read_tum

from .evaluation import evaluate, map_relative_truth, reference_path, summary
from .uncertainty import INFLATION

__all__ = ["FRAMES_COLUMNS", "TIMING_KEYS", "FALSE_FIX_M", "reference_path", "map_relative_truth", "compute_metrics",
           "read_frames_csv", "evaluate_localisation", "write_outputs", "detection_rates", "inlier_types",
           "evaluate_folder"]

#: Accepted localisations further than this from the truth are ``false_fixes`` (metres).
FALSE_FIX_M = 5.0


def compute_metrics(result: Localisation, store: MapStore, max_path_distance_m: float | None = None):
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


def localisation_metrics(result: Localisation, store: MapStore, truth=None) -> dict:
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
        "settings": result.settings or {},
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
    metrics["integrity_alerts"] = len(result.integrity_alerts or [])
    metrics["integrity_alert_frames"] = int(np.sum(result.integrity_alert))
    if result.integrity_alerts:
        metrics["integrity_alert_list"] = result.integrity_alerts[:20]   # localiser.integrity.Alert
    if result.camera_check is not None:
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

    ``result`` is a :class:`scenesig.surveys.localisation.Localisation`, from the replay or read back from an
    output folder (its bounds then those ``frames.csv`` recorded).
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


def _evaluate_valid(result: Localisation, truth_times, truth_poses, store: MapStore, max_path_distance_m):
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


def evaluate_localisation(loc: Localisation, store: MapStore, max_path_distance_m: float | None = None):
    """Complete a localisation for its files: the 95 % bounds (:mod:`scenesig.localiser.uncertainty`), the
    metrics (:func:`compute_metrics`) and the per-frame errors (NaN without truth) go into ``loc``, and the
    drawing of ``trajectory.png`` (it needs the map); returns the evaluation
    (:class:`scenesig.localiser.evaluation.EvaluationResult`)."""
    from .uncertainty import bounds_from_result

    bounds_from_result(loc, store)
    metrics, ev = compute_metrics(loc, store, max_path_distance_m)
    _fill(loc, metrics, ev, store)
    return ev


def _fill(loc: Localisation, metrics: dict, ev, store: MapStore) -> None:
    # new arrays, not writes into the old ones: a copy made with dataclasses.replace shares the table
    loc.frames = {**loc.frames, "lateral_error": np.asarray(ev.lateral_m, float),
                  "heading_error": np.asarray(ev.heading_deg, float)}
    loc.metrics = metrics
    loc.figure = _Figure(store, ev)


class _Figure:
    """Draws a localisation's ``trajectory.png`` against the map and the evaluation it was made with."""

    def __init__(self, store: MapStore, ev):
        self.store, self.ev = store, ev

    def __call__(self, path, loc: Localisation) -> None:
        from .plots import plot_trajectory

        plot_trajectory(path, loc, self.store, self.ev, loc.metrics)


def write_outputs(loc: Localisation, store: MapStore, out, max_path_distance_m: float | None = None,
                  figure: bool = True) -> dict:
    """Evaluate ``loc`` (:func:`evaluate_localisation`) and write trajectory.tum, covariances.csv, frames.csv,
    metrics.json (and trajectory.png) into ``out`` (:meth:`Localisation.write`); return the metrics.

    What the localiser produced is written whether or not the run has truth -- the trajectory never
    depends on the truth; where there is truth the evaluation fills the errors in.
    """
    evaluate_localisation(loc, store, max_path_distance_m)
    return loc.write(out, figure=figure)


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
    loc = Localisation.from_folder(folder)
    metrics = loc.metrics
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
    loc.run = run
    tm, ev = truth_metrics(loc, store, tt, tp, source, max_path_distance_m)
    _fill(loc, merge_truth_metrics(metrics, tm), ev, store)
    loc.write_results(folder)
    if figure:
        loc.figure(folder / "trajectory.png", loc)
    return loc.metrics
