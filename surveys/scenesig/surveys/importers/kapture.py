"""kapture (NAVER LABS' pivot format for localisation data, text format 1.1) <-> survey runs.

Written and read here, to the format's specification (``kapture_format.adoc`` in naver/kapture), without
the ``kapture`` package. Every text file starts ``# kapture format: 1.1``; values are comma separated,
spaces around commas ignored; ``#`` lines are comments. Poses are *world to device* (``T_device_world``,
as COLMAP), quaternions ``qw, qx, qy, qz``; timestamps are integers (here nanoseconds).

Export (:func:`export_kapture`) of a run::

    sensors/sensors.txt         <camera_id>, <run name>, camera, PINHOLE|OPENCV|FULL_OPENCV, w, h, fx, fy, cx, cy[, dist]
                                odometry, <odometry source>, odometry        (custom sensor type)
                                gps, , gps_local                              (custom: local metric x, y, z)
                                truth, , pose                                 (custom: simulator's exact poses)
    sensors/rigs.txt            vehicle, <camera_id>, T_camera_vehicle        (the extrinsic)
    sensors/trajectories.txt    t, vehicle, T_vehicle_world                   (groundtruth.tum, inverted)
    sensors/records_camera.txt  t, <camera_id>, <camera_id>/<image file>
    sensors/records_odometry.txt, records_gps_local.txt, records_pose.txt     (odometry.csv, gps.csv, truth.tum)
    sensors/records_data/<camera_id>/...                                      (the images, bytes unchanged)
    scenesig_run.toml           name, conditions, rates, metadata, timestamp unit (what kapture has no place for)

Import (:func:`load_kapture`) of any kapture with a camera and a trajectory: frames from
``records_camera.txt`` for ``--camera``; the intrinsics from ``sensors.txt``; the vehicle frame is the
camera's rig when the camera is in one that has a trajectory (``T_vehicle_camera`` from ``rigs.txt``),
otherwise the camera's own trajectory is used and the vehicle frame is the camera with its axes renamed
(x forward, y left, z up). Odometry comes from ``records_odometry.txt`` when present (a scenesig export),
else from the trajectory itself -- then it is **not** an independent sensor, and ``odometry_noise`` makes
it drift as a real odometer does.
"""
from __future__ import annotations

import math
import shutil
import tomllib
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import CAMERA_FROM_VEHICLE_AXES, Camera, invert, make_pose, pose_to_xyzquat, xyzquat_to_pose
from ..io import atomic_folder
from ..run import FORMAT_VERSION, SurveyRun, dump_toml
from ..settings import merge_settings
from .common import (
    TIMESTAMP_UNITS,
    nominal_rate,
    numbers,
    odometry_from_groundtruth,
    odometry_note,
    odometry_with_noise,
    read_rows,
    ticks_to_seconds,
    write_imported,
)

__all__ = ["default_config", "export_kapture", "load_kapture", "import_kapture", "read_kapture_csv",
           "KAPTURE_VERSION", "TIMESTAMP_UNITS"]

KAPTURE_VERSION = "1.1"
default_config = {
    "camera": None,            # sensor id; None = the only camera
    "timestamp_unit": None,    # ns|us|ms|s; None = scenesig_run.toml's, else ns
    "name": None,
    "conditions": None,        # None = scenesig_run.toml's, else []
    "odometry_noise": 0.0,     # drift added to the recorded odometry, or to the trajectory-derived one
    "odometry_seed": 0,
}
_HEADER = f"# kapture format: {KAPTURE_VERSION}\n"
_POSE_COLS = "qw, qx, qy, qz, tx, ty, tz"
_SIDE = "scenesig_run.toml"


# --------------------------------------------------------------------------------------- text files
def read_kapture_csv(path, min_cols: int) -> list[tuple[int, list[str]]]:
    """``[(line number, fields)]`` of a kapture text file (comments and blank lines skipped; version checked)."""
    rows = read_rows(path, min_cols)
    first = Path(path).read_text(encoding="utf-8").split("\n", 1)[0].strip()
    if first.startswith("# kapture format:"):
        version = first.split(":", 1)[1].strip()
        if not version.startswith("1."):
            raise DataError(path, f"kapture format {version} not supported (this reads 1.x)", 1)
    return rows


def _timestamp(path: Path, n: int, field: str) -> int:
    try:
        return int(field)
    except ValueError:
        raise DataError(path, f"timestamp must be an integer, found {field!r}", n) from None


def _pose(path: Path, n: int, fields: list[str]) -> np.ndarray:
    """``qw, qx, qy, qz, tx, ty, tz`` (world to device) -> the 4x4 ``T_device_world``."""
    qw, qx, qy, qz, tx, ty, tz = numbers(path, n, fields)
    if math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) < 1e-9:
        raise DataError(path, "zero quaternion", n)
    return xyzquat_to_pose([tx, ty, tz, qx, qy, qz, qw])


