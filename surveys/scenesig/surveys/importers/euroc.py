"""A EuRoC MAV sequence (ASL folder layout) -> a survey run (Burri et al., "The EuRoC micro aerial vehicle
datasets", IJRR 2016).

The layout (``MH_01_easy/`` etc.)::

    mav0/camN/data.csv                            '#timestamp [ns],filename' then one line per image
    mav0/camN/data/<timestamp>.png                752x480 grey images
    mav0/camN/sensor.yaml                         T_BS (camera in the body frame), intrinsics [fu, fv, cu, cv],
                                                  distortion_coefficients [k1, k2, p1, p2] (radial-tangential)
    mav0/state_groundtruth_estimate0/data.csv     timestamp [ns], p_RS_R xyz, q_RS_R wxyz, then velocities, biases

What becomes what:

* frames: ``camN``'s images inside the ground truth's time span (the others counted in the metadata);
  nanosecond timestamps converted to seconds exactly.
* camera: ``intrinsics`` and ``distortion_coefficients`` (radial-tangential only) of ``sensor.yaml``.
* ``T_vehicle_camera``: ``T_BS``; the vehicle frame is EuRoC's body (IMU) frame *as it is* -- it is
  not x forward / z up, and a MAV is not a ground vehicle, so the localiser's SE(2) snapping does not
  apply to these runs (evaluate in 6 DoF).
* ``groundtruth.tum``: ``state_groundtruth_estimate0`` (the body's pose in the gravity-aligned world).
* ``odometry.csv``: **the ground truth itself**, optionally made to drift (``odometry_noise``): not an
  independent sensor.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import Camera, nearest_rotation, xyzquat_to_pose
from ..run import SurveyRun
from ..settings import merge_settings
from .common import (
    find_gaps,
    nominal_rate,
    numbers,
    odometry_from_groundtruth,
    read_rows,
    ticks_to_seconds,
    write_imported,
)

__all__ = ["default_config", "read_sensor_yaml", "read_asl_csv", "load_euroc", "import_euroc"]

default_config = {
    "camera": 0,              # cam0 (left) or cam1 (right)
    "name": None,
    "conditions": [],
    "odometry_noise": 0.0,
    "odometry_seed": 0,
    "gap_factor": 1.5,
}


def read_sensor_yaml(path) -> tuple[Camera, np.ndarray]:
    """A EuRoC camera ``sensor.yaml`` -> (camera, ``T_body_camera``)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file not found")
    text = path.read_text(errors="replace")
    if text.startswith("%YAML:"):  # OpenCV's directive, which PyYAML does not accept
        text = text.split("\n", 1)[1]
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DataError(path, f"not valid YAML: {exc}") from None
    if not isinstance(d, dict):
        raise DataError(path, "not a sensor description")
    try:
        T = np.asarray(d["T_BS"]["data"], dtype=float).reshape(4, 4)
        fu, fv, cu, cv = (float(v) for v in d["intrinsics"])
        w, h = (int(v) for v in d["resolution"])
        dist = tuple(float(v) for v in d.get("distortion_coefficients", ()))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(path, f"missing or malformed camera entry ({exc!r}): needs T_BS.data (16 numbers), "
                              "intrinsics [fu, fv, cu, cv], resolution [w, h]") from None
    model = d.get("distortion_model", "radial-tangential")
    if model != "radial-tangential" and any(dist):
        raise DataError(path, f"distortion model {model!r} not supported (radial-tangential is)")
    if not np.all(np.isfinite(T)) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise DataError(path, "T_BS is not a rigid transform")
    T[:3, :3] = nearest_rotation(T[:3, :3])
    return Camera(fu, fv, cu, cv, w, h, dist if any(dist) else ()), T


def read_asl_csv(path, min_cols: int) -> tuple[np.ndarray, list[list[str]], list[int]]:
    """An ASL ``data.csv`` -> (integer nanosecond timestamps, the other fields, line numbers)."""
    ticks, rows, lines = [], [], []
    for n, parts in read_rows(path, min_cols):
        try:
            t = int(parts[0])
        except ValueError:
            raise DataError(path, f"timestamp must be integer nanoseconds, found {parts[0]!r}", n) from None
        if ticks and t <= ticks[-1]:
            raise DataError(path, f"timestamps must strictly increase: {t} after {ticks[-1]}", n)
        ticks.append(t)
        rows.append(parts[1:])
        lines.append(n)
    if not ticks:
        raise DataError(path, "no data rows")
    return np.asarray(ticks, dtype=np.int64), rows, lines


