"""The first real drive end to end: a map from KITTI camera 2 (one run), camera 3 and a darkened camera 3
localised against it by signatures and the point-feature baselines; prints JSON.

    python -m scenesig.benchmarks.kitti_drive [DRIVE_DIR] [--work DIR] [--methods signatures,orb,sift] [--jobs 2]
                                     [--map-photometric dusk,night] [--json OUT]

Camera 3 looks at the same street at the same time, 0.54 m to the right of camera 2 with its own
extrinsic; the vehicle (OXTS/IMU) trajectory is the same for both, so the errors against OXTS measure
the geometry -- camera model, extrinsics, landmark depths, pose solve -- on real images. The night
replay is camera 3 darkened by :mod:`scenesig.surveys.importers.photometric` (a photometric transform of day
images, not real night). Targets (camera 3): lateral median <= 0.3 m, heading median <= 1 deg, no failure.

The map is built from the camera-2 run alone (the protocol). ``--map-photometric`` adds photometric
copies of that same run (same camera, same instant, :data:`scenesig.surveys.importers.photometric.PRESETS`) as
extra training runs, for a map builder that needs several runs per place; the JSON says which were used.
Exit status 0 when every step ran (whether or not the targets are met), 3 when the map could not be built.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_DRIVE = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "kitti" / "2011_09_26_snippet"
TARGETS = {"lateral_median_m": 0.3, "heading_median_deg": 1.0, "failures": 0}


def _summary(m: dict) -> dict:
    return {"lateral_median_m": m["lateral_error_m"]["median"], "lateral_p95_m": m["lateral_error_m"]["p95"],
            "heading_median_deg": m["heading_error_deg"]["median"], "heading_p95_deg": m["heading_error_deg"]["p95"],
            "localised_fraction": m["localised_fraction"], "failures": m["failures"],
            "truth_source": m.get("truth_source")}


def _emit(result: dict, json_path) -> None:
    """Print the JSON, and write it atomically to ``json_path`` if given."""
    from scenesig.surveys.io import atomic_write_text

    text = json.dumps(result, indent=1)
    print(text)
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, text + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.kitti_drive", description=__doc__.splitlines()[0])
    ap.add_argument("drive", nargs="?", default=str(DEFAULT_DRIVE))
    ap.add_argument("--work", default=None, help="keep runs, map and replays here (default: a temporary folder)")
    ap.add_argument("--methods", default="signatures,orb,sift")
    ap.add_argument("--jobs", type=int, default=1, help="places built in parallel")
    ap.add_argument("--every", type=int, default=4, help="detector on every N-th frame")
    ap.add_argument("--map-photometric", default="", metavar="PRESET[,PRESET]",
                    help="also train on these photometric copies of the camera-2 run (default: none)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    drive = Path(args.drive)
    if not drive.is_dir():
        print(f"kitti_drive: drive not found: {drive} (the shared data is expected at ../shared/data)", file=sys.stderr)
        return 2
    from scenesig.localiser.replay import localise
    from scenesig.mapping.build import build_map
    from scenesig.surveys.importers.kitti_raw import import_kitti_raw
    from scenesig.surveys.run import read_run

    tmp = None if args.work else tempfile.TemporaryDirectory()
    work = Path(args.work or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    runs = {"cam2": ({"camera": 2, "conditions": ["day"]}, None),
            "cam3": ({"camera": 3, "conditions": ["day"]}, None),
            "cam3_night": ({"camera": 3, "conditions": ["night"], "name": "2011_09_26_snippet_cam3_night"}, "night")}
    extra = [p for p in args.map_photometric.split(",") if p]
    for p in extra:
        runs[f"cam2_{p}"] = ({"camera": 2, "conditions": [p], "name": f"2011_09_26_snippet_cam2_{p}"}, p)
    for key, (conf, photometric) in runs.items():
        if not (work / key).exists():
            import_kitti_raw(drive, work / key, conf, photometric=photometric, progress=False)
    map_runs = ["cam2"] + [f"cam2_{p}" for p in extra]
    result = {"benchmark": "kitti_drive", "drive": str(drive.resolve()), "map_runs": map_runs, "targets": TARGETS,
              "photometric_night": read_run(work / "cam3_night", check_images=False).metadata.get("photometric_transform")}
    t0 = time.perf_counter()
    try:
        build = build_map([read_run(work / k) for k in map_runs], read_run(work / "cam2"), work / "map", jobs=args.jobs)
    except (ValueError, RuntimeError) as exc:
        result["build"] = {"error": f"{type(exc).__name__}: {exc}"}
        _emit(result, args.json)
        return 3
    result["build"] = {"seconds": round(time.perf_counter() - t0, 1), "places": build.get("places"),
                       "signatures_per_place_mean": build.get("signatures_per_place_mean")}
    result["replays"] = {}
    for key in ("cam3", "cam3_night"):
        result["replays"][key] = {}
        for method in args.methods.split(","):
            m = localise(work / "map", work / key, work / "out" / key / method, method=method, every=args.every,
                         progress=False)
            result["replays"][key][method] = _summary(m)
    s = result["replays"]["cam3"].get("signatures")
    if s:
        result["targets_met"] = {"lateral": s["lateral_median_m"] <= TARGETS["lateral_median_m"],
                                 "heading": s["heading_median_deg"] <= TARGETS["heading_median_deg"],
                                 "no_failure": s["failures"] == 0}
    _emit(result, args.json)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