def _pose_fields(T: np.ndarray) -> list[str]:
    tx, ty, tz, qx, qy, qz, qw = pose_to_xyzquat(T)
    return [repr(float(v)) for v in (qw, qx, qy, qz, tx, ty, tz)]


def _ns(t: float) -> int:
    """Seconds -> integer nanoseconds through the 9-decimal text the run files use (exact round trip)."""
    return int(f"{t:.9f}".replace(".", ""))


def _write(path: Path, columns: str, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [", ".join(str(v) for v in r) for r in rows]
    path.write_text(_HEADER + f"# {columns}\n" + "".join(line + "\n" for line in lines), encoding="utf-8")


# --------------------------------------------------------------------------------------- cameras
def _camera_params(cam: Camera) -> list:
    base = [cam.width, cam.height, repr(cam.fx), repr(cam.fy), repr(cam.cx), repr(cam.cy)]
    d = list(cam.distortion)
    if not any(d):
        return ["PINHOLE"] + base
    d += [0.0] * (5 - len(d))
    if len(cam.distortion) <= 4:
        return ["OPENCV"] + base + [repr(float(v)) for v in d[:4]]
    return ["FULL_OPENCV"] + base + [repr(float(v)) for v in d[:5]] + ["0.0", "0.0", "0.0"]


def _camera_from_params(path: Path, n: int, params: list[str]) -> Camera:
    model, vals = params[0], params[1:]
    nums = numbers(path, n, vals)
    need = {"SIMPLE_PINHOLE": 5, "PINHOLE": 6, "SIMPLE_RADIAL": 6, "RADIAL": 7, "OPENCV": 10, "FULL_OPENCV": 14}
    if model not in need:
        raise DataError(path, f"camera model {model} not supported (PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, "
                              "OPENCV, FULL_OPENCV are)", n)
    if len(nums) != need[model]:
        raise DataError(path, f"{model} needs {need[model]} parameters, found {len(nums)}", n)
    w, h = int(nums[0]), int(nums[1])
    if model.startswith("SIMPLE") or model == "RADIAL":
        f, cx, cy = nums[2:5]
        fx = fy = f
        dist = (nums[5], nums[6] if model == "RADIAL" else 0.0, 0.0, 0.0) if model != "SIMPLE_PINHOLE" else ()
    else:
        fx, fy, cx, cy = nums[2:6]
        dist = tuple(nums[6:11]) if model == "FULL_OPENCV" else tuple(nums[6:10])
        if model == "FULL_OPENCV" and any(nums[11:14]):
            raise DataError(path, "FULL_OPENCV with k4..k6 (rational model) is not supported", n)
    if fx <= 0 or fy <= 0 or w <= 0 or h <= 0:
        raise DataError(path, "camera size and focal length must be positive", n)
    dist = tuple(float(v) for v in dist) if any(dist) else ()
    return Camera(float(fx), float(fy), float(cx), float(cy), w, h, dist)


# --------------------------------------------------------------------------------------- export
def export_kapture(run: SurveyRun, out, camera_id: str = "cam", overwrite: bool = False,
                   progress: bool = True) -> Path:
    """Write ``run`` (read from its folder) as a kapture folder ``out``, atomically; returns ``out``."""
    from tqdm import tqdm

    if run.root is None:
        raise ValueError("the run has no folder to take its images from")
    if not camera_id or any(c in camera_id for c in ",/\\") or camera_id in ("vehicle", "odometry", "gps", "truth"):
        raise ValueError(f"camera id {camera_id!r}: no commas or slashes, and not a name the export uses itself")
    out = Path(out)
    with atomic_folder(out, overwrite, "kapture folder") as tmp:
        s = tmp / "sensors"
        # kapture values must not contain commas; the exact name travels in scenesig_run.toml
        sensors = [[camera_id, run.name.replace(",", " "), "camera"] + _camera_params(run.camera),
                   ["odometry", run.odometry_source.replace(",", " "), "odometry"]]
        if run.gps is not None:
            sensors.append(["gps", "", "gps_local"])
        if run.truth_times is not None:
            sensors.append(["truth", "", "pose"])
        _write(s / "sensors.txt", "sensor_device_id, name, sensor_type, [sensor_params]+", sensors)
        _write(s / "rigs.txt", "rig_device_id, sensor_device_id, " + _POSE_COLS,
               [["vehicle", camera_id] + _pose_fields(invert(run.T_vehicle_camera))])
        if run.groundtruth_times is not None:
            _write(s / "trajectories.txt", "timestamp, device_id, " + _POSE_COLS,
                   [[_ns(t), "vehicle"] + _pose_fields(invert(T))
                    for t, T in zip(run.groundtruth_times, run.groundtruth_poses)])
        paths = [f[len("images/"):] if f.startswith("images/") else f for f in run.frame_files]
        _write(s / "records_camera.txt", "timestamp, device_id, image_path",
               [[_ns(t), camera_id, f"{camera_id}/{p}"] for t, p in zip(run.frame_times, paths)])
        for src, p in zip(tqdm(run.frame_files, desc=f"export {run.name}", unit="frame", disable=not progress), paths):
            dst = s / "records_data" / camera_id / p
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run.root / src, dst)
        _write(s / "records_odometry.txt", "timestamp, device_id, " + _POSE_COLS + "  (T_vehicle_odom)",
               [[_ns(t), "odometry"] + _pose_fields(invert(T)) for t, T in zip(run.odometry_times, run.odometry_poses)])
        if run.gps is not None:
            _write(s / "records_gps_local.txt", "timestamp, device_id, x, y, z",
                   [[_ns(r[0]), "gps"] + [repr(float(v)) for v in r[1:4]] for r in run.gps])
        if run.truth_times is not None:
            _write(s / "records_pose.txt", "timestamp, device_id, " + _POSE_COLS + "  (T_vehicle_world)",
                   [[_ns(t), "truth"] + _pose_fields(invert(T)) for t, T in zip(run.truth_times, run.truth_poses)])
        side = {"scenesig_format_version": FORMAT_VERSION, "name": run.name, "conditions": list(run.conditions),
                "camera_id": camera_id, "timestamp_unit": "ns", "rates": dict(run.rates),
                "metadata": dict(run.metadata)}
        (tmp / _SIDE).write_text(dump_toml(side))
    return out


