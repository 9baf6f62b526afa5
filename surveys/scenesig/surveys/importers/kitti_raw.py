"""A KITTI raw drive -> a survey run (Geiger et al., "Vision meets robotics: the KITTI dataset", IJRR 2013).

The KITTI raw layout::

    DRIVE/image_0{2,3}/data/NNNNNNNNNN.{png,jpg}   rectified colour cameras (left, right)
    DRIVE/image_0{2,3}/timestamps.txt             one line per frame index: 2011-09-26 13:04:32.345808896
    DRIVE/oxts/data/NNNNNNNNNN.txt                30 numbers per frame (oxts/dataformat.txt names them)
    DRIVE/oxts/timestamps.txt
    calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt   in DRIVE or its parent (the date folder)

What becomes what:

* frames: the camera's image files, timed by its ``timestamps.txt`` (line ``i + 1`` for file ``i``).
  Missing files and dropped frames stay gaps; nothing is interpolated. Trailing timestamp lines with
  no file (a drive cut short, as the shared 91-frame snippet is) are ignored and counted.
* camera: the *rectified* projection ``P_rect_0c`` gives fx, fy, cx, cy (no distortion: the images
  are rectified) and the size ``S_rect_0c``.
* ``T_vehicle_camera``: the vehicle frame is the OXTS/IMU frame (x forward, y left, z up, as ours).
  The calibration chain is IMU -> velodyne -> camera 0 -> rectified camera 0 -> rectified camera c:
  ``T_c_imu = [I | K^-1 P_rect_0c[:, 3]] @ R_rect_00 @ T_cam0_velo @ T_velo_imu``, inverted.
* ``groundtruth.tum``: OXTS poses as the KITTI devkit makes them (``convertOxtsToPose``):
  Mercator projection with scale ``s = cos(lat0)`` from the first sample's latitude,
  ``x = s R lon``, ``y = s R ln tan(pi/4 + lat/2)`` (R = 6378137 m), ``z = alt``; orientation
  ``Rz(yaw) Ry(pitch) Rx(roll)``. Unlike the devkit we keep the axes east-north-up and only move the
  origin to the first sample, so the world frame is level and ``gps.csv`` shares it; the origin
  (lat0, lon0, alt0) and the scale go to the run's metadata.
* ``odometry.csv``: the OXTS forward and leftward velocities and the yaw rate about the up axis,
  integrated in the plane (:func:`.common.planar_dead_reckoning`) -- a wheel-odometry-like signal.
  **It is not independent of the INS**: the OXTS velocities come from the same GPS/IMU filter as the
  ground truth, so it drifts far less than a real odometer. ``odometry_noise`` (a factor on the
  simulator's VO error model) makes it drift as a real odometer does.
* ``gps.csv``: OXTS latitude/longitude/altitude in the same local metric frame.
"""
from __future__ import annotations

import datetime as _dt
import math
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import Camera, invert, make_pose, nearest_rotation, rot_x, rot_y, rot_z
from ..run import SurveyRun
from ..settings import merge_settings
from .common import (
    find_gaps,
    nominal_rate,
    numbers,
    odometry_note,
    odometry_with_noise,
    planar_dead_reckoning,
    write_imported,
)

__all__ = ["default_config", "read_calib", "read_timestamps", "read_oxts", "oxts_poses", "camera_from_calib",
           "load_kitti_raw", "import_kitti_raw", "OXTS_FIELDS", "EARTH_RADIUS"]

default_config = {
    "camera": 2,              # 2 = left colour, 3 = right colour (0, 1: grey)
    "name": None,             # run name (default: drive folder name + "_cam<c>")
    "conditions": [],         # condition tags for run.toml, e.g. ["day", "overcast"]
    "odometry_noise": 0.0,    # factor on the simulator's VO error model; 0 = the clean OXTS signal
    "odometry_seed": 0,
    "gap_factor": 1.5,        # an interval over this many median intervals is a dropped frame
}

EARTH_RADIUS = 6378137.0  # m, as the KITTI devkit's latToScale / latlonToMercator
OXTS_FIELDS = ("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az",
               "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy",
               "navstat", "numsats", "posmode", "velmode", "orimode")
_F = {name: i for i, name in enumerate(OXTS_FIELDS)}
_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")


