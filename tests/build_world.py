"""A small simulated world and its map, shared by the map-building and map-figure tests.

The ``tiny`` preset (a 60 m open road, 320x240 images), three runs (sunny, overcast, night) at 4 Hz, and
a build configuration cut down for speed -- places every 20 m (three places), a 12-shape candidate
template mined in two partitions from one frame per run, 9-frame refinement windows, 100 ORB points per
place -- but the same
code path as a full build.  Runs and the reference map are made once per test session (under pytest's
session temp folder) and reused by every module that asks for them.
"""
from __future__ import annotations

import json
from pathlib import Path

RUNS = ["sunny", "overcast", "night"]
SHAPES = {"kinds": [{"name": "square-s", "size": 0.2, "aspect": 1.0, "nx": 3, "ny": 2},
                    {"name": "wide", "size": 0.25, "aspect": 2.0, "nx": 3, "ny": 2}]}
CONFIG = {
    "places": {"spacing_m": 20.0},
    "max_window_frames": 9,
    "mining": {"shapes": SHAPES, "n_partitions": 2},
    "points": {"n_candidates": 500, "max_points": 100},
    # ORB point features (reference and every run's keyframe) for the baseline tests
    "layers": ["signatures", "orb", "orb-all"],
    # the paper's one training frame per run (three images, enough for two partitions): what these tests
    # check does not depend on how many frames a run gives; maps from few runs: tests/test_fewrun.py
    "frames_per_run": 1, "min_images": 3,
}


def tiny_runs(base: Path):
    """The simulated runs (simulated on first use into ``base/tiny_runs``), reference (sunny) first."""
    from scenesig.surveys.run import read_run
    from scenesig.surveys.sim.simulate import simulate

    root = Path(base) / "tiny_runs"
    if not (root / "simulate_summary.json").exists():
        simulate(root, preset="tiny", seed=1, runs=RUNS, camera_hz=4.0, jobs=2, show_progress=False,
                 overwrite=True)
    runs = [read_run(p) for p in sorted(root.iterdir()) if p.is_dir()]
    assert [r.conditions[0] for r in runs] == RUNS
    return runs


def tiny_map(base: Path, jobs: int = 2) -> Path:
    """The reference map of the tiny world: a local joblib build (``base/tiny_map``), built on first use."""
    from scenesig.mapping.build import build_map

    runs = tiny_runs(base)
    root = Path(base) / "tiny_map"
    if not (root / "build_summary.json").exists():
        build_map(runs, runs[0], root, jobs=jobs, progress=False, config=CONFIG)
    return root


def map_contents(root: Path) -> dict:
    """Everything a build writes that must not depend on how it was run: place files (bytes), the
    manifest (parsed) and the build summary without its timing fields."""
    root = Path(root)
    out = {f"places/{p.name}": p.read_bytes() for p in sorted((root / "places").glob("*"))}
    out["manifest.json"] = json.loads((root / "manifest.json").read_text())
    out["manifest.json"].pop("map_id")      # every build draws its own identity (mapping.identity)
    summary = json.loads((root / "build_summary.json").read_text())
    out["build_summary.json"] = {k: v for k, v in summary.items()
                                 if k not in ("seconds", "seconds_per_place_mean", "seconds_per_place_by_layer_mean")}
    return out
