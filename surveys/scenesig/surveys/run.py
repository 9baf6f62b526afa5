"""The survey-run folder format: reading (with validation) and atomic writing.

A survey run is a folder::

    run.toml          name, condition tags, camera intrinsics (+ distortion), camera-to-vehicle
                      extrinsic, nominal rates, odometry source, free-form [metadata]
    frames.csv        timestamp,file            (file relative to the run folder, e.g. images/000001.jpg)
    images/           the camera images (JPEG or PNG)
    odometry.csv      timestamp,x,y,z,qx,qy,qz,qw
    groundtruth.tum   INS/GPS poses T_world_vehicle, TUM format (optional for live runs)
    truth.tum         exact poses (simulator only; evaluation never feeds it to the localiser)
    gps.csv           timestamp,x,y,z in the local metric world frame (optional)

``odometry.csv`` holds *poses of the vehicle in the odometry source's own frame* ``T_odom_vehicle``,
as a VO or wheel-odometry driver publishes them: that frame drifts, so only increments are
meaningful.  The increment between samples k-1 and k is ``inv(P[k-1]) @ P[k]`` (see
:meth:`SurveyRun.odometry_increments`).  Storing poses rather than increments keeps the file
loss-free under resampling and lets any rate be used.

Every problem found on reading raises :class:`scenesig.surveys.errors.DataError` naming the file and line.
"""
from __future__ import annotations

import csv
import io
import math
import shutil
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import CorruptImageError, DataError
from .geometry import Camera, interpolate_poses, pose_to_xyzquat, xyzquat_to_pose
from .images import read_image
from .io import atomic_folder
from .tum import read_tum, write_tum

__all__ = ["SurveyRun", "read_run", "write_run", "FORMAT_VERSION", "dump_toml", "read_meta", "read_frames",
           "read_odometry", "read_gps"]

FORMAT_VERSION = 1
_IMAGE_MAGIC = {b"\xff\xd8\xff": "jpeg", b"\x89PNG": "png"}


@dataclass
class SurveyRun:
    """One traverse of the route: images, odometry, INS/GPS and (simulated) truth.

    See the module docstring for the on-disk layout and frame conventions.
    """

    name: str
    conditions: list[str]
    camera: Camera
    T_vehicle_camera: np.ndarray
    rates: dict
    frame_times: np.ndarray
    frame_files: list[str]
    odometry_times: np.ndarray
    odometry_poses: np.ndarray
    odometry_source: str = "vo"
    groundtruth_times: np.ndarray | None = None
    groundtruth_poses: np.ndarray | None = None
    truth_times: np.ndarray | None = None
    truth_poses: np.ndarray | None = None
    gps: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)
    root: Path | None = None

    def __len__(self) -> int:
        return len(self.frame_times)

    def image_path(self, i: int) -> Path:
        if self.root is None:
            raise ValueError(f"run {self.name!r} has no folder: images are not on disk")
        return self.root / self.frame_files[i]

    def image(self, i: int, gray: bool = False) -> np.ndarray:
        """Load frame ``i`` (BGR uint8, or gray) from disk, decoded strictly (:mod:`scenesig.surveys.images`).

        Raises :class:`scenesig.surveys.errors.CorruptImageError` (a :class:`DataError`) naming the file if it
        is missing, truncated, corrupt or not the size ``run.toml`` states; nothing is cached.
        """
        path = self.image_path(i)
        img = read_image(path, gray)        # strict: a truncated or corrupt frame raises
        h, w = img.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise CorruptImageError(path, f"image is {w}x{h} but run.toml says "
                                          f"{self.camera.width}x{self.camera.height}")
        return img

    def without_frames(self, drop) -> "SurveyRun":
        """The same run with the frames ``drop`` (indices) left out (e.g. corrupt images)."""
        import dataclasses

        keep = np.setdiff1d(np.arange(len(self)), np.asarray(list(drop), dtype=int))
        return dataclasses.replace(self, frame_times=self.frame_times[keep],
                                   frame_files=[self.frame_files[i] for i in keep])

    def pose_at(self, t, which: str = "groundtruth") -> np.ndarray:
        """Interpolated pose(s) at time(s) ``t`` from 'groundtruth' (INS), 'truth' or 'odometry'."""
        times = getattr(self, f"{which}_times")
        poses = getattr(self, f"{which}_poses")
        if times is None:
            raise ValueError(f"run {self.name!r} has no {which} poses")
        return interpolate_poses(times, poses, t)

    def odometry_increments(self) -> np.ndarray:
        """(M-1,4,4) increments ``T_{k-1,k} = inv(P[k-1]) @ P[k]`` of the odometry source."""
        from .geometry import invert

        P = self.odometry_poses
        return invert(P[:-1]) @ P[1:]


