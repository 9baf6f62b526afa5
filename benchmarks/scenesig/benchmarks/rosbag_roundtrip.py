"""Round trip: simulated runs -> ROS bags -> ``import rosbag`` -> ``build-map`` / ``localise``: prints JSON.

    python -m scenesig.benchmarks.rosbag_roundtrip [--work DIR] [--format mcap] [--images raw] [--json OUT]

Simulates the tiny world (seed 1: sunny, overcast and night training runs, a fog live run, 4 Hz), writes
every run as a bag (``scenesig.surveys.importers.rosbag.write_run_bag``; raw ``sensor_msgs/Image`` by default, which
the importer stores as PNG: lossless), imports each back, then builds the map from the three training runs
and localises the fog run against it, both from the original runs and from the imported ones, with the
same commands (``scenesig build-map``, ``scenesig localise``). Reports whether the map's files (place files
byte for byte, manifest) and the localisation's ``frames.csv`` and ``trajectory.tum`` are identical and,
where they are not, the largest difference -- and repeats the original build with every pose and the
extrinsic passed once through a quaternion, as ROS messages carry them (matrix -> quaternion -> matrix
rounds in the last bit), and with ``--images raw|png`` the frames decoded and stored as PNG as the import
stores them, to tell those two exactly explained changes from anything else.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RUNS = ["sunny", "overcast", "night", "fog"]
CONFIG = {  # tests/build_world.py's cut-down build (three places, 12 shapes): the full code path, fast
    "places": {"spacing_m": 20.0}, "max_window_frames": 9,
    "mining": {"shapes": {"kinds": [{"name": "square-s", "size": 0.2, "aspect": 1.0, "nx": 3, "ny": 2},
                                    {"name": "wide", "size": 0.25, "aspect": 2.0, "nx": 3, "ny": 2}]},
               "n_partitions": 2},
    "points": {"n_candidates": 500, "max_points": 100}, "layers": ["signatures", "orb", "orb-all"], "frames_per_run": 1, "min_images": 3,
}


def _cli(*argv) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "scenesig", *map(str, argv)], capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"scenesig {' '.join(map(str, argv))} failed:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


def _through_quaternion(P):
    """Poses as a ROS message carries them: matrix -> (x, y, z, qx, qy, qz, qw) -> matrix."""
    import numpy as np

    from scenesig.surveys.geometry import pose_to_xyzquat, xyzquat_to_pose

    return None if P is None else xyzquat_to_pose(pose_to_xyzquat(P)).reshape(np.shape(P))


def _map_files(root: Path) -> dict:
    out = {f"places/{p.name}": p.read_bytes() for p in sorted((root / "places").glob("*"))}
    out["manifest.json"] = json.loads((root / "manifest.json").read_text())
    return out


def _pipeline(runs: dict, work: Path) -> Path:
    """build-map from the training runs, localise the fog run; returns ``work``."""
    train = [runs[c] for c in RUNS[:3]]
    work.mkdir(parents=True, exist_ok=True)
    (work / "config.json").write_text(json.dumps(CONFIG))
    _cli("build-map", *train, "--reference", train[0], "--out", work / "map", "--jobs", "2",
         "--config", work / "config.json")
    _cli("localise", work / "map", runs["fog"], "--method", "signatures", "--out", work / "loc")
    return work


def _compare(a: Path, b: Path) -> dict:
    import numpy as np

    ma, mb = _map_files(a / "map"), _map_files(b / "map")
    differing = sorted(k for k in set(ma) | set(mb) if ma.get(k) != mb.get(k))
    fa, fb = (p / "loc" / "frames.csv" for p in (a, b))
    ta, tb = (np.loadtxt(p / "loc" / "trajectory.tum", ndmin=2) for p in (a, b))
    same_traj = (a / "loc" / "trajectory.tum").read_bytes() == (b / "loc" / "trajectory.tum").read_bytes()
    fr = [p.read_text().splitlines() for p in (fa, fb)]
    mets = [json.loads((p / "loc" / "metrics.json").read_text()) for p in (a, b)]
    keys = ("lateral_error_m", "heading_error_deg", "localised_fraction", "failures")
    return {"map_files": len(ma), "map_files_differing": differing,
            "frames_csv_rows_differing": sum(x != y for x, y in zip(*fr)) + abs(len(fr[0]) - len(fr[1])),
            "frames_csv_rows": len(fr[0]) - 1,
            "metrics": [{k: m.get(k) for k in keys} for m in mets],
            "frames_csv_identical": fa.read_bytes() == fb.read_bytes(),
            "trajectory_tum_identical": same_traj,
            "trajectory_max_position_difference_m": (float(np.abs(ta[:, 1:4] - tb[:, 1:4]).max())
                                                     if ta.shape == tb.shape else None)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m scenesig.benchmarks.rosbag_roundtrip", description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="working folder (default: a temporary one)")
    ap.add_argument("--format", choices=["ros1", "ros2", "mcap"], default="mcap")
    ap.add_argument("--images", choices=["raw", "png", "jpeg"], default="raw")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    from scenesig.surveys.importers.rosbag import import_rosbag, write_run_bag
    from scenesig.surveys.run import read_run, write_run
    from scenesig.surveys.sim.simulate import simulate

    tmp = None if args.work else tempfile.TemporaryDirectory()
    work = Path(args.work or tmp.name)
    t0 = time.perf_counter()
    world = work / "world"
    if not (world / "simulate_summary.json").exists():
        simulate(world, preset="tiny", seed=1, runs=RUNS, camera_hz=4.0, jobs=2, show_progress=False, overwrite=True)
    originals = {r.conditions[0]: r for r in (read_run(p) for p in sorted(world.iterdir()) if p.is_dir())}
    bags, imported, qext = {}, {}, {}
    t_import = 0.0
    for cond, run in originals.items():
        name = f"{run.name}.bag" if args.format == "ros1" else run.name
        bags[cond] = write_run_bag(run, work / "bags" / name, args.format, images=args.images, progress=False,
                                   overwrite=True)
        t1 = time.perf_counter()
        topic = "/camera/image_raw" if args.images == "raw" else "/camera/image_raw/compressed"
        imported[cond] = import_rosbag(bags[cond], work / "imported" / run.name, {
            "image_topic": topic, "camera_info_topic": "/camera/camera_info", "odom_topic": "/odom",
            "gt_topic": "/ins", "truth_topic": "/truth", "name": run.name, "conditions": run.conditions},
            overwrite=True, progress=False)
        t_import += time.perf_counter() - t1
        # control: the original run with its poses and extrinsic once through a quaternion, as a bag carries them
        q = dataclasses.replace(run, T_vehicle_camera=_through_quaternion(run.T_vehicle_camera),
                                odometry_poses=_through_quaternion(run.odometry_poses),
                                groundtruth_poses=_through_quaternion(run.groundtruth_poses),
                                truth_poses=_through_quaternion(run.truth_poses))
        images = None
        if args.images != "jpeg":  # and, for decoded images, the same frames as the import's lossless PNGs
            import cv2

            q = dataclasses.replace(q, frame_files=[f"images/{i:06d}.png" for i in range(len(run))])
            images = (cv2.imencode(".png", run.image(i))[1].tobytes() for i in range(len(run)))
        qext[cond] = write_run(q, work / "original_quaternions" / run.name, images=images, overwrite=True)
    a = _pipeline({c: r.root for c, r in originals.items()}, work / "out_original")
    b = _pipeline(imported, work / "out_bag")
    result = {"benchmark": "rosbag_roundtrip", "format": args.format, "images": args.images,
              "runs": {c: len(r) for c, r in originals.items()},
              "import_seconds": round(t_import, 2), "original_vs_bag": _compare(a, b)}
    if result["original_vs_bag"]["map_files_differing"] or not result["original_vs_bag"]["frames_csv_identical"]:
        c = _pipeline(qext, work / "out_original_quaternions")
        result["bag_vs_original_through_quaternions"] = _compare(c, b)
        result["original_vs_original_through_quaternions"] = _compare(a, c)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        from scenesig.surveys.io import atomic_write_text

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, text + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