# --------------------------------------------------------------------------------------- import
def _timed_poses(path: Path, device: str, unit: str):
    """``(times, T_world_device)`` of ``device``'s lines in a pose file (world-to-device on disk)."""
    times, poses, lines = [], [], []
    for n, f in read_kapture_csv(path, 9):
        if f[1] != device:
            continue
        times.append(_timestamp(path, n, f[0]))
        poses.append(_pose(path, n, f[2:9]))
        lines.append(n)
    if not times:
        return None, None
    order = np.argsort(times, kind="stable")
    t = np.asarray(times, dtype=np.int64)[order]
    dup = np.nonzero(np.diff(t) == 0)[0]
    if len(dup):
        raise DataError(path, f"two poses of {device} at timestamp {t[dup[0]]}", lines[order[dup[0] + 1]])
    P = np.asarray(poses)[order]
    return ticks_to_seconds(t, unit), invert(P)


def load_kapture(root, config: dict | None = None) -> tuple[SurveyRun, list[Path]]:
    """Read one camera of a kapture folder as a :class:`SurveyRun` (no writing) and its image files."""
    conf = merge_settings(default_config, config, "kapture import")
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "kapture folder not found")
    s = root / "sensors"
    side = {}
    if (root / _SIDE).is_file():
        try:
            side = tomllib.loads((root / _SIDE).read_text())
        except tomllib.TOMLDecodeError as exc:
            raise DataError(root / _SIDE, f"not valid TOML: {exc}") from None
    unit = conf["timestamp_unit"] or side.get("timestamp_unit", "ns")
    if unit not in TIMESTAMP_UNITS:
        raise ValueError(f"timestamp unit must be one of {', '.join(TIMESTAMP_UNITS)}, not {unit!r}")

    sensors_path = s / "sensors.txt"
    sensors = {}
    for n, f in read_kapture_csv(sensors_path, 3):
        if f[0] in sensors:
            raise DataError(sensors_path, f"sensor id {f[0]!r} defined twice", n)
        sensors[f[0]] = (n, f)
    cameras = [k for k, (_, f) in sensors.items() if f[2] == "camera"]
    cam_id = conf["camera"] or side.get("camera_id")
    if cam_id is None:
        if len(cameras) != 1:
            raise DataError(sensors_path, f"{len(cameras)} cameras ({', '.join(cameras)}): choose one with --camera")
        cam_id = cameras[0]
    if cam_id not in cameras:
        raise DataError(sensors_path, f"no camera {cam_id!r} (cameras: {', '.join(cameras) or 'none'})")
    n, f = sensors[cam_id]
    if len(f) < 4:
        raise DataError(sensors_path, f"camera {cam_id!r} has no model parameters", n)
    camera = _camera_from_params(sensors_path, n, f[3:])

    # frames
    rec_path = s / "records_camera.txt"
    frames = []
    for n, f in read_kapture_csv(rec_path, 3):
        if f[1] == cam_id:
            frames.append((_timestamp(rec_path, n, f[0]), f[2], n))
    if not frames:
        raise DataError(rec_path, f"no images of camera {cam_id!r}")
    frames.sort(key=lambda r: r[0])
    for a, b in zip(frames, frames[1:]):
        if b[0] == a[0]:
            raise DataError(rec_path, f"two images of {cam_id!r} at timestamp {b[0]}", b[2])
    sources = []
    for _, p, n in frames:
        src = s / "records_data" / p
        if not src.is_file():
            raise DataError(rec_path, f"image not found: {src}", n)
        sources.append(src)
    frame_times = ticks_to_seconds([r[0] for r in frames], unit)
    # a scenesig export stores images under <camera id>/; other kaptures keep their own tree
    files = [f"images/{p[len(cam_id) + 1:]}" if p.startswith(cam_id + "/") else f"images/{p}" for _, p, _ in frames]

    # vehicle frame and trajectory
    traj_path = s / "trajectories.txt"
    if not traj_path.is_file():
        raise DataError(traj_path, "file not found: importing needs the poses of the camera or of its rig")
    rig = None
    if (s / "rigs.txt").is_file():
        for n, f in read_kapture_csv(s / "rigs.txt", 9):
            if f[1] == cam_id:
                rig = (f[0], _pose(s / "rigs.txt", n, f[2:9]))
                break
    gt_t = gt_T = None
    if rig is not None:
        gt_t, gt_T = _timed_poses(traj_path, rig[0], unit)
        T_vc = invert(rig[1])
    if gt_t is None:
        gt_t, T_wc = _timed_poses(traj_path, cam_id, unit)
        if gt_t is None:
            raise DataError(traj_path, f"no poses of camera {cam_id!r}" + (f" or of its rig {rig[0]!r}" if rig else ""))
        T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES)
        gt_T = T_wc @ invert(T_vc)

    # odometry: the exporter's own record, or derived from the trajectory
    odo_path = s / "records_odometry.txt"
    odo_t = None
    if odo_path.is_file() and "odometry" in sensors:
        odo_t, odo_P = _timed_poses(odo_path, "odometry", unit)
    note = {}
    if odo_t is None:
        odo_P, odo_source, note = odometry_from_groundtruth(gt_T, conf, "the kapture trajectory")
        odo_t = gt_t
    else:
        odo_source = sensors["odometry"][1][1] or "odometry"
        if float(conf["odometry_noise"]) > 0:  # asked for: drift on top of the recorded odometry
            odo_P = odometry_with_noise(odo_P, float(conf["odometry_noise"]), int(conf["odometry_seed"]))
            note = odometry_note(side.get("metadata", {}).get("odometry", odo_source), conf)
            odo_source += "+noise"
    gps = truth_t = truth_T = None
    if (s / "records_gps_local.txt").is_file():
        gpath = s / "records_gps_local.txt"
        rows = [(n, f) for n, f in read_kapture_csv(gpath, 5) if f[1] == "gps"]
        if rows:
            gps = np.column_stack([ticks_to_seconds([_timestamp(gpath, n, f[0]) for n, f in rows], unit),
                                   [numbers(gpath, n, f[2:5]) for n, f in rows]])
    if (s / "records_pose.txt").is_file():
        truth_t, truth_T = _timed_poses(s / "records_pose.txt", "truth", unit)

    metadata = dict(side.get("metadata", {}))
    if not side:
        metadata["source"] = "kapture"
        metadata["source_path"] = str(root.resolve())
    metadata.update(note)
    rates = side.get("rates") or {"camera_hz": nominal_rate(frame_times), "odometry_hz": nominal_rate(odo_t),
                                  "ins_hz": nominal_rate(gt_t)}
    conditions = conf["conditions"] if conf["conditions"] is not None else side.get("conditions", [])
    run = SurveyRun(
        name=conf["name"] or side.get("name") or f"{root.name}_{cam_id}", conditions=list(conditions),
        camera=camera, T_vehicle_camera=T_vc, rates={k: float(v) for k, v in rates.items()},
        frame_times=frame_times, frame_files=files, odometry_times=odo_t, odometry_poses=odo_P,
        odometry_source=odo_source, groundtruth_times=gt_t, groundtruth_poses=gt_T, truth_times=truth_t,
        truth_poses=truth_T, gps=gps, metadata=metadata,
    )
    return run, sources


def import_kapture(root, out, config: dict | None = None, overwrite: bool = False, progress: bool = True,
                   photometric: str | dict | None = None) -> Path:
    """Import one camera of a kapture folder as the survey run ``out``, written atomically
    (:func:`.common.write_imported`)."""
    run, sources = load_kapture(root, config)
    return write_imported(run, sources, out, overwrite, progress, photometric)
