"""Landmark-refinement benchmark: accuracy and speed of the temporal check, depth sweep and
Levenberg-Marquardt with Huber weights (McManus et al. 2015, §3.3) on synthetic windows:
``scenesig bench refine`` (one JSON line per path: straight, curved).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from scenesig.localiser.synthetic import synthetic_window
from scenesig.mapping.refine import REASONS, refine_landmarks

__all__ = ["benchmark", "main"]


def benchmark(n_landmarks=300, n_frames=21, path="straight", sigma_px=1.0, n_random=30, seed=0,
              repeats=3, config=None) -> dict:
    """Accuracy and speed of :func:`refine_landmarks` on :func:`synthetic_window` (one place)."""
    w = synthetic_window(n_landmarks=n_landmarks, n_frames=n_frames, path=path, sigma_px=sigma_px,
                         n_random=n_random, seed=seed)
    args = (w["detections"], w["T_window_place"], w["camera"], w["T_vehicle_camera"], w["reference"], w["Q"])
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = refine_landmarks(*args, config=config)
        times.append(time.perf_counter() - t0)
    true = ~w["random"]
    kept = res.kept & true
    rel = np.abs(res.depth[kept] - w["depth"][kept]) / w["depth"][kept]
    err = res.points[kept] - w["points"][kept]
    m2 = np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.covariances[kept]), err)
    return {
        "landmarks": int(true.sum()), "random_classifiers": int(w["random"].sum()), "frames": n_frames,
        "path": path, "sigma_px": sigma_px,
        "kept_true": int(kept.sum()),
        "rejected_true": {r: int(((res.reason == r) & true).sum()) for r in REASONS},
        "random_rejected": {r: int(((res.reason == r) & w["random"]).sum()) for r in REASONS},
        "random_kept": int((res.kept & w["random"]).sum()),
        "depth_rel_error_median": float(np.median(rel)) if rel.size else None,
        "depth_rel_error_p90": float(np.percentile(rel, 90)) if rel.size else None,
        "within_95pct_ellipsoid": float(np.mean(m2 <= 7.815)) if rel.size else None,
        "seconds_median": float(np.median(times)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench refine",
                                 description="Synthetic accuracy/speed benchmark of landmark refinement.")
    ap.add_argument("--landmarks", type=int, default=300)
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--random", type=int, default=30, help="classifiers firing at random (of --landmarks)")
    ap.add_argument("--sigma", type=float, default=1.0, help="base pixel noise (px)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for path in ("straight", "curved"):
        print(json.dumps(benchmark(args.landmarks, args.frames, path, args.sigma, args.random, args.seed)))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "refine", *sys.argv[1:]]))
