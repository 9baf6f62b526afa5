"""Detector benchmark: bank detection time and hit rate on a run's frames, priors from its INS, windowed vs
whole image: ``scenesig bench detector MAP RUN``.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from scenesig.localiser.detector import Detector
from scenesig.mapping.store import MapStore
from scenesig.surveys.geometry import invert
from scenesig.surveys.run import read_run

__all__ = ["benchmark", "main"]


def benchmark(map_root, run_root, frames: int = 40, seed: int = 0) -> dict:
    """Detection time and hit rate on a run's frames, priors from the run's INS, windowed vs whole image."""
    store = MapStore.open(map_root)
    run = read_run(run_root)
    det = Detector(store, run.camera, run.T_vehicle_camera)
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(run), size=min(frames, len(run)), replace=False))
    P = np.diag([1e-4, 1e-4, 4e-4, 0.25, 0.25, 0.04])
    out = {}
    for mode in ("windows", "whole_image"):
        ms, hits = [], []
        for i in idx:
            T = run.pose_at(run.frame_times[i])
            place = store.nearest_place(T)
            Twp = store.places[place].T_world_place
            img = run.image(int(i), gray=not det.place(place).bank.hog.get("color", False))
            obs = det.detect(img, place, invert(Twp) @ T, P, whole_image=(mode == "whole_image"))
            ms.append(obs.ms)
            hits.append(len(obs))
        out[mode] = {"ms_per_detection_median": float(np.median(ms)), "detections_mean": float(np.mean(hits))}
    det.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench detector",
                                 description="Time bank detection on a run's frames (priors from its INS).")
    ap.add_argument("map")
    ap.add_argument("run")
    ap.add_argument("--frames", type=int, default=40)
    args = ap.parse_args(argv)
    print(json.dumps(benchmark(args.map, args.run, args.frames), indent=2))
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "detector", *sys.argv[1:]]))