# --------------------------------------------------------------------------------------- parsing
def read_calib(path) -> dict[str, np.ndarray]:
    """A KITTI ``calib_*.txt``: ``KEY: v v v ...`` per line -> ``{KEY: float array}`` (``calib_time`` skipped)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "calibration file not found (KITTI raw keeps calib_*.txt in the drive's date folder)")
    out = {}
    for n, raw in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        if not raw.strip():
            continue
        key, sep, rest = raw.partition(":")
        if not sep:
            raise DataError(path, f"expected 'KEY: values', found {raw.strip()!r}", n)
        key = key.strip()
        if key == "calib_time":
            continue
        out[key] = np.array(numbers(path, n, rest.split()), dtype=float)
        out.setdefault("_lines", {})[key] = n
    return out


def _calib_entry(calib: dict, path: Path, key: str, size: int) -> np.ndarray:
    if key not in calib:
        raise DataError(path, f"missing {key}")
    v = calib[key]
    if v.size != size:
        raise DataError(path, f"{key} needs {size} numbers, found {v.size}", calib["_lines"][key])
    return v


def _rigid(calib: dict, path: Path) -> np.ndarray:
    R = _calib_entry(calib, path, "R", 9).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise DataError(path, "R is not a rotation matrix", calib["_lines"]["R"])
    return make_pose(nearest_rotation(R), _calib_entry(calib, path, "T", 3))


def parse_kitti_time(text: str) -> float:
    """``2011-09-26 13:04:32.345808896`` -> seconds since the epoch (the clock read as UTC), nanoseconds kept."""
    s = text.strip()
    date, _, frac = s.partition(".")
    base = _dt.datetime.strptime(date, "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc).timestamp()
    if frac and not frac.isdigit():
        raise ValueError(s)
    return base + (int(frac) / 10 ** len(frac) if frac else 0.0)


def read_timestamps(path) -> np.ndarray:
    """A KITTI ``timestamps.txt`` -> (N,) seconds; line ``i + 1`` belongs to frame ``i``."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file not found")
    out = []
    for n, raw in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        if not raw.strip():
            if n == 1:
                raise DataError(path, "empty timestamp line", n)
            break  # a final blank line ends the file
        try:
            out.append(parse_kitti_time(raw))
        except ValueError:
            raise DataError(path, f"not a timestamp 'YYYY-MM-DD HH:MM:SS.fffffffff': {raw.strip()!r}", n) from None
        if len(out) > 1 and out[-1] <= out[-2]:
            raise DataError(path, f"timestamps must strictly increase: {raw.strip()!r} after line {n - 1}", n)
    if not out:
        raise DataError(path, "no timestamps")
    return np.asarray(out)


def read_oxts(paths) -> np.ndarray:
    """OXTS packets, one file each -> (N, 30); a short, non-numeric or non-finite line is a DataError."""
    out = np.empty((len(paths), len(OXTS_FIELDS)))
    for i, p in enumerate(paths):
        try:
            line = Path(p).read_text().split("\n", 1)[0]
        except OSError:
            raise DataError(p, "OXTS file missing or unreadable") from None
        parts = line.split()
        if len(parts) != len(OXTS_FIELDS):
            raise DataError(p, f"expected {len(OXTS_FIELDS)} values (see oxts/dataformat.txt), found {len(parts)}"
                               " -- truncated line?", 1)
        out[i] = numbers(p, 1, parts)
    return out


def _indexed_files(folder: Path, exts: tuple[str, ...]) -> dict[int, Path]:
    """``{frame index: path}`` of the ``NNNNNNNNNN.ext`` files in ``folder``."""
    if not folder.is_dir():
        raise DataError(folder, "folder not found (not a KITTI raw drive?)")
    out = {}
    for p in folder.iterdir():
        if p.suffix.lower() in exts and p.stem.isdigit():
            out[int(p.stem)] = p
    if not out:
        raise DataError(folder, f"no {'/'.join(exts)} files named by frame index")
    return dict(sorted(out.items()))


