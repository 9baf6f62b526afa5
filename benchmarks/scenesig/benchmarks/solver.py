"""Solver benchmark: ms per solve of the localisation problem (McManus et al. 2015, §3.4, eq. 10) per
back end, and the pose error, on synthetic problems: ``scenesig bench solver``.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from scenesig.localiser.solver import pose_log, solve
from scenesig.localiser.synthetic import synthetic_problem
from scenesig.surveys.geometry import invert

__all__ = ["benchmark", "main"]


def benchmark(n_detections=50, repeats=50, outlier_fraction=0.2, backends=("numpy", "gtsam")) -> dict:
    """Median ms per solve per back end, and the pose error, on synthetic problems (generated first)."""
    problems = [synthetic_problem(n_detections, outlier_fraction, seed=s) for s in range(repeats)]
    out = {"n_detections": n_detections, "outlier_fraction": outlier_fraction, "repeats": repeats}
    for backend in backends:
        cfg = {"backend": backend}
        solve(**{k: v for k, v in problems[0].items() if k not in ("T_true", "outliers")}, config=cfg)  # warm-up
        ms, err_t, err_r, ok = [], [], [], 0
        for p in problems:
            res = solve(**{k: v for k, v in p.items() if k not in ("T_true", "outliers")}, config=cfg)
            ms.append(res.ms)
            ok += res.ok
            d = invert(p["T_true"]) @ res.T_place_vehicle
            err_t.append(np.linalg.norm(d[:3, 3]))
            err_r.append(np.degrees(np.linalg.norm(pose_log(d)[:3])))
        out[backend] = {"ms_per_solve_median": float(np.median(ms)), "ms_per_solve_p95": float(np.percentile(ms, 95)),
                        "ok_fraction": ok / repeats, "translation_error_m_median": float(np.median(err_t)),
                        "rotation_error_deg_median": float(np.median(err_r))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench solver",
                                 description="Benchmark the eq. 10 solver back ends on synthetic problems.")
    ap.add_argument("--detections", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--outliers", type=float, default=0.2, help="outlier fraction")
    ap.add_argument("--backends", default="numpy,gtsam")
    args = ap.parse_args(argv)
    print(json.dumps(benchmark(args.detections, args.repeats, args.outliers, tuple(args.backends.split(","))),
                     indent=2))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "solver", *sys.argv[1:]]))