# --------------------------------------------------------------------------------------- TOML
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"TOML cannot hold {v}")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(data: dict, _prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts of scalars/lists (the stdlib only reads TOML)."""
    lines, tables = [], []
    for k, v in data.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif v is not None:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{_prefix}{k}"
        out += f"\n[{name}]\n" + dump_toml(v, name + ".")
    return out


# --------------------------------------------------------------------------------------- reading
def _read_csv(path: Path, header: list[str]) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise DataError(path, "file not found")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            try:
                first = next(reader)
            except StopIteration:
                raise DataError(path, "empty file", 1) from None
            if [h.strip() for h in first] != header:
                raise DataError(path, f"header must be {','.join(header)!r}, found {','.join(first)!r}", 1)
            rows = []
            for row in reader:
                n = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != len(header):
                    raise DataError(path, f"expected {len(header)} columns, found {len(row)}", n)
                rows.append((n, [c.strip() for c in row]))
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except csv.Error as exc:  # e.g. a NUL byte, an unterminated quote
        raise DataError(path, f"not valid CSV ({exc})", getattr(reader, "line_num", None) or None) from None
    if not rows:
        raise DataError(path, "no data rows")
    return rows


def _numeric_rows(path: Path, rows, cols: slice | None = None) -> np.ndarray:
    out = []
    for n, row in rows:
        vals = row if cols is None else row[cols]
        try:
            f = [float(v) for v in vals]
        except ValueError:
            raise DataError(path, f"non-numeric value in {','.join(row)!r}", n) from None
        if not all(math.isfinite(x) for x in f):
            raise DataError(path, "NaN or infinite value", n)
        out.append(f)
    return np.asarray(out, dtype=float)


def _check_increasing(path: Path, times: np.ndarray, lines: list[int]) -> None:
    bad = np.nonzero(np.diff(times) <= 0)[0]
    if len(bad):
        k = bad[0] + 1
        raise DataError(path, f"timestamps must strictly increase: {float(times[k])!r} after {float(times[k - 1])!r}", lines[k])


def _require(path: Path, table: dict, key: str, kind):
    if key not in table:
        raise DataError(path, f"missing key {key!r}")
    v = table[key]
    if kind is float and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, kind) or (kind is int and isinstance(v, bool)):
        raise DataError(path, f"key {key!r} must be {kind.__name__}, found {type(v).__name__}")
    if kind is float and not math.isfinite(v):
        raise DataError(path, f"key {key!r} is not finite")
    return v


def _image_ok(path: Path) -> str | None:
    """Cheap check (exists, known magic bytes); strict decoding happens when a frame is used."""
    try:
        with path.open("rb") as fh:
            head = fh.read(8)
    except OSError:
        return "image file missing"
    for magic, _ in _IMAGE_MAGIC.items():
        if head.startswith(magic):
            return None
    return "not a JPEG or PNG image"


def read_meta(path) -> dict:
    """Read and validate ``run.toml``.

    Returns
    -------
    dict with ``name``, ``conditions``, ``camera`` (:class:`Camera`), ``T_vehicle_camera`` (4x4),
    ``rates`` (dict of positive floats), ``odometry_source`` and ``metadata``.
    """
    meta_path = Path(path)
    if not meta_path.is_file():
        raise DataError(meta_path, "file not found (every survey run needs run.toml)")
    try:
        meta = tomllib.loads(meta_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:   # TOMLDecodeError is a ValueError
        raise DataError(meta_path, f"not valid TOML: {exc}") from None
    version = meta.get("format_version")
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise DataError(meta_path, f"format_version {version!r} not supported (this scenesig reads {FORMAT_VERSION})")
    name = _require(meta_path, meta, "name", str)
    conditions = meta.get("conditions", [])
    if not isinstance(conditions, list) or not all(isinstance(c, str) for c in conditions):
        raise DataError(meta_path, "'conditions' must be a list of strings")
    cam_t = _require(meta_path, meta, "camera", dict)
    for key in ("fx", "fy", "cx", "cy"):
        v = _require(meta_path, cam_t, key, float)
        if key in ("fx", "fy") and v <= 0:
            raise DataError(meta_path, f"camera.{key} must be positive")
    for key in ("width", "height"):
        if _require(meta_path, cam_t, key, int) <= 0:
            raise DataError(meta_path, f"camera.{key} must be positive")
    dist = cam_t.get("distortion", [])
    if not isinstance(dist, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                             and math.isfinite(v) for v in dist):
        raise DataError(meta_path, "camera.distortion must be a list of finite numbers")
    camera = Camera.from_dict(cam_t)
    ext = _require(meta_path, meta, "extrinsic", dict)
    try:
        T_vc = np.asarray(ext["T_vehicle_camera"], dtype=float) if "T_vehicle_camera" in ext else None
    except (TypeError, ValueError):
        T_vc = None
    if T_vc is None or T_vc.shape != (4, 4) or not np.all(np.isfinite(T_vc)):
        raise DataError(meta_path, "extrinsic.T_vehicle_camera must be a finite 4x4 matrix")
    R = T_vc[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not np.allclose(T_vc[3], [0, 0, 0, 1]):
        raise DataError(meta_path, "extrinsic.T_vehicle_camera is not a rigid transform")
    rates = meta.get("rates", {})
    if not isinstance(rates, dict):
        raise DataError(meta_path, "[rates] must be a table")
    for k, v in rates.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not (0 < v < math.inf):
            raise DataError(meta_path, f"rates.{k} must be a positive number")
    metadata = meta.get("metadata", {})
    if not isinstance(metadata, dict):
        raise DataError(meta_path, "[metadata] must be a table")
    return {"name": name, "conditions": list(conditions), "camera": camera, "T_vehicle_camera": T_vc,
            "rates": {k: float(v) for k, v in rates.items()},
            "odometry_source": str(meta.get("odometry_source", "vo")), "metadata": dict(metadata)}


def read_frames(path) -> tuple[np.ndarray, list[str], list[int]]:
    """Read ``frames.csv``: (times, image files relative to the run folder, line number of each)."""
    fpath = Path(path)
    rows = _read_csv(fpath, ["timestamp", "file"])
    ftimes = _numeric_rows(fpath, rows, slice(0, 1))[:, 0]
    lines = [n for n, _ in rows]
    _check_increasing(fpath, ftimes, lines)
    files = [r[1] for _, r in rows]
    for n, f in zip(lines, files):
        if not f or Path(f).is_absolute() or ".." in Path(f).parts:
            raise DataError(fpath, f"image file {f!r} must be a path inside the run folder", n)
    return ftimes, files, lines


def read_odometry(path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``odometry.csv``: (times (M,), poses T_odom_vehicle (M,4,4))."""
    opath = Path(path)
    orows = _read_csv(opath, ["timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"])
    odo = _numeric_rows(opath, orows)
    _check_increasing(opath, odo[:, 0], [n for n, _ in orows])
    qn = np.linalg.norm(odo[:, 4:], axis=1)
    bad = np.nonzero(~((qn > 1e-9) & np.isfinite(qn)))[0]
    if len(bad):
        raise DataError(opath, "zero or non-normalisable quaternion", orows[bad[0]][0])
    return odo[:, 0], xyzquat_to_pose(odo[:, 1:]).reshape(-1, 4, 4)


def read_gps(path) -> np.ndarray:
    """Read ``gps.csv``: (K, 4) rows ``timestamp, x, y, z``."""
    gpath = Path(path)
    grows = _read_csv(gpath, ["timestamp", "x", "y", "z"])
    gps = _numeric_rows(gpath, grows)
    _check_increasing(gpath, gps[:, 0], [n for n, _ in grows])
    return gps


#: Optional files of a run that :func:`read_run` can be told not to open (``skip``).
OPTIONAL_FILES = {"groundtruth": "groundtruth.tum", "truth": "truth.tum", "gps": "gps.csv"}


def read_run(folder, check_images: bool = True, skip=()) -> SurveyRun:
    """Read and validate a survey-run folder.

    Parameters
    ----------
    folder : path of the run folder.
    check_images : check that every image file exists and is a JPEG/PNG (headers only) and that the
        first one decodes strictly at the size ``run.toml`` states. Images themselves load lazily
        (and strictly: :meth:`SurveyRun.image`); ``scenesig check`` decodes every one.
    skip : optional files not to open even where present (keys of :data:`OPTIONAL_FILES`), e.g. a
        localiser running without GPS opens neither ``groundtruth.tum`` nor ``gps.csv``.

    Raises
    ------
    DataError
        naming the file (and line) of the first problem found.
    """
    root = Path(folder)
    if not root.is_dir():
        raise DataError(root, "survey run folder not found")
    meta = read_meta(root / "run.toml")
    fpath = root / "frames.csv"
    ftimes, files, lines = read_frames(fpath)
    if check_images:
        for n, f in zip(lines, files):
            problem = _image_ok(root / f)
            if problem:
                raise DataError(fpath, f"{problem}: {root / f}", n)
    odo_t, odo_p = read_odometry(root / "odometry.csv")

    unknown = set(skip) - set(OPTIONAL_FILES)
    if unknown:
        raise ValueError(f"unknown optional file(s) {sorted(unknown)}; known: {sorted(OPTIONAL_FILES)}")
    gt_t = gt_p = tr_t = tr_p = gps = None
    if "groundtruth" not in skip and (root / "groundtruth.tum").exists():
        gt_t, gt_p = read_tum(root / "groundtruth.tum")
    if "truth" not in skip and (root / "truth.tum").exists():
        tr_t, tr_p = read_tum(root / "truth.tum")
    if "gps" not in skip and (root / "gps.csv").exists():
        gps = read_gps(root / "gps.csv")

    run = SurveyRun(
        name=meta["name"], conditions=meta["conditions"], camera=meta["camera"],
        T_vehicle_camera=meta["T_vehicle_camera"], rates=meta["rates"], frame_times=ftimes, frame_files=files,
        odometry_times=odo_t, odometry_poses=odo_p, odometry_source=meta["odometry_source"],
        groundtruth_times=gt_t, groundtruth_poses=gt_p, truth_times=tr_t, truth_poses=tr_p, gps=gps,
        metadata=meta["metadata"], root=root,
    )
    if check_images:
        run.image(0, gray=True)  # decodes, and checks the size against run.toml
    return run


# --------------------------------------------------------------------------------------- writing
def _csv_text(header: list[str], rows) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def write_run(run: SurveyRun, folder, images=None, overwrite: bool = False, jpeg_quality: int = 95) -> Path:
    """Write ``run`` to ``folder`` atomically.

    Everything goes to ``folder.tmp`` first and is renamed into place only when complete, so an
    interrupted write never leaves a half-written run that looks valid.

    Parameters
    ----------
    images : iterable of uint8 images in frame order, written to ``run.frame_files`` (names default to
        ``images/NNNNNN.jpg``); an item that is ``bytes`` is an encoded file written as it is (importers
        keep the source's JPEG/PNG bytes rather than re-encode). If None, the images are copied from
        ``run.root``.
    overwrite : replace an existing run folder (refused by default: nothing written is lost silently).
    """
    import cv2

    folder = Path(folder)
    if images is None and run.root is None:
        raise ValueError("no images given and the run has no source folder to copy them from")
    with atomic_folder(folder, overwrite, "survey run") as tmp:
        (tmp / "images").mkdir()
        files = list(run.frame_files) if run.frame_files else [f"images/{i:06d}.jpg" for i in range(len(run.frame_times))]
        if len(files) != len(run.frame_times):
            raise ValueError(f"{len(files)} frame files for {len(run.frame_times)} frame times")
        if images is None:
            for f in files:
                (tmp / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(run.root / f, tmp / f)
        else:
            n = 0
            for f, img in zip(files, images):
                (tmp / f).parent.mkdir(parents=True, exist_ok=True)
                if isinstance(img, (bytes, bytearray, memoryview)):  # already encoded: kept bit for bit
                    (tmp / f).write_bytes(img)
                    n += 1
                    continue
                params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if f.lower().endswith((".jpg", ".jpeg")) else []
                if not cv2.imwrite(str(tmp / f), img, params):
                    raise OSError(f"{tmp / f}: could not write image")
                n += 1
            if n != len(files):
                raise ValueError(f"got {n} images for {len(files)} frames")
        meta = {
            "format_version": FORMAT_VERSION, "name": run.name, "conditions": list(run.conditions),
            "odometry_source": run.odometry_source, "camera": run.camera.to_dict(),
            "extrinsic": {"T_vehicle_camera": np.asarray(run.T_vehicle_camera, float).tolist()},
            "rates": dict(run.rates), "metadata": dict(run.metadata),
        }
        (tmp / "run.toml").write_text(dump_toml(meta))
        (tmp / "frames.csv").write_text(_csv_text(["timestamp", "file"],
                                                  [[f"{t:.9f}", f] for t, f in zip(run.frame_times, files)]))
        odo = pose_to_xyzquat(run.odometry_poses).reshape(-1, 7)
        (tmp / "odometry.csv").write_text(_csv_text(
            ["timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"],
            [[f"{t:.9f}"] + [repr(float(v)) for v in r] for t, r in zip(run.odometry_times, odo)]))
        if run.groundtruth_times is not None:
            write_tum(tmp / "groundtruth.tum", run.groundtruth_times, run.groundtruth_poses)
        if run.truth_times is not None:
            write_tum(tmp / "truth.tum", run.truth_times, run.truth_poses)
        if run.gps is not None:
            (tmp / "gps.csv").write_text(_csv_text(["timestamp", "x", "y", "z"],
                                                   [[f"{r[0]:.9f}"] + [repr(float(v)) for v in r[1:4]] for r in run.gps]))
    return folder
