"""An ordered folder of images (a real traverse with no odometry and no truth) as a survey run.

``scenesig import images FOLDER --hz H [--positions CSV] [--aligned-with RUN] --out RUN``

What a folder of frames from a dash camera, a phone or a place-recognition data set (Nordland, the
GRIEF season sequence) holds is the images and their order, nothing else.  The run written here says
so rather than inventing what is missing:

* **frames**: the folder's image files (``.jpg``, ``.jpeg``, ``.png``; ``.ppm``, ``.pgm``, ``.bmp``,
  ``.tif``, ``.tiff`` are decoded and stored as PNG, losslessly) in *natural* order of their names
  (``img2`` before ``img10``), at ``t_i = i / hz``.  Other files (a ``displacements.txt`` beside the
  frames) are ignored and counted.  Every image is decoded strictly once
  (:func:`scenesig.surveys.images.decode_image`): a truncated or corrupt one stops the import with a
  :class:`~scenesig.surveys.errors.DataError` naming the file, and so does one of another size than the
  first.
* **odometry**: none.  ``odometry_source = "none"`` and ``odometry.csv`` holds the identity at every
  frame time (the run format needs the file); nothing that needs motion may use it as motion.  Such a
  run is localised by place recognition with sequence constraints (``scenesig bench sequence``,
  :mod:`scenesig.benchmarks.sequence`), which reports the matched reference frame per query frame.
* **camera**: ``intrinsics`` when given, else a pinhole of ``hfov_deg`` horizontal field of view
  centred on the image (recorded as assumed in the metadata); the camera looks along the vehicle's x
  axis (:data:`scenesig.surveys.geometry.CAMERA_FROM_VEHICLE_AXES`).
* **positions** (optional CSV, header ``frame,x,y[,z]`` with 0-based frame indices, or ``file,x,y[,z]``
  with file names in the folder; metres in a local frame): ``gps.csv`` at those frames' times, and --
  when every frame has one -- ``groundtruth.tum`` with the heading along the path (roll and pitch 0;
  recorded in the metadata).
* **aligned with** another imported run (``aligned_with``): frame i of both shows the same place, the
  evaluation truth of a traverse pair without positions (Nordland's and GRIEF season's convention).
  The two must have the same number of frames; the run's folder is recorded (``metadata.aligned_with``).
"""
from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import CAMERA_FROM_VEHICLE_AXES, Camera, make_pose
from ..images import decode_image, image_kind
from ..run import SurveyRun, read_run, write_run
from ..settings import merge_settings

__all__ = ["default_config", "IMAGE_SUFFIXES", "natural_key", "list_images", "read_positions",
           "load_image_folder", "import_image_folder", "aligned_group"]

#: Suffixes taken as frames (case-insensitive); JPEG and PNG are kept bit for bit, the rest become PNG.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")

default_config = {
    "hz": None,               # frame rate (required): t_i = i / hz
    "name": None,             # default: the folder's name
    "conditions": [],
    "intrinsics": None,       # a Camera, or [fx, fy, cx, cy(, distortion...)]; None: from hfov_deg
    "hfov_deg": 60.0,         # assumed horizontal field of view when no intrinsics are given
    "positions": None,        # CSV of per-frame positions (module docstring)
    "aligned_with": None,     # an imported run whose frame i is this run's frame i
    "start_time": 0.0,        # time of the first frame (s)
}

_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple:
    """Sort key putting ``img2`` before ``img10``: digit runs compare as numbers, the rest as text."""
    parts = _DIGITS.split(name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts if p != "") + (name,)


