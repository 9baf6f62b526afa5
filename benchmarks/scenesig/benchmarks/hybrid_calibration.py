"""Calibrate the hybrid localiser's per-type weights on runs that are not reported.

``scenesig bench hybrid_calibration MAP RUN... [--points sift] [--every 2] [--json OUT]``

Replays each RUN (runs with exact truth, of the map's world, that no reported figure uses) with
scene signatures and with the point method of ``--points``, and keeps every accepted fix's pose from
the measurements alone (``LocalisationConstraint.T_world_vehicle_detections``) with its information.
Against the truth relative to the map (:func:`scenesig.localiser.outputs.map_relative_truth`):

* per type, ``nees_planar_median`` -- the median of the planar (x, y, yaw) normalised estimation error
  squared ``eᵀ C⁻¹ e`` (``C`` the planar block of the inverse information); a consistent noise model
  gives the median of χ²(3), 2.366.  ``sigma_scale = sqrt(nees_planar_median / 2.366)`` is the σ
  multiplier that makes the type consistent: the hybrid's ``signature_sigma_scale`` and
  ``point_sigma_scale``;
* per type, ``lateral_error_m`` and ``heading_error_deg`` (median, p95) of the fixes, lateral across
  the reference path (:func:`scenesig.localiser.evaluation.lateral_heading_errors`);
* ``by_point_inliers`` -- the point fixes with at least k inliers (k in ``--inlier-steps``): their
  count and median errors; ``point_dominant_inliers`` is the smallest k whose point fixes have median
  lateral and heading errors no larger than the signature fixes' (from there on points are the more
  accurate type, and the hybrid lets them lead with the signatures as the gate).

``config`` in the JSON is the hybrid's settings these give.  Nothing is timed.
"""
from __future__ import annotations

import argparse

import numpy as np

#: median of χ²(3)
CHI2_3_MEDIAN = 2.3660


class _Recording:
    """A weak localiser that records every accepted measurement's constraint (``prior.t``)."""

    def __init__(self, method):
        self.method = method
        self.name, self.color = method.name, method.color
        self.records: list = []

    def __getattr__(self, k):
        return getattr(self.method, k)

    def prepare(self, image):
        return self.method.prepare(image)

    def prefetch(self, place):
        self.method.prefetch(place)

    def detect(self, image, place, prior):
        return self.method.detect(image, place, prior)

    def solve(self, obs, place, prior):
        from scenesig.localiser.pipeline import Measurement

        m = Measurement.coerce(self.method.solve(obs, place, prior))
        if m.constraint is not None:
            self.records.append((prior.t, m.constraint.T_world_vehicle_detections,
                                 m.constraint.information_detections, int(m.inliers)))
        return m

    def method_config(self):
        return self.method.method_config()

    def close(self):
        self.method.close()


def _fixes(store, run, method_name: str, every: int):
    """(times, T_det, information, inliers) of the accepted fixes of one replay."""
    from scenesig.localiser.pipeline import make_method
    from scenesig.localiser.replay import replay

    rec = _Recording(make_method(method_name, store, run.camera, run.T_vehicle_camera))
    try:
        replay(store, run, rec, every=every)
    finally:
        rec.close()
    if not rec.records:
        return np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), np.zeros(0, int)
    t, T, L, k = zip(*rec.records)
    return np.array(t), np.stack(T), np.stack(L), np.array(k)


def _errors(store, run, t, T, L):
    """Planar NEES, |lateral| (m) and |heading| (deg) of each fix against the truth relative to the map."""
    from scenesig.localiser.evaluation import lateral_heading_errors
    from scenesig.localiser.outputs import map_relative_truth, reference_path
    from scenesig.localiser.solver import pose_log
    from scenesig.surveys.geometry import interpolate_poses, invert

    tmap = map_relative_truth(store, run.truth_poses)
    if tmap is None:
        raise ValueError(f"map {store.root} records no place truth (T_truth_place): calibrate on a simulated map")
    ok = (t >= run.truth_times[0]) & (t <= run.truth_times[-1])
    t, T, L = t[ok], T[ok], L[ok]
    truth = interpolate_poses(run.truth_times, tmap, t).reshape(-1, 4, 4)
    nees = np.full(len(t), np.nan)
    for i in range(len(t)):
        e = pose_log(invert(truth[i]) @ T[i])[[2, 3, 4]]          # yaw, x, y in the vehicle frame
        C = np.linalg.pinv(0.5 * (L[i] + L[i].T))[np.ix_([2, 3, 4], [2, 3, 4])]
        try:
            nees[i] = float(e @ np.linalg.solve(C, e))
        except np.linalg.LinAlgError:
            pass
    lat, head = lateral_heading_errors(T, truth, reference_path(store))[:2]
    return ok, nees, np.abs(lat), np.abs(head)


