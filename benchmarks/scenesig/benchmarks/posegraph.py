"""Pose-graph benchmark: the sliding-window smoother on a synthetic drive: ``scenesig bench posegraph``.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from scenesig.localiser.posegraph import PoseGraph
from scenesig.localiser.solver import pose_exp
from scenesig.surveys.geometry import make_pose, rot_z

__all__ = ["benchmark", "main"]


def benchmark(seconds: float = 60.0, odometry_hz: float = 20.0, localisation_every: int = 4,
              window_seconds: float = 5.0, seed: int = 0) -> dict:
    """Timing of a synthetic drive: odometry at ``odometry_hz``, a localisation every N-th sample.

    Returns ms per odometry message (including the keyframe updates it triggers), ms per
    localisation, ms per smoother update and ms per latest-pose query.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / odometry_hz
    n = int(seconds * odometry_hz)
    step = make_pose(rot_z(0.1 * dt), [10.0 * dt, 0, 0])
    odo_sig = np.array([1e-3, 1e-3, 2e-3, 0.02, 0.01, 0.01])
    loc_sig = np.array([0.005, 0.005, 0.01, 0.3, 0.3, 0.3])
    g = PoseGraph(window_seconds=window_seconds)
    truth = np.eye(4)
    g.reset(0.0, truth, np.diag([1e-4] * 3 + [1e-2] * 3))
    t_odo = t_loc = t_est = 0.0
    n_loc = 0
    for k in range(1, n):
        truth = truth @ step
        meas = step @ pose_exp(rng.normal(0, 1, 6) * odo_sig)
        t0 = time.perf_counter()
        g.add_odometry(k * dt, meas, np.diag(odo_sig ** 2))
        t1 = time.perf_counter()
        if k % localisation_every == 0:
            g.add_localisation(k * dt, truth @ pose_exp(rng.normal(0, 1, 6) * loc_sig), cov=np.diag(loc_sig ** 2))
            n_loc += 1
        t2 = time.perf_counter()
        g.estimate()
        t3 = time.perf_counter()
        t_odo += t1 - t0
        t_loc += t2 - t1
        t_est += t3 - t2
    return {"seconds_simulated": seconds, "odometry_messages": n - 1, "localisations": n_loc,
            "smoother_updates": g.n_updates, "ms_per_odometry_update": 1e3 * t_odo / (n - 1),
            "ms_per_localisation": 1e3 * t_loc / max(n_loc, 1), "ms_per_smoother_update": g.ms_per_update,
            "ms_per_estimate": 1e3 * t_est / (n - 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench posegraph",
                                 description="Time the sliding-window pose graph on a synthetic drive.")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--window", type=float, default=5.0, help="window length (s)")
    args = ap.parse_args(argv)
    print(json.dumps(benchmark(args.seconds, window_seconds=args.window), indent=2))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "posegraph", *sys.argv[1:]]))
