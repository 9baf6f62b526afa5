"""Robust absolute-pose estimators on synthetic 2D-3D matches: speed, accuracy, success with outliers.

``python -m scenesig.benchmarks.absolute_pose [--matches 300] [--outliers 0.7] [--repeats 100] [--json OUT]``
prints JSON: per estimator (:data:`scenesig.localiser.absolute_pose.ESTIMATORS`) the median and 95th
percentile milliseconds per call, the median translation (m) and rotation (deg) errors against the
true pose, the share of problems solved (translation error < 0.5 m and rotation < 1 deg), and the
median RANSAC iterations.  Problems come from :func:`scenesig.localiser.synthetic.synthetic_problem` (landmarks
8-60 m ahead, 1-px keypoint noise, 5-cm landmark noise, outliers uniform over the image).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from scenesig.localiser.absolute_pose import ESTIMATORS, estimate
from scenesig.localiser.solver import pose_log
from scenesig.localiser.synthetic import synthetic_problem
from scenesig.surveys.geometry import invert


def benchmark(n_matches: int = 300, outliers: float = 0.7, repeats: int = 100,
              estimators=ESTIMATORS, max_error_px: float = 4.0) -> dict:
    problems = [synthetic_problem(n_matches, outliers, seed=s, landmark_sigma=0.05) for s in range(repeats)]
    out = {"matches": n_matches, "outlier_fraction": outliers, "repeats": repeats, "max_error_px": max_error_px,
           "estimators": {}}
    for name in estimators:
        cfg = {"estimator": name, "max_error_px": max_error_px}
        if name == "opencv":
            cfg["max_iterations"] = 200       # the localiser's former setting
        estimate(problems[0]["uv"], problems[0]["landmarks"], problems[0]["camera"], cfg)   # warm-up
        ms, et, er, ok, iters, inl_ok = [], [], [], 0, [], []
        for p in problems:
            r = estimate(p["uv"], p["landmarks"], p["camera"], cfg)
            ms.append(r.ms)
            iters.append(r.iterations)
            if not r.ok:
                et.append(np.inf)
                er.append(np.inf)
                continue
            T_pv = invert(p["T_vehicle_camera"] @ r.T_cam_place)
            d = invert(p["T_true"]) @ T_pv
            et.append(float(np.linalg.norm(d[:3, 3])))
            er.append(float(np.degrees(np.linalg.norm(pose_log(d)[:3]))))
            ok += et[-1] < 0.5 and er[-1] < 1.0
            inl_ok.append(float((r.inliers & ~p["outliers"]).sum() / max(r.n_inliers, 1)))
        out["estimators"][name] = {
            "ms_median": float(np.median(ms)), "ms_p95": float(np.percentile(ms, 95)),
            "translation_error_m_median": float(np.median(et)), "rotation_error_deg_median": float(np.median(er)),
            "solved_fraction": ok / repeats, "iterations_median": float(np.median(iters)) if min(iters) >= 0 else None,
            "inlier_precision_mean": float(np.mean(inl_ok)) if inl_ok else None}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.absolute_pose", description=__doc__.splitlines()[0])
    ap.add_argument("--matches", type=int, default=300)
    ap.add_argument("--outliers", type=float, default=0.7)
    ap.add_argument("--repeats", type=int, default=100)
    ap.add_argument("--estimators", default=",".join(ESTIMATORS))
    ap.add_argument("--json", default=None, help="also write the JSON here")
    a = ap.parse_args(argv)
    res = benchmark(a.matches, a.outliers, a.repeats, tuple(a.estimators.split(",")))
    text = json.dumps(res, indent=1)
    print(text)
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
