"""``scenesig bench NAME ARGS...``: run a benchmark script of the top-level ``benchmarks`` package.

Each benchmark is ``benchmarks/<module>.py`` with its own ``main(argv) -> int`` (own arguments, JSON on
stdout, ``--json OUT``).  They are imported by name when run -- nothing in the code base imports
``benchmarks`` statically -- so ``scenesig bench NAME --help`` shows the benchmark's own arguments.
"""
from __future__ import annotations

import importlib

#: ``scenesig bench NAME`` -> (module under ``benchmarks``, one-line description)
BENCHMARKS = {
    "heading": ("heading", "GRIEF heading-estimation benchmark (error rate at 20 px)."),
    "speed": ("speed", "Training and detection speed on simulated images."),
    "hog": ("hog", "HOG level and pyramid time on one image."),
    "refine": ("refine", "Landmark refinement accuracy and speed on synthetic windows."),
    "solver": ("solver", "Localisation solver back ends on synthetic problems."),
    "posegraph": ("posegraph", "Sliding-window pose graph on a synthetic drive."),
    "detector": ("detector", "Bank detection time on a run's frames against a map."),
    "render": ("render", "Simulator render speed (frames/s per condition, one core)."),
    "pointmap": ("pointmap", "ORB/SIFT point map of one keyframe: time, size, depth error."),
    "mining": ("mining", "Mine one place's scene signatures from images; mining statistics."),
    "webcam": ("webcam", "Real night/fog/snow matching on fixed webcams (correct within 15 px)."),
    "webcam-speed": ("webcam_speed", "Time targets on webcam images: mining 20 images, detection at 1024x627 (one core)."),
    "simcam": ("simcam", "Simulated fixed webcams (night, fog, snow...): a webcam-layout development folder."),
    "realism": ("realism", "ORB matches across simulated conditions (and GRIEF with --real)."),
    "kitti-import": ("kitti_import", "KITTI raw import speed, frames/s on one core (decode + write)."),
    "rosbag-import": ("rosbag_import", "ROS bag import speed per format (ROS 1, ROS 2, MCAP; raw, JPEG), one core."),
    "rosbag-roundtrip": ("rosbag_roundtrip", "Simulated runs -> bags -> import -> build-map/localise: same map and frames.csv?"),
    "kitti-drive": ("kitti_drive", "KITTI snippet end to end: camera-2 map; camera 3, darkened camera 3 localised."),
    "strict_decode": ("strict_decode", "Cost per VGA frame and catch rate of strict image decoding."),
    "aerial": ("aerial", "Monte-Carlo UAV-to-satellite-map matching (MRSM-CC and baselines)."),
    "absolute-pose": ("absolute_pose", "Robust absolute pose (poselib, pycolmap, OpenCV) on synthetic matches."),
    "profile_localise": ("profile_localise", "Where a deterministic replay spends its time, per stage."),
    "profile_mining": ("profile_mining", "Where one place's mining spends its time, per stage."),
    "places": ("places", "Place recognition on GRIEF data (recall@1, recall@5 per method)."),
    "sequence": ("sequence", "Odometry-free sequence localisation: matched reference frame per query frame, recall@1 within +-N frames."),
    "relocalise": ("relocalise", "Global localisation cost per frame at 30, 100, 300 places."),
    "uncertainty": ("uncertainty", "Honesty of the localiser's 95-percent bounds on outputs with truth (coverage)."),
    "demo_localise": ("demo_localise", "The demo's localisation stage on a finished demo: wall and CPU time."),
    "integrity": ("integrity", "Integrity monitor on many simulated worlds: wrong maps refused, right maps silent."),
    "session": ("session", "Per-call latency of scenesig.Session.add_image (p50/p95/max, CPU) and a paced 5 Hz replay."),
    "hybrid_calibration": ("hybrid_calibration", "Per-type noise scales and the point-dominance count of the hybrid localiser, on runs not reported."),
}


def register(groups):
    for name, (module, help) in BENCHMARKS.items():
        p = groups["bench"].add_parser(name, help=help, description=help, add_help=False)
        p.set_defaults(_run=run, _bench=module, _pass_extra=True)


def run(args) -> int:
    module = importlib.import_module(f"scenesig.benchmarks.{args._bench}")
    return int(module.main(list(args._extra)) or 0)
