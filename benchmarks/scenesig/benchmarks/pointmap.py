"""Point-map benchmark: build the ORB/SIFT point map of one keyframe of a survey run and report its time,
statistics, size and (for simulated runs) the depth error of its 3D points:
``scenesig bench pointmap RUN --frame I``.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from scenesig.mapping.places import TrainingView
from scenesig.mapping.pointmap import build_point_features
from scenesig.surveys.geometry import interpolate_poses, invert
from scenesig.surveys.run import read_run
from scenesig.surveys.sim.truth import depth_image

__all__ = ["main"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench pointmap",
                                 description="Build the ORB/SIFT point map of one keyframe of a survey run.")
    ap.add_argument("run")
    ap.add_argument("--frame", type=int, required=True, help="keyframe index")
    ap.add_argument("--window-m", type=float, default=10.0)
    args = ap.parse_args(argv)
    run = read_run(args.run)
    if not 0 <= args.frame < len(run):
        ap.error(f"--frame must be in 0..{len(run) - 1}")
    odo = interpolate_poses(run.odometry_times, run.odometry_poses, run.frame_times)
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(odo[:, :3, 3], axis=0), axis=1))])
    win = np.flatnonzero(np.abs(s - s[args.frame]) <= args.window_m)
    view = TrainingView(run, args.frame, win, invert(odo[args.frame]) @ odo[win], 0.0)
    t0 = time.perf_counter()
    points, stats = build_point_features(view, run.camera, run.T_vehicle_camera, return_stats=True)
    out = {"seconds": time.perf_counter() - t0, "stats": stats,
           "bytes": int(sum(v.nbytes for v in points.values()))}
    depth = depth_image(run, args.frame)  # simulated runs only (None otherwise)
    if depth is not None:
        T_cv = invert(run.T_vehicle_camera)
        for kind in stats:
            xyz, kp = points[f"{kind}_xyz"].astype(float), points[f"{kind}_kp"]
            z = xyz @ T_cv[2, :3] + T_cv[2, 3]
            true = depth[np.clip(np.round(kp[:, 1]).astype(int), 0, depth.shape[0] - 1),
                         np.clip(np.round(kp[:, 0]).astype(int), 0, depth.shape[1] - 1)]
            ok = np.isfinite(true)
            out[f"{kind}_depth_rel_error_median"] = float(np.median(np.abs(z[ok] - true[ok]) / true[ok])) if ok.any() else None
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "pointmap", *sys.argv[1:]]))