def list_images(folder) -> tuple[list[Path], int]:
    """The image files directly in ``folder`` in natural order, and the number of other files ignored."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "image folder not found")
    images, ignored = [], 0
    for p in folder.iterdir():
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
            images.append(p)
        elif p.is_file():
            ignored += 1
    if not images:
        raise DataError(folder, f"no image files ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    images.sort(key=lambda p: natural_key(p.name))
    return images, ignored


def read_positions(path, files: list[Path]) -> dict[int, np.ndarray]:
    """``{frame index: (x, y, z)}`` from a positions CSV (module docstring); DataError naming the line."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "positions file not found")
    by_name = {f.name: i for i, f in enumerate(files)}
    out: dict[int, np.ndarray] = {}
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            if not header:
                raise DataError(path, "empty file")
            key = "frame" if "frame" in header else "file" if "file" in header else None
            if key is None or "x" not in header or "y" not in header:
                raise DataError(path, f"header must be frame,x,y[,z] or file,x,y[,z]; found {','.join(header)!r}", 1)
            col = {h: header.index(h) for h in header}
            for row in reader:
                n = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != len(header):
                    raise DataError(path, f"expected {len(header)} columns, found {len(row)}", n)
                k = row[col[key]].strip()
                if key == "frame":
                    if not k.isdigit() or int(k) >= len(files):
                        raise DataError(path, f"frame {k!r} is not an index 0..{len(files) - 1} of the folder's "
                                              "images", n)
                    i = int(k)
                else:
                    if k not in by_name:
                        raise DataError(path, f"file {k!r} is not an image of the folder", n)
                    i = by_name[k]
                try:
                    xyz = [float(row[col[c]]) for c in ("x", "y")] + [float(row[col["z"]]) if "z" in col else 0.0]
                except ValueError:
                    raise DataError(path, f"non-numeric position in {','.join(row)!r}", n) from None
                if not np.all(np.isfinite(xyz)):
                    raise DataError(path, "NaN or infinite position", n)
                if i in out:
                    raise DataError(path, f"frame {i} ({files[i].name}) has a second position", n)
                out[i] = np.asarray(xyz)
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text ({exc.reason})") from None
    except csv.Error as exc:
        raise DataError(path, f"not valid CSV ({exc})") from None
    if not out:
        raise DataError(path, "no positions")
    return out


def _camera(conf: dict, width: int, height: int) -> tuple[Camera, str]:
    intr = conf["intrinsics"]
    if isinstance(intr, Camera):
        if intr.size != (width, height):
            raise ValueError(f"intrinsics are for {intr.size[0]}x{intr.size[1]} but the images are {width}x{height}")
        return intr, "given"
    if intr is not None:
        v = [float(x) for x in intr]
        if len(v) not in (4, 8, 9) or v[0] <= 0 or v[1] <= 0:
            raise ValueError(f"intrinsics must be fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] with fx, fy > 0, got {intr!r}")
        return Camera(v[0], v[1], v[2], v[3], width, height, tuple(v[4:])), "given"
    hfov = float(conf["hfov_deg"])
    if not 0.0 < hfov < 180.0:
        raise ValueError(f"hfov_deg must be in (0, 180), got {hfov}")
    f = 0.5 * width / np.tan(np.radians(hfov) / 2.0)
    return Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height), f"assumed: {hfov:g} deg horizontal"


