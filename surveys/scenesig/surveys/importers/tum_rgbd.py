"""A TUM RGB-D sequence -> a survey run (Sturm et al., "A benchmark for the evaluation of RGB-D SLAM
systems", IROS 2012).

The layout (one folder per sequence, e.g. ``rgbd_dataset_freiburg2_pioneer_360``)::

    rgb.txt           '# ...' comments, then 'timestamp rgb/<timestamp>.png' per colour image
    rgb/              the colour images (640x480 PNG)
    groundtruth.txt   TUM trajectory 'timestamp tx ty tz qx qy qz qw' of the colour camera (motion capture)

What becomes what:

* frames: the colour images of ``rgb.txt`` inside the ground truth's time span (frames before or
  after it cannot be evaluated and have no odometry; their number goes to the metadata).
* camera: the sequence's published calibration, chosen from the folder name (``freiburg1/2/3``) or
  given (``intrinsics``): fr1 and fr2 images are *not* undistorted, so their distortion is kept.
* ``groundtruth.tum``: the motion-capture poses. They are taken as the colour camera's optical frame
  (x right, y down, z forward); the vehicle frame is that camera with its axes renamed (x forward,
  y left, z up), so ``T_vehicle_camera`` is a pure axis permutation. Motion-capture dropouts stay gaps.
* ``odometry.csv``: **the ground truth itself**, optionally made to drift (``odometry_noise``, the
  simulator's VO model): not an independent sensor.

The handheld sequences move in 6 DoF; the localiser's pose snapping to SE(2) assumes a ground
vehicle, so use the robot-mounted ``pioneer`` sequences for localisation figures.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import CAMERA_FROM_VEHICLE_AXES, Camera, invert, make_pose
from ..run import SurveyRun
from ..settings import merge_settings
from ..tum import read_tum
from .common import find_gaps, nominal_rate, numbers, odometry_from_groundtruth, read_rows, write_imported

__all__ = ["default_config", "INTRINSICS", "load_tum_rgbd", "import_tum_rgbd", "read_image_list", "intrinsics_for"]

# The colour cameras' calibration published with the benchmark (k1, k2, p1, p2, k3).
INTRINSICS = {
    "fr1": Camera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": Camera(535.4, 539.2, 320.1, 247.6, 640, 480),
}

default_config = {
    "intrinsics": None,       # "fr1" | "fr2" | "fr3" | a Camera; None = from the folder name
    "name": None,
    "conditions": [],
    "odometry_noise": 0.0,
    "odometry_seed": 0,
    "gap_factor": 1.5,
}


def read_image_list(path) -> tuple[np.ndarray, list[str], list[int]]:
    """``rgb.txt`` -> (times, file names, line numbers); comments skipped, times strictly increasing."""
    times, files, lines = [], [], []
    for n, parts in read_rows(path, 2, sep=None):
        if len(parts) != 2:
            raise DataError(path, f"expected 'timestamp filename', found {' '.join(parts)!r}", n)
        t = numbers(path, n, parts[:1])[0]
        if times and t <= times[-1]:
            raise DataError(path, f"timestamps must strictly increase: {t!r} after {times[-1]!r}", n)
        times.append(t)
        files.append(parts[1])
        lines.append(n)
    if not times:
        raise DataError(path, "no images listed")
    return np.asarray(times), files, lines


def intrinsics_for(folder: Path, intrinsics) -> Camera:
    """The camera for a sequence: given, a preset name, or the preset named in the folder name."""
    if isinstance(intrinsics, Camera):
        return intrinsics
    key = intrinsics
    if key is None:
        for k, tag in (("fr1", "freiburg1"), ("fr2", "freiburg2"), ("fr3", "freiburg3")):
            if tag in folder.name:
                key = k
        if key is None:
            raise DataError(folder, "cannot tell the camera from the folder name (no 'freiburg1/2/3'): "
                                    "give --intrinsics fr1|fr2|fr3 or fx,fy,cx,cy[,k1,k2,p1,p2,k3]")
    if key not in INTRINSICS:
        raise ValueError(f"unknown TUM RGB-D camera {key!r} (fr1, fr2, fr3)")
    return INTRINSICS[key]


def load_tum_rgbd(folder, config: dict | None = None) -> tuple[SurveyRun, list[Path]]:
    """Read a TUM RGB-D sequence into a :class:`SurveyRun` (no writing) and its image files."""
    conf = merge_settings(default_config, config, "tum_rgbd import")
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "TUM RGB-D sequence folder not found")
    camera = intrinsics_for(folder, conf["intrinsics"])
    times, files, lines = read_image_list(folder / "rgb.txt")
    gt_t, T_wc = read_tum(folder / "groundtruth.txt")
    inside = (times >= gt_t[0]) & (times <= gt_t[-1])
    if not inside.any():
        raise DataError(folder / "rgb.txt", f"no image inside the ground truth's time span "
                                            f"[{gt_t[0]!r}, {gt_t[-1]!r}] (groundtruth.txt)")
    sources = []
    for ok, f, n in zip(inside, files, lines):
        if ok:
            src = folder / f
            if not src.is_file():
                raise DataError(folder / "rgb.txt", f"image not found: {src}", n)
            sources.append(src)
    frame_times = times[inside]
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES)
    T_wv = T_wc @ invert(T_vc)
    odo, odo_source, note = odometry_from_groundtruth(T_wv, conf)
    metadata = {
        "source": "tum_rgbd", "source_path": str(folder.resolve()), **note,
        "frames_outside_groundtruth": int((~inside).sum()),
        "gaps": find_gaps(frame_times, conf["gap_factor"]),
        "groundtruth_gaps": find_gaps(gt_t, conf["gap_factor"]),
    }
    run = SurveyRun(
        name=conf["name"] or folder.name, conditions=list(conf["conditions"]), camera=camera, T_vehicle_camera=T_vc,
        rates={"camera_hz": nominal_rate(frame_times), "odometry_hz": nominal_rate(gt_t), "ins_hz": nominal_rate(gt_t)},
        frame_times=frame_times, frame_files=[f"images/{Path(f).name}" for f in np.array(files)[inside]],
        odometry_times=gt_t, odometry_poses=odo, odometry_source=odo_source,
        groundtruth_times=gt_t, groundtruth_poses=T_wv, metadata=metadata,
    )
    return run, sources


def import_tum_rgbd(folder, out, config: dict | None = None, overwrite: bool = False, progress: bool = True,
                    photometric: str | dict | None = None) -> Path:
    """Import a TUM RGB-D sequence as the survey run ``out``, written atomically
    (:func:`.common.write_imported`)."""
    run, sources = load_tum_rgbd(folder, config)
    return write_imported(run, sources, out, overwrite, progress, photometric)