# --------------------------------------------------------------------------------------- geometry
def oxts_poses(oxts: np.ndarray, origin: tuple[float, float, float] | None = None) -> tuple[np.ndarray, dict]:
    """``T_world_imu`` (N,4,4) from OXTS packets, and the frame's definition.

    The KITTI devkit's Mercator projection (scale ``cos(lat0)``), east-north-up axes, origin at
    ``origin`` = (lat0, lon0, alt0) (default: the first packet).
    """
    lat, lon, alt = oxts[:, 0], oxts[:, 1], oxts[:, 2]
    lat0, lon0, alt0 = origin if origin is not None else (float(lat[0]), float(lon[0]), float(alt[0]))
    scale = math.cos(math.radians(lat0))
    mx = scale * EARTH_RADIUS * np.radians(lon)
    my = scale * EARTH_RADIUS * np.log(np.tan(np.radians(90.0 + lat) / 2.0))
    mx0 = scale * EARTH_RADIUS * math.radians(lon0)
    my0 = scale * EARTH_RADIUS * math.log(math.tan(math.radians(90.0 + lat0) / 2.0))
    T = np.tile(np.eye(4), (len(oxts), 1, 1))
    for i, (r, p, y) in enumerate(oxts[:, 3:6]):
        T[i, :3, :3] = rot_z(y) @ rot_y(p) @ rot_x(r)
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = mx - mx0, my - my0, alt - alt0
    frame = {"projection": "mercator (KITTI devkit)", "mercator_scale": scale, "earth_radius_m": EARTH_RADIUS,
             "lat0_deg": lat0, "lon0_deg": lon0, "alt0_m": alt0, "axes": "east-north-up"}
    return T, frame


def camera_from_calib(folder, camera: int) -> tuple[Camera, np.ndarray]:
    """The rectified camera ``c`` and ``T_imu_camera`` from the three calibration files in ``folder``."""
    folder = Path(folder)
    c2c_path, v2c_path, i2v_path = (folder / f for f in _CALIB_FILES)
    c2c = read_calib(c2c_path)
    P = _calib_entry(c2c, c2c_path, f"P_rect_0{camera}", 12).reshape(3, 4)
    size = _calib_entry(c2c, c2c_path, f"S_rect_0{camera}", 2)
    R_rect = _calib_entry(c2c, c2c_path, "R_rect_00", 9).reshape(3, 3)
    if not np.allclose(R_rect @ R_rect.T, np.eye(3), atol=1e-4):
        raise DataError(c2c_path, "R_rect_00 is not a rotation matrix", c2c["_lines"]["R_rect_00"])
    K = P[:, :3]
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[0, 1]) > 1e-9 or np.any(np.abs(K[2] - [0, 0, 1]) > 1e-9):
        raise DataError(c2c_path, f"P_rect_0{camera} is not a rectified projection [K | K t]",
                        c2c["_lines"][f"P_rect_0{camera}"])
    cam = Camera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(round(size[0])),
                 int(round(size[1])))
    # the rectified cameras share R_rect_00's orientation and differ by the baseline in P's last column
    T_c_rect0 = make_pose(None, np.linalg.solve(K, P[:, 3]))
    T_cam0_velo = _rigid(read_calib(v2c_path), v2c_path)
    T_velo_imu = _rigid(read_calib(i2v_path), i2v_path)
    T_c_imu = T_c_rect0 @ make_pose(nearest_rotation(R_rect)) @ T_cam0_velo @ T_velo_imu
    return cam, invert(T_c_imu)


def _calib_folder(drive: Path) -> Path:
    """The folder holding the three calibration files: the drive itself or its date folder."""
    for folder in (drive, drive.parent):
        if all((folder / f).is_file() for f in _CALIB_FILES):
            return folder
    here = drive if any((drive / f).is_file() for f in _CALIB_FILES) else drive.parent
    missing = next(f for f in _CALIB_FILES if not (here / f).is_file())
    raise DataError(here / missing, "calibration file not found (KITTI raw needs calib_cam_to_cam.txt, "
                                    "calib_velo_to_cam.txt and calib_imu_to_velo.txt in the drive or its date folder)")