def _path_poses(xyz: np.ndarray) -> np.ndarray:
    """Poses T_world_vehicle at the given positions, heading along the path (central differences)."""
    d = np.gradient(xyz[:, :2], axis=0) if len(xyz) > 1 else np.array([[1.0, 0.0]])
    still = np.linalg.norm(d, axis=1) < 1e-9
    yaw = np.arctan2(d[:, 1], d[:, 0])
    if still.all():
        yaw[:] = 0.0
    elif still.any():   # a stop: keep the heading it had (or will have) when moving
        idx = np.flatnonzero(~still)
        yaw[still] = yaw[idx[np.clip(np.searchsorted(idx, np.flatnonzero(still)), 0, len(idx) - 1)]]
    out = np.tile(np.eye(4), (len(xyz), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, :3, 3] = xyz
    return out


def aligned_group(run: SurveyRun) -> set[str]:
    """Resolved folders the run is frame-aligned with: itself and its ``metadata.aligned_with``."""
    group = set()
    if run.root is not None:
        group.add(str(Path(run.root).resolve()))
    other = run.metadata.get("aligned_with")
    if other:
        group.add(str(Path(other).resolve()))
    return group


def _decoded(files: list[Path]):
    """(stored name, bytes or array, decoded image) of every file, decoded strictly once."""
    for f in files:
        try:
            data = f.read_bytes()
        except OSError as exc:
            raise DataError(f, f"cannot read image ({exc.strerror})") from None
        if not data:
            raise DataError(f, "empty image file")
        img = decode_image(data, f)           # CorruptImageError (a DataError) naming the file
        if image_kind(data) in ("jpeg", "png"):
            yield f.name, data, img
        else:
            yield f.stem + ".png", img, img    # lossless re-encoding of PPM/BMP/TIFF


def load_image_folder(folder, config: dict | None = None):
    """The survey run of an image folder (nothing written) and an iterator of its images to write."""
    conf = merge_settings(default_config, config, "image-folder import")
    hz = conf["hz"]
    if hz is None or not np.isfinite(float(hz)) or float(hz) <= 0:
        raise ValueError(f"hz (the frame rate) must be a positive number, got {hz!r}")
    hz = float(hz)
    folder = Path(folder)
    files, ignored = list_images(folder)
    stored = [f.name if f.suffix.lower() in (".jpg", ".jpeg", ".png") else f.stem + ".png" for f in files]
    seen: dict[str, Path] = {}
    for f, s in zip(files, stored):
        if s in seen:
            raise DataError(f, f"would be stored as images/{s}, as {seen[s].name} is")
        seen[s] = f
    _, _, first = next(_decoded(files[:1]))
    height, width = first.shape[:2]
    camera, cam_note = _camera(conf, width, height)
    times = float(conf["start_time"]) + np.arange(len(files)) / hz
    metadata = {"source": "image_folder", "source_path": str(folder.resolve()), "ignored_files": ignored,
                "odometry": "none: an image folder has no odometry (odometry.csv holds the identity)",
                "camera": cam_note}
    gt_t = gt_p = gps = None
    if conf["positions"] is not None:
        pos = read_positions(conf["positions"], files)
        idx = np.array(sorted(pos))
        xyz = np.stack([pos[i] for i in idx])
        gps = np.column_stack([times[idx], xyz])
        metadata["positions"] = str(Path(conf["positions"]).resolve())
        if len(idx) == len(files):
            gt_t, gt_p = times.copy(), _path_poses(xyz)
            metadata["groundtruth"] = "the positions file; heading along the path, roll and pitch 0"
    if conf["aligned_with"] is not None:
        other = read_run(conf["aligned_with"], check_images=False)
        if len(other) != len(files):
            raise DataError(Path(conf["aligned_with"]) / "frames.csv",
                            f"has {len(other)} frames but {folder} has {len(files)}: frame-aligned traverses need "
                            "the same number")
        metadata["aligned_with"] = str(Path(conf["aligned_with"]).resolve())
        metadata["aligned_with_name"] = other.name
    run = SurveyRun(
        name=conf["name"] or folder.name, conditions=list(conf["conditions"]), camera=camera,
        T_vehicle_camera=make_pose(CAMERA_FROM_VEHICLE_AXES), rates={"camera_hz": hz, "odometry_hz": hz},
        frame_times=times, frame_files=[f"images/{s}" for s in stored], odometry_times=times.copy(),
        odometry_poses=np.tile(np.eye(4), (len(files), 1, 1)), odometry_source="none",
        groundtruth_times=gt_t, groundtruth_poses=gt_p, gps=gps, metadata=metadata,
    )
    return run, files


def import_image_folder(folder, out, config: dict | None = None, overwrite: bool = False,
                        progress: bool = True) -> Path:
    """Import the image folder ``folder`` as the survey run ``out``, written atomically.

    Raises
    ------
    DataError
        naming the file: the folder missing or without images, a corrupt or truncated image, an image
        of another size than the first, a bad positions file, an ``aligned_with`` run of another length.
    """
    from tqdm import tqdm

    run, files = load_image_folder(folder, config)
    width, height = run.camera.size

    def images():
        it = _decoded(files)
        for f, (_, data, img) in zip(files, tqdm(it, total=len(files), desc=f"import {run.name}", unit="frame",
                                                 disable=not progress)):
            h, w = img.shape[:2]
            if (w, h) != (width, height):
                raise DataError(f, f"image is {w}x{h} but the folder's first image ({files[0].name}) is "
                                   f"{width}x{height}")
            yield data

    return write_run(run, out, images=images(), overwrite=overwrite)