def _summary(nees, lat, head) -> dict:
    good = np.isfinite(nees)
    med = float(np.median(nees[good])) if good.any() else None
    return {"fixes": int(len(lat)), "nees_planar_median": med,
            "sigma_scale": None if med is None else float(np.sqrt(med / CHI2_3_MEDIAN)),
            "lateral_error_m": {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95))} if len(lat) else None,
            "heading_error_deg": {"median": float(np.median(head)), "p95": float(np.percentile(head, 95))} if len(head) else None}


def main(argv=None) -> int:
    from scenesig.benchmarks._stages import emit_json
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    ap = argparse.ArgumentParser(prog="scenesig bench hybrid_calibration", description=__doc__.splitlines()[0])
    ap.add_argument("map", help="map folder (simulated: places record their truth)")
    ap.add_argument("runs", nargs="+", help="calibration runs with truth.tum (never the reported ones)")
    ap.add_argument("--points", default="sift", help="point method whose fixes calibrate the point type")
    ap.add_argument("--every", type=int, default=2, help="detector on every N-th frame (the demo: 2 at 10 Hz)")
    ap.add_argument("--inlier-steps", default="12,16,20,25,30,40,50,60,80,100,150")
    ap.add_argument("--json", help="write the result JSON here")
    args = ap.parse_args(argv)
    store = MapStore.open(args.map, cache_size=1000)
    steps = [int(k) for k in args.inlier_steps.split(",")]
    pooled = {"signatures": [[], [], []], "points": [[], [], []]}
    point_inliers = []
    per_run = {}
    for path in args.runs:
        run = read_run(path)
        if run.truth_times is None:
            raise SystemExit(f"scenesig: error: {path}: no truth.tum -- calibration needs exact truth")
        per_run[run.name] = {}
        for typ, name in (("signatures", "signatures"), ("points", args.points)):
            t, T, L, k = _fixes(store, run, name, args.every)
            ok, nees, lat, head = _errors(store, run, t, T, L)
            per_run[run.name][typ] = _summary(nees, lat, head)
            for acc, a in zip(pooled[typ], (nees, lat, head)):
                acc.append(a)
            if typ == "points":
                point_inliers.append(k[ok])
    summ = {typ: _summary(*(np.concatenate(a) for a in acc)) for typ, acc in pooled.items()}
    k = np.concatenate(point_inliers)
    _, p_lat, p_head = (np.concatenate(a) for a in pooled["points"])
    s_lat, s_head = summ["signatures"]["lateral_error_m"]["median"], summ["signatures"]["heading_error_deg"]["median"]
    by = []
    dominant = None
    for step in steps:
        sel = k >= step
        row = {"min_inliers": step, "fixes": int(sel.sum()),
               "lateral_error_m_median": float(np.median(p_lat[sel])) if sel.any() else None,
               "heading_error_deg_median": float(np.median(p_head[sel])) if sel.any() else None}
        by.append(row)
        if dominant is None and sel.sum() >= 20 and row["lateral_error_m_median"] <= s_lat \
                and row["heading_error_deg_median"] <= s_head:
            dominant = step
    out = {"map": str(store.root), "runs": per_run, "every": args.every, "points": args.points,
           "types": summ, "by_point_inliers": by, "point_dominant_inliers": dominant,
           "config": {"signature_sigma_scale": summ["signatures"]["sigma_scale"],
                      "point_sigma_scale": summ["points"]["sigma_scale"],
                      "point_dominant_inliers": dominant}}
    emit_json(out, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