def _groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    ticks, rows, lines = read_asl_csv(path, 8)
    vals = np.empty((len(rows), 7))
    for i, (r, n) in enumerate(zip(rows, lines)):
        px, py, pz, qw, qx, qy, qz = numbers(path, n, r[:7])
        vals[i] = (px, py, pz, qx, qy, qz, qw)
        if np.linalg.norm(vals[i, 3:]) < 1e-9:
            raise DataError(path, "zero quaternion", n)
    return ticks_to_seconds(ticks, "ns"), xyzquat_to_pose(vals).reshape(-1, 4, 4)


def load_euroc(folder, config: dict | None = None) -> tuple[SurveyRun, list[Path]]:
    """Read one camera of a EuRoC sequence into a :class:`SurveyRun` (no writing) and its image files."""
    conf = merge_settings(default_config, config, "euroc import")
    folder = Path(folder)
    mav = folder / "mav0" if (folder / "mav0").is_dir() else folder
    if not (mav / f"cam{conf['camera']}").is_dir():
        raise DataError(mav / f"cam{conf['camera']}", "camera folder not found (not a EuRoC/ASL sequence?)")
    cam_dir = mav / f"cam{conf['camera']}"
    camera, T_vc = read_sensor_yaml(cam_dir / "sensor.yaml")
    ticks, rows, lines = read_asl_csv(cam_dir / "data.csv", 2)
    times = ticks_to_seconds(ticks, "ns")
    gt_t, T_wv = _groundtruth(mav / "state_groundtruth_estimate0" / "data.csv")
    inside = (times >= gt_t[0]) & (times <= gt_t[-1])
    if not inside.any():
        raise DataError(cam_dir / "data.csv", "no image inside the ground truth's time span "
                                              "(state_groundtruth_estimate0/data.csv)")
    sources = []
    for ok, r, n in zip(inside, rows, lines):
        if ok:
            src = cam_dir / "data" / r[0]
            if not src.is_file():
                raise DataError(cam_dir / "data.csv", f"image not found: {src}", n)
            sources.append(src)
    frame_times = times[inside]
    odo, odo_source, note = odometry_from_groundtruth(T_wv, conf)
    metadata = {
        "source": "euroc", "source_path": str(folder.resolve()), "euroc_camera": int(conf["camera"]),
        "vehicle_frame": "EuRoC body (IMU) frame, not x-forward/z-up", **note,
        "frames_outside_groundtruth": int((~inside).sum()),
        "gaps": find_gaps(frame_times, conf["gap_factor"]),
        "groundtruth_gaps": find_gaps(gt_t, conf["gap_factor"]),
    }
    run = SurveyRun(
        name=conf["name"] or f"{folder.name}_cam{conf['camera']}", conditions=list(conf["conditions"]),
        camera=camera, T_vehicle_camera=T_vc,
        rates={"camera_hz": nominal_rate(frame_times), "odometry_hz": nominal_rate(gt_t), "ins_hz": nominal_rate(gt_t)},
        frame_times=frame_times, frame_files=[f"images/{Path(r[0]).name}" for ok, r in zip(inside, rows) if ok],
        odometry_times=gt_t, odometry_poses=odo, odometry_source=odo_source, groundtruth_times=gt_t,
        groundtruth_poses=T_wv,
        metadata=metadata,
    )
    return run, sources


def import_euroc(folder, out, config: dict | None = None, overwrite: bool = False, progress: bool = True,
                 photometric: str | dict | None = None) -> Path:
    """Import one camera of a EuRoC sequence as the survey run ``out``, written atomically
    (:func:`.common.write_imported`)."""
    run, sources = load_euroc(folder, config)
    return write_imported(run, sources, out, overwrite, progress, photometric)