# --------------------------------------------------------------------------------------- import
def load_kitti_raw(drive_dir, config: dict | None = None) -> tuple[SurveyRun, list[Path]]:
    """Read a KITTI raw drive into a :class:`SurveyRun` (no writing) and the source image paths.

    Returns the run (``root`` None; ``frame_files`` are the names it will have) and the image files
    in frame order. See the module docstring for what becomes what.
    """
    conf = merge_settings(default_config, config, "kitti_raw import")
    drive = Path(drive_dir)
    if not drive.is_dir():
        raise DataError(drive, "KITTI raw drive folder not found")
    c = int(conf["camera"])
    if c not in (0, 1, 2, 3):
        raise ValueError(f"KITTI raw has cameras 0-3, not {c}")
    camera, T_vc = camera_from_calib(_calib_folder(drive), c)

    img_dir = drive / f"image_0{c}"
    images = _indexed_files(img_dir / "data", (".png", ".jpg", ".jpeg"))
    cam_ts_path = img_dir / "timestamps.txt"
    cam_ts = read_timestamps(cam_ts_path)
    last = max(images)
    if last >= len(cam_ts):
        raise DataError(cam_ts_path, f"{len(cam_ts)} timestamps but image_0{c}/data has frame index {last} "
                                     f"({images[last].name}): frame counts do not match", len(cam_ts))

    oxts_files = _indexed_files(drive / "oxts" / "data", (".txt",))
    oxts_ts_path = drive / "oxts" / "timestamps.txt"
    oxts_ts = read_timestamps(oxts_ts_path)
    if max(oxts_files) >= len(oxts_ts):
        k = max(oxts_files)
        raise DataError(oxts_ts_path, f"{len(oxts_ts)} timestamps but oxts/data has frame index {k} "
                                      f"({oxts_files[k].name}): frame counts do not match", len(oxts_ts))
    # the synchronised layout has one OXTS packet per camera frame, same index
    if set(images) != set(oxts_files):
        only_img = sorted(set(images) - set(oxts_files))
        only_oxts = sorted(set(oxts_files) - set(images))
        what = (f"no OXTS packet for frame {only_img[0]} ({images[only_img[0]].name})" if only_img
                else f"no image for OXTS packet {only_oxts[0]} ({oxts_files[only_oxts[0]].name})")
        raise DataError(drive / "oxts" / "data", f"{len(oxts_files)} OXTS packets but {len(images)} images in "
                                                 f"image_0{c}/data: frame counts do not match; {what}")

    idx = np.array(list(images))
    frame_times = cam_ts[idx]
    oidx = np.array(list(oxts_files))
    oxts = read_oxts(list(oxts_files.values()))
    otimes = oxts_ts[oidx]
    T_wv, frame = oxts_poses(oxts)
    odo = planar_dead_reckoning(otimes, oxts[:, _F["vf"]], oxts[:, _F["vl"]], oxts[:, _F["wu"]])
    odo = odometry_with_noise(odo, float(conf["odometry_noise"]), int(conf["odometry_seed"]))
    gps = np.column_stack([otimes, T_wv[:, :3, 3]])

    ext = {p.suffix.lower() for p in images.values()}
    files = [f"images/{i:010d}{images[i].suffix.lower()}" for i in idx]
    gaps = find_gaps(frame_times, conf["gap_factor"])
    missing_idx = sorted(set(range(int(idx[0]), int(idx[-1]) + 1)) - set(images))
    name = conf["name"] or f"{drive.name}_cam{c}"
    noise = float(conf["odometry_noise"])
    metadata = {
        "source": "kitti_raw", "source_path": str(drive.resolve()), "kitti_camera": c,
        "world_frame": frame,
        **odometry_note("OXTS forward/leftward velocity and yaw rate integrated in the plane; NOT independent "
                        "of the INS", conf),
        # what the OXTS unit itself claims for the ground truth (KITTI's gps_mode_to_string: 4 differential,
        # 5 RTK float, 6 RTK integer): errors against it below this are not measurable
        "oxts_pos_accuracy_m": {"median": float(np.median(oxts[:, _F["pos_accuracy"]])),
                                "max": float(oxts[:, _F["pos_accuracy"]].max())},
        "oxts_posmode": sorted({int(v) for v in oxts[:, _F["posmode"]]}),
        "dropped_frames": len(missing_idx), "gaps": gaps,
        "trailing_timestamps_without_images": int(len(cam_ts) - 1 - last),
        "image_formats": sorted(e.lstrip(".") for e in ext),
    }
    run = SurveyRun(
        name=name, conditions=list(conf["conditions"]), camera=camera, T_vehicle_camera=T_vc,
        rates={"camera_hz": nominal_rate(frame_times), "odometry_hz": nominal_rate(otimes),
               "ins_hz": nominal_rate(otimes)},
        frame_times=frame_times, frame_files=files, odometry_times=otimes, odometry_poses=odo,
        odometry_source="oxts_velocities" if not noise else "oxts_velocities+noise",
        groundtruth_times=otimes, groundtruth_poses=T_wv, gps=gps, metadata=metadata,
    )
    return run, list(images.values())


def import_kitti_raw(drive_dir, out, config: dict | None = None, overwrite: bool = False, progress: bool = True,
                     photometric: str | dict | None = None) -> Path:
    """Import a KITTI raw drive as the survey run ``out``, written atomically
    (:func:`.common.write_imported`)."""
    run, sources = load_kitti_raw(drive_dir, config)
    return write_imported(run, sources, out, overwrite, progress, photometric)
