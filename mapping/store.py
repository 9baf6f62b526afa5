"""The map store: one folder per map, one file per place, a manifest written last.

Layout of ``maps/NAME/``::

    manifest.json            format version, camera, T_vehicle_camera, build parameters, software version,
                             places (pose T_world_place, neighbours, file, sha256, size) -- written last
    places/place_0007.npz    one place: the signature bank's arrays (opaque), landmarks (N,3) in the place
                             frame, covariances (N,3,3), classifier ids (N,), a small keyframe (JPEG bytes),
                             per-place metadata and, optionally, the point-feature map (``points/``: ORB/SIFT
                             keypoints, descriptors and 3D points of the reference keyframe)
    journal.jsonl            only while a build runs: header + one line per place written (for resume)

Guarantees:

* every file is written atomically (temp file in the same folder, fsync, ``os.replace``, fsync folder);
* place files are byte-deterministic (a zip written entry by entry in sorted key order with a fixed
  timestamp; ``np.savez`` would stamp the current time), so a local build, a distributed build and an
  interrupted-then-resumed build give the same bytes;
* re-opening a :class:`MapWriter` on an interrupted build keeps every place whose file matches its journal
  checksum, so ``has_place`` lets the builder skip it;
* :class:`MapStore` checks the format version and every file's sha256, and raises
  :class:`surveys.errors.DataError` naming the file; places load lazily through a small LRU cache.

Float arrays are stored in the smallest float type whose rounding error stays below a tolerance, measured
per array (and, for the bank, optionally on the detection scores themselves), and restored to their
original dtype on load; large float16 arrays (the classifier filters) keep only the mantissa bits the
tolerance needs and are written as byte planes, and zip entries are LZMA-compressed (format version 2;
version 1 files, deflated plain float16, still load).

The store only knows the bank as a ``dict[str, np.ndarray]`` (``Bank.to_arrays()`` /
``Bank.from_arrays()``), so it does not depend on how signatures are represented.

``scenesig map verify maps/NAME`` verifies a map and prints a summary (:func:`verify_summary`).
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import threading
import zipfile
from collections import OrderedDict, namedtuple
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from surveys.errors import DataError
from surveys.geometry import Camera, yaw_of

__all__ = ["verify_summary", "FORMAT_NAME", "FORMAT_VERSION", "PlaceData", "PlaceMeta", "MapWriter", "MapStore",
           "encode_keyframe", "decode_keyframe", "place_file_name", "atomic_write_bytes", "software_version"]

FORMAT_NAME = "scenesig-map"
FORMAT_VERSION = 2
#: Versions this code reads (1: float16 arrays stored as such; 2: as byte planes, fewer mantissa bits).
READABLE_VERSIONS = (1, 2)
#: float16 arrays keep at least this many of their 10 mantissa bits.
FLOAT16_MIN_MANTISSA_BITS = 4
MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"
PLACES_DIR = "places"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # the earliest date zip can store; fixed so bytes repeat
# LZMA zip entries (np.load reads them through zipfile): 4.5 % smaller places than deflate on the demo
# map (252.8 -> 241.4 kB), lossless; loading a place takes ~20 ms instead of ~5 ms, once per place.
_ZIP_COMPRESSION = zipfile.ZIP_LZMA
_BANK_PREFIX = "bank/"
_POINTS_PREFIX = "points/"

#: Relative rounding error (per row, L2) tolerated when storing landmarks and covariances.
GEOMETRY_TOL = 1e-6
CacheInfo = namedtuple("CacheInfo", "hits misses size maxsize")


def software_version() -> str:
    """The installed scenesig version (recorded in the manifest)."""
    try:
        from importlib.metadata import version
        return version("scenesig")
    except Exception:  # running from a source tree that is not installed
        return "unknown"


def place_file_name(index: int) -> str:
    """Relative path of a place's file, e.g. ``places/place_0007.npz``."""
    return f"{PLACES_DIR}/place_{int(index):04d}.npz"


# --------------------------------------------------------------------------------------------------------
# keyframes
# --------------------------------------------------------------------------------------------------------
def encode_keyframe(image: np.ndarray, width: int = 160, quality: int = 90) -> bytes:
    """A small gray JPEG of ``image`` (BGR or gray uint8) for figures, ``width`` pixels wide."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError(f"keyframe must be a uint8 gray or BGR image, got {img.dtype} {img.shape}")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    h, w = img.shape
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("could not encode the keyframe as JPEG")
    return buf.tobytes()


def decode_keyframe(data: bytes | None) -> np.ndarray | None:
    """Gray uint8 image from keyframe bytes (None stays None)."""
    if data is None or len(data) == 0:
        return None
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("keyframe bytes are not a decodable image")
    return img


# --------------------------------------------------------------------------------------------------------
# place data
# --------------------------------------------------------------------------------------------------------
@dataclass
class PlaceData:
    """Everything stored for one place.

    Parameters
    ----------
    bank_arrays : dict of str -> ndarray
        The place's signature bank (``Bank.to_arrays()``); numeric arrays only.
    landmarks : (N, 3) array
        Landmark of each kept signature in the place frame (metres).
    covariances : (N, 3, 3) array
        Their covariances.
    classifier_ids : (N,) int array
        Which classifier of the bank each landmark belongs to.
    keyframe : bytes or uint8 image, optional
        Encoded image (JPEG/PNG bytes); an image array is encoded with :func:`encode_keyframe` on write.
    meta : dict, optional
        JSON-serialisable per-place metadata (e.g. reference run, frame, rejection counts).
    points : dict of str -> ndarray, optional
        Point-feature map of the place for the ORB / SIFT baselines
        (:func:`mapping.pointmap.build_point_features`: keyframe keypoints, descriptors, 3D points).
        Stored under ``points/`` exactly in the dtypes given (the builder already picks compact,
        lossless ones); a place without point features stores nothing extra, so its bytes do not change.
    """

    bank_arrays: dict
    landmarks: np.ndarray
    covariances: np.ndarray
    classifier_ids: np.ndarray
    keyframe: bytes | np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    points: dict = field(default_factory=dict)

    def __post_init__(self):
        lm = np.asarray(self.landmarks)
        cov = np.asarray(self.covariances)
        # keep float32/float64 as given (the store records and restores the dtype); empty places are fine
        lm = lm if lm.dtype.kind == "f" else lm.astype(float)
        cov = cov if cov.dtype.kind == "f" else cov.astype(float)
        self.landmarks = lm.reshape(-1, 3) if lm.size == 0 else lm
        self.covariances = cov.reshape(-1, 3, 3) if cov.size == 0 else cov
        N = len(self.landmarks)
        if self.landmarks.shape != (N, 3):
            raise ValueError(f"landmarks must be (N, 3), got {self.landmarks.shape}")
        if self.covariances.shape != (N, 3, 3):
            raise ValueError(f"covariances must be (N, 3, 3) with N = {N}, got {self.covariances.shape}")
        ids = np.asarray(self.classifier_ids)
        if ids.shape != (N,) or (N and ids.dtype.kind not in "iu"):
            raise ValueError(f"classifier_ids must be (N,) integers with N = {N}, got {ids.dtype} {ids.shape}")
        self.classifier_ids = ids.astype(np.int64) if N else np.zeros(0, np.int64)
        if not isinstance(self.bank_arrays, dict):
            raise TypeError("bank_arrays must be a dict of str -> numpy array (Bank.to_arrays())")
        for k, v in self.bank_arrays.items():
            if not isinstance(k, str) or not k:
                raise ValueError(f"bank array names must be non-empty strings, got {k!r}")
            if np.asarray(v).dtype.kind not in "biufUS":
                raise ValueError(f"bank array {k!r} has dtype {np.asarray(v).dtype}; only numeric and string "
                                 f"arrays are stored (no pickled objects)")
        if not isinstance(self.meta, dict):
            raise TypeError("meta must be a dict")
        if self.points is None:
            self.points = {}
        if not isinstance(self.points, dict):
            raise TypeError("points must be a dict of str -> numpy array (mapping.pointmap.build_point_features)")
        for k, v in self.points.items():
            if not isinstance(k, str) or not k or "/" in k:
                raise ValueError(f"point array names must be non-empty strings without '/', got {k!r}")
            if np.asarray(v).dtype.kind not in "biuf":
                raise ValueError(f"point array {k!r} has dtype {np.asarray(v).dtype}; only numeric arrays are stored")

    @property
    def n_signatures(self) -> int:
        """Number of landmarks (kept signatures)."""
        return len(self.landmarks)

    def keyframe_image(self) -> np.ndarray | None:
        """The keyframe decoded to a uint8 image (None if there is none)."""
        if isinstance(self.keyframe, np.ndarray):
            return self.keyframe
        return decode_keyframe(self.keyframe)


def _row_rel_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest per-row relative L2 error ||b - a|| / ||a|| (rows = first axis; a 1-D array is one row)."""
    a2 = a.reshape(len(a), -1) if a.ndim >= 2 else a.reshape(1, -1)
    b2 = b.reshape(a2.shape)
    num = np.linalg.norm(b2 - a2, axis=1)
    den = np.linalg.norm(a2, axis=1)
    if np.any((den == 0) & (num > 0)):
        return np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return float(r.max()) if r.size else 0.0


def _smallest_float(a: np.ndarray, tol: float, min_itemsize: int = 2, min_size: int = 0) -> np.dtype:
    """The smallest float dtype (float16, float32, own) storing ``a`` within relative row error ``tol``.

    For a linear classifier ``score = w . h + b`` the score changes by at most ``||dw|| ||h||``, so a per-row
    relative error bound on ``w`` bounds the score change relative to the score scale ``||w|| ||h||``.
    Arrays with fewer than ``min_size`` elements are kept as they are (nothing to gain in size).
    """
    if a.dtype.kind != "f" or a.size == 0 or a.size < min_size:
        return a.dtype
    if not np.isfinite(a).all():
        return a.dtype  # NaN/inf are kept exactly in the original type
    for dt in (np.float16, np.float32):
        if np.dtype(dt).itemsize >= a.dtype.itemsize:
            break
        if np.dtype(dt).itemsize < min_itemsize:
            continue
        if np.abs(a).max() > np.finfo(dt).max:
            continue
        if _row_rel_error(a.astype(np.float64), a.astype(dt).astype(np.float64)) <= tol:
            return np.dtype(dt)
    return a.dtype


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    # (np.ascontiguousarray would turn 0-d arrays into 1-d ones)
    np.lib.format.write_array(buf, np.require(arr, requirements="C"), allow_pickle=False)
    return buf.getvalue()


def _deterministic_npz(entries: dict) -> bytes:
    """A zip of ``name.npy`` entries readable by ``np.load``, with sorted names and fixed timestamps."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for name in sorted(entries):
            info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_DATE)
            info.compress_type = _ZIP_COMPRESSION
            info.create_system = 3
            info.external_attr = 0o644 << 16
            zf.writestr(info, _npy_bytes(entries[name]), compress_type=_ZIP_COMPRESSION)
    return out.getvalue()


def _json_bytes(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode(),
                         dtype=np.uint8)


def _round_float16(a: np.ndarray, tol: float, min_bits: int = FLOAT16_MIN_MANTISSA_BITS):
    """``a`` (float16-able) rounded to the fewest float16 mantissa bits keeping the row error within ``tol``.

    Returns ``(bits, values)``: the mantissa bits kept (10 = plain float16) and the rounded float16 array.
    Rounding is to nearest (a carry into the exponent is the correct rounding); zeroed low bits cost
    almost nothing once the bytes are split into planes and compressed.
    """
    a64 = np.asarray(a, dtype=np.float64)
    h = np.asarray(a).astype(np.float16)
    u = h.view(np.uint16).astype(np.uint32)
    bits, best = 10, h
    for b in range(9, int(min_bits) - 1, -1):
        drop = 10 - b
        r = (((u + (1 << (drop - 1))) >> drop) << drop).astype(np.uint16).view(np.float16)
        if not np.isfinite(r).all() or _row_rel_error(a64, r.astype(np.float64)) > tol:
            break
        bits, best = b, r
    return bits, best


def _to_planes(h: np.ndarray) -> np.ndarray:
    """float16 array -> (2, n) uint8: low bytes, then high bytes (sign, exponent: very compressible)."""
    u = np.ascontiguousarray(h).reshape(-1).view(np.uint16)
    return np.stack([(u & 0xFF).astype(np.uint8), (u >> 8).astype(np.uint8)])


def _from_planes(planes: np.ndarray, shape) -> np.ndarray:
    p = np.asarray(planes, dtype=np.uint16).reshape(2, -1)
    return (p[0] | (p[1] << 8)).astype(np.uint16).view(np.float16).reshape(shape)


def encode_place(index: int, data: PlaceData, float16_tol: float = 4e-3,
                 score_fn: Callable[[dict], np.ndarray] | None = None, score_tol: float = 1e-3,
                 float16_min_size: int = 4096) -> bytes:
    """Serialise one place to deterministic npz bytes (see :class:`MapWriter` for the dtype rule)."""
    bank = {k: np.asarray(v) for k, v in data.bank_arrays.items()}
    stored = {k: v.astype(_smallest_float(v, float16_tol, min_size=float16_min_size), copy=False)
              for k, v in bank.items()}
    mantissa = {}
    for k, v in stored.items():
        if v.dtype == np.float16 and bank[k].dtype != np.float16:
            mantissa[k], stored[k] = _round_float16(bank[k], float16_tol)
    if score_fn is not None and any(stored[k].dtype != bank[k].dtype for k in bank):
        ref = np.asarray(score_fn(bank), dtype=float)
        low = {k: stored[k].astype(bank[k].dtype) for k in bank}
        if not np.max(np.abs(np.asarray(score_fn(low), dtype=float) - ref), initial=0.0) <= score_tol:
            # the measured scores moved too much: no float16, at most float32 (or the original type)
            mantissa = {}
            stored = {k: v.astype(_smallest_float(v, float16_tol, min_itemsize=4, min_size=float16_min_size),
                                  copy=False) for k, v in bank.items()}
            low = {k: stored[k].astype(bank[k].dtype) for k in bank}
            if not np.max(np.abs(np.asarray(score_fn(low), dtype=float) - ref), initial=0.0) <= score_tol:
                stored = bank
    # float16 arrays go to disk as byte planes (see _to_planes): the compressor then sees the repetitive
    # sign/exponent bytes apart from the mantissa bytes -- about 10 % smaller, bit-exact
    planes = {k: {"shape": list(v.shape), "mantissa_bits": int(mantissa.get(k, 10))}
              for k, v in stored.items() if v.dtype == np.float16 and v.size >= float16_min_size}
    stored = {k: (_to_planes(v) if k in planes else v) for k, v in stored.items()}
    lm = data.landmarks
    cov = data.covariances
    lm_s = lm.astype(_smallest_float(lm, GEOMETRY_TOL))
    cov_s = cov.astype(_smallest_float(cov, GEOMETRY_TOL))
    kf = data.keyframe
    if isinstance(kf, np.ndarray):
        kf = encode_keyframe(kf)
    entries = {_BANK_PREFIX + k: v for k, v in stored.items()}
    # point features are stored as given: the point-map builder chose lossless compact dtypes
    entries.update({_POINTS_PREFIX + k: np.asarray(v) for k, v in (data.points or {}).items()})
    entries.update({
        "landmarks": lm_s, "covariances": cov_s, "classifier_ids": data.classifier_ids.astype(np.int64),
        "keyframe": np.frombuffer(kf or b"", dtype=np.uint8),
        "meta": _json_bytes(data.meta),
        "format": _json_bytes({
            "format": FORMAT_NAME, "format_version": FORMAT_VERSION, "place": int(index),
            "has_keyframe": kf is not None,
            # original dtypes, restored on load
            "dtypes": {**{_BANK_PREFIX + k: str(v.dtype) for k, v in bank.items()},
                       "landmarks": str(lm.dtype), "covariances": str(cov.dtype)},
            # arrays stored as float16 byte planes: their shape (and, for the record, mantissa bits kept)
            "float16_planes": {_BANK_PREFIX + k: v for k, v in planes.items()},
        }),
    })
    return _deterministic_npz(entries)


def decode_place(raw: bytes, path: Path, index: int | None = None) -> PlaceData:
    """Parse the bytes of a place file; DataError naming ``path`` if they are not a valid place."""
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:  # BadZipFile, ValueError from a bad .npy header, zlib errors, CRC errors...
        raise DataError(path, f"not a readable place file ({type(exc).__name__}: {exc})") from None
    for key in ("format", "meta", "landmarks", "covariances", "classifier_ids", "keyframe"):
        if key not in arrays:
            raise DataError(path, f"place file has no '{key}' entry")
    try:
        fmt = json.loads(arrays.pop("format").tobytes())
        meta = json.loads(arrays.pop("meta").tobytes())
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(path, f"bad JSON in the place file's format/meta entry: {exc}") from None
    if fmt.get("format") != FORMAT_NAME or fmt.get("format_version") not in READABLE_VERSIONS:
        raise DataError(path, f"place file is {fmt.get('format')!r} version {fmt.get('format_version')!r}; "
                              f"this scenesig reads {FORMAT_NAME!r} versions {list(READABLE_VERSIONS)}")
    if index is not None and fmt.get("place") != index:
        raise DataError(path, f"place file holds place {fmt.get('place')}, expected place {index}")
    dtypes = fmt.get("dtypes", {})
    for k, enc in fmt.get("float16_planes", {}).items():
        try:
            arrays[k] = _from_planes(arrays[k], enc["shape"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(path, f"bad float16 planes for {k!r}: {exc}") from None
    restore = {k: (v.astype(dtypes[k]) if k in dtypes and str(v.dtype) != dtypes[k] else v) for k, v in arrays.items()}
    kf = restore.pop("keyframe").tobytes()
    try:
        return PlaceData(
            bank_arrays={k[len(_BANK_PREFIX):]: v for k, v in restore.items() if k.startswith(_BANK_PREFIX)},
            landmarks=restore["landmarks"], covariances=restore["covariances"],
            classifier_ids=restore["classifier_ids"], keyframe=kf if fmt.get("has_keyframe") else None, meta=meta,
            points={k[len(_POINTS_PREFIX):]: v for k, v in restore.items() if k.startswith(_POINTS_PREFIX)})
    except (ValueError, TypeError) as exc:
        raise DataError(path, f"inconsistent place data: {exc}") from None


# --------------------------------------------------------------------------------------------------------
# atomic files
# --------------------------------------------------------------------------------------------------------
def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _tmp_name(path: Path) -> Path:
    return path.parent / f".{path.name}.{os.getpid()}.tmp"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old file or the whole new one, never a part."""
    path = Path(path)
    tmp = _tmp_name(path)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _pose_list(T) -> list:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"a pose must be a finite 4x4 matrix, got shape {T.shape}")
    return [[float(x) for x in row] for row in T]


# --------------------------------------------------------------------------------------------------------
# writer
# --------------------------------------------------------------------------------------------------------
class MapWriter:
    """Writes a map folder place by place; re-opening an interrupted build resumes it.

    One writer per map folder (the build's driver process): workers compute :class:`PlaceData`, the driver
    writes it.

    Parameters
    ----------
    root : path
        The map folder (``maps/NAME``); created if missing.
    camera : Camera
    T_vehicle_camera : (4, 4) array
    params : dict
        Build parameters (JSON-serialisable); recorded in the manifest.  Resuming requires the same
        camera, extrinsic, parameters and software version.
    float16_tol : float
        Bank float arrays of at least ``float16_min_size`` elements are stored as float16 when every row's
        relative L2 rounding error is below this (rows = first axis; a 1-D array is one row; for
        ``score = w . h + b`` it bounds the score change relative to ``||w|| ||h||``), with as few
        mantissa bits (at least :data:`FLOAT16_MIN_MANTISSA_BITS`) as keep that error below it; else
        float32 when that is below it, else unchanged.  They are restored to their own dtype on load.
        The default, 4e-3, keeps 6-7 of float16's 10 mantissa bits for scene-signature filters: on the
        demo world's banks (992 detections over real frames) no detection moved and no probability
        changed by more than 0.003, and the filters take a quarter less space than plain float16.
    float16_min_size : int
        Smaller arrays (boxes, biases, scalars: a few kB at most) are stored exactly.
    score_fn : callable, optional
        ``score_fn(bank_arrays) -> scores``: if given, the downcast is also checked on the detection scores
        themselves (e.g. the bank scoring fixed HOG samples); if any score moves by more than ``score_tol``
        the bank is stored at float32 / full precision instead.
    score_tol : float
        Absolute score tolerance for ``score_fn``.
    overwrite : bool
        Discard an existing map or partial build in ``root`` with different settings instead of failing.
    """

    def __init__(self, root, camera: Camera, T_vehicle_camera, params: dict, *, float16_tol: float = 4e-3,
                 score_fn: Callable[[dict], np.ndarray] | None = None, score_tol: float = 1e-3,
                 float16_min_size: int = 4096, overwrite: bool = False):
        self.root = Path(root)
        self.camera = camera
        self.T_vehicle_camera = np.asarray(T_vehicle_camera, dtype=float)
        self.params = json.loads(_canonical(params))  # fails early on non-JSON parameters
        self.float16_tol = float(float16_tol)
        self.float16_min_size = int(float16_min_size)
        self.score_fn = score_fn
        self.score_tol = float(score_tol)
        self.header = {
            "format": FORMAT_NAME, "format_version": FORMAT_VERSION, "software": software_version(),
            "camera": camera.to_dict(), "T_vehicle_camera": _pose_list(self.T_vehicle_camera),
            "params": self.params,
            # how floats are stored changes the bytes, so a resumed build must use the same rule
            "storage": {"float16_tol": self.float16_tol, "float16_min_size": self.float16_min_size,
                        "score_tol": self.score_tol if score_fn is not None else None},
        }
        (self.root / PLACES_DIR).mkdir(parents=True, exist_ok=True)
        self._done: dict[int, dict] = {}
        self._remove_stale_temp_files()
        if overwrite:
            self._clear()
        self._resume()

    # -- resume -------------------------------------------------------------------------------------------
    def _remove_stale_temp_files(self):
        # Left by a killed writer: never renamed, so never part of the map.
        for folder in (self.root, self.root / PLACES_DIR):
            for p in folder.glob(".*.tmp"):
                p.unlink(missing_ok=True)

    def _clear(self):
        for p in (self.root / PLACES_DIR).glob("place_*.npz"):
            p.unlink()
        for name in (MANIFEST, JOURNAL):
            (self.root / name).unlink(missing_ok=True)

    def _header_mismatch(self, other: dict) -> list[str]:
        return [k for k in self.header if _canonical(self.header[k]) != _canonical(other.get(k))]

    def _verified(self, record: dict) -> bool:
        path = self.root / record["file"]
        try:
            return path.is_file() and _sha256(path.read_bytes()) == record["sha256"]
        except OSError:
            return False

    def _resume(self):
        manifest = self.root / MANIFEST
        journal = self.root / JOURNAL
        records: list[dict] = []
        if manifest.exists():
            doc = _read_json(manifest)
            bad = self._header_mismatch(doc)
            if bad:
                raise DataError(manifest, f"an existing map here differs in {bad}; use another folder or "
                                          f"overwrite=True to rebuild it")
            records = [{"index": p["index"], "file": p["file"], "sha256": p["sha256"], "bytes": p["bytes"],
                        "signatures": p.get("signatures", 0)} for p in doc.get("places", [])]
        elif journal.exists():
            header, records = _read_journal(journal)
            bad = self._header_mismatch(header)
            if bad:
                raise DataError(journal, f"an interrupted build here used a different {bad}; resume it with "
                                         f"the same settings, or use overwrite=True to start again")
        for r in records:
            if self._verified(r):
                self._done[int(r["index"])] = r
        # Start a fresh, compact journal holding only the verified places.
        lines = [_canonical({"header": self.header})] + [_canonical(r) for _, r in sorted(self._done.items())]
        atomic_write_bytes(journal, ("\n".join(lines) + "\n").encode())

    # -- writing ------------------------------------------------------------------------------------------
    def has_place(self, index: int) -> bool:
        """True if place ``index`` is already written and its file matches its checksum."""
        return int(index) in self._done

    @property
    def written(self) -> list[int]:
        """Indices of the places written so far."""
        return sorted(self._done)

    def write_place(self, index: int, data: PlaceData) -> dict:
        """Atomically write one place and journal it; returns its record (file, sha256, bytes)."""
        if not isinstance(data, PlaceData):
            raise TypeError("data must be a mapping.store.PlaceData")
        index = int(index)
        if index < 0:
            raise ValueError(f"place index must be >= 0, got {index}")
        raw = encode_place(index, data, self.float16_tol, self.score_fn, self.score_tol, self.float16_min_size)
        rel = place_file_name(index)
        atomic_write_bytes(self.root / rel, raw)
        record = {"index": index, "file": rel, "sha256": _sha256(raw), "bytes": len(raw),
                  "signatures": data.n_signatures}
        with open(self.root / JOURNAL, "a", encoding="utf-8") as f:
            f.write(_canonical(record) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self._done[index] = record
        return record

    def finalise(self, places_meta) -> Path:
        """Write the manifest (last, atomically) and remove the journal.

        Parameters
        ----------
        places_meta : iterable of dict or PlaceMeta
            One entry per place: ``index``, ``T_world_place`` (4x4; ``pose`` is accepted too),
            ``neighbours`` (indices), and optionally ``extra`` (JSON dict).  Every place must have been
            written, and every written place must be listed.

        Returns
        -------
        Path
            The manifest.
        """
        entries = []
        for m in places_meta:
            if isinstance(m, PlaceMeta):
                m = {"index": m.index, "T_world_place": m.T_world_place, "neighbours": list(m.neighbours),
                     "extra": m.extra}
            idx = int(m["index"])
            pose = m.get("T_world_place", m.get("pose"))
            if pose is None:
                raise ValueError(f"place {idx}: no T_world_place")
            entries.append((idx, pose, [int(n) for n in m.get("neighbours", [])], m.get("extra", {})))
        listed = {e[0] for e in entries}
        if len(listed) != len(entries):
            raise ValueError("places_meta lists a place twice")
        missing = sorted(listed - set(self._done))
        extra = sorted(set(self._done) - listed)
        if missing:
            raise ValueError(f"cannot finalise: places {missing} were never written")
        if extra:
            raise ValueError(f"cannot finalise: places {extra} were written but are not in places_meta")
        unknown_nb = sorted({n for e in entries for n in e[2]} - listed)
        if unknown_nb:
            raise ValueError(f"neighbours refer to unknown places {unknown_nb}")
        places = []
        for idx, pose, nb, ext in sorted(entries, key=lambda e: e[0]):
            r = self._done[idx]
            places.append({"index": idx, "T_world_place": _pose_list(pose), "neighbours": nb,
                           "file": r["file"], "sha256": r["sha256"], "bytes": r["bytes"],
                           "signatures": r["signatures"], "extra": json.loads(_canonical(ext))})
        doc = {**self.header, "places": places}
        path = self.root / MANIFEST
        atomic_write_bytes(path, (json.dumps(doc, sort_keys=True, indent=1, allow_nan=False) + "\n").encode())
        (self.root / JOURNAL).unlink(missing_ok=True)
        _fsync_dir(self.root)
        return path


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataError(path, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None


def _read_journal(path: Path):
    lines = path.read_text(encoding="utf-8", errors="replace").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    header, records = None, []
    for i, line in enumerate(lines, 1):
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines):  # torn last line of a killed writer: that place is simply redone
                break
            raise DataError(path, "corrupt journal line", line=i) from None
        if i == 1:
            if "header" not in obj:
                raise DataError(path, "journal has no header line", line=1)
            header = obj["header"]
        elif not {"index", "file", "sha256", "bytes"} <= set(obj):
            raise DataError(path, "journal entry lacks index/file/sha256/bytes", line=i)
        else:
            records.append(obj)
    if header is None:
        raise DataError(path, "empty journal")
    return header, records


# --------------------------------------------------------------------------------------------------------
# reader
# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlaceMeta:
    """Manifest entry of one place."""

    index: int
    T_world_place: np.ndarray
    neighbours: tuple
    file: str = ""
    sha256: str = ""
    bytes: int = 0
    signatures: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def position(self) -> np.ndarray:
        return self.T_world_place[:3, 3]

    @property
    def yaw(self) -> float:
        return float(yaw_of(self.T_world_place))


class MapStore:
    """A built map, opened read-only.  Use :meth:`open`.

    Attributes
    ----------
    root : Path
    camera : Camera
    T_vehicle_camera : (4, 4) array
    params : dict
        Build parameters.
    software : str
        scenesig version that built it.
    places : dict of int -> PlaceMeta
        In index order.
    """

    def __init__(self, root: Path, doc: dict, cache_size: int):
        self.root = root
        self.manifest_path = root / MANIFEST
        self.camera = Camera.from_dict(doc["camera"])
        self.T_vehicle_camera = np.asarray(doc["T_vehicle_camera"], dtype=float)
        self.params = doc["params"]
        self.software = doc["software"]
        self.format_version = doc["format_version"]
        self.places: dict[int, PlaceMeta] = {}
        for p in doc["places"]:
            self.places[int(p["index"])] = PlaceMeta(
                index=int(p["index"]), T_world_place=np.asarray(p["T_world_place"], dtype=float),
                neighbours=tuple(int(n) for n in p["neighbours"]), file=p["file"], sha256=p["sha256"],
                bytes=int(p["bytes"]), signatures=int(p.get("signatures", 0)), extra=p.get("extra", {}))
        self._idx = np.array(list(self.places), dtype=int)
        self._xyz = np.array([m.position for m in self.places.values()]).reshape(-1, 3)
        self._yaw = np.array([m.yaw for m in self.places.values()])
        self._cache: OrderedDict[int, PlaceData] = OrderedDict()
        self._cache_size = max(0, int(cache_size))
        self._lock = threading.Lock()
        self._hits = self._misses = 0

    @classmethod
    def open(cls, root, cache_size: int = 8, verify: bool = False) -> "MapStore":
        """Open ``maps/NAME``: read and validate the manifest (and, with ``verify``, every checksum)."""
        root = Path(root)
        path = root / MANIFEST
        if not path.is_file():
            hint = (" (a build was interrupted here: re-run build-map with the same arguments to resume it)"
                    if (root / JOURNAL).exists() else "")
            raise DataError(path, f"no manifest: not a finished scenesig map{hint}")
        doc = _read_json(path)
        _validate_manifest(doc, path)
        store = cls(root, doc, cache_size)
        if verify:
            store.verify()
        return store

    def __len__(self) -> int:
        return len(self.places)

    def _read_place_bytes(self, meta: PlaceMeta) -> bytes:
        path = self.root / meta.file
        if not path.is_file():
            raise DataError(path, f"place {meta.index}'s file listed in {MANIFEST} is missing")
        raw = path.read_bytes()
        digest = _sha256(raw)
        if digest != meta.sha256:
            raise DataError(path, f"checksum mismatch: {MANIFEST} says sha256 {meta.sha256[:16]}..., the file "
                                  f"has {digest[:16]}... (corrupt, truncated or modified after the build)")
        return raw

    def verify(self) -> None:
        """Check every place file against its manifest checksum; DataError naming the first bad file."""
        for meta in self.places.values():
            self._read_place_bytes(meta)

    def load_place(self, index: int) -> PlaceData:
        """Load one place (checksum-verified), through a small LRU cache.

        The returned arrays are shared with the cache: treat them as read-only.
        """
        index = int(index)
        if index not in self.places:
            raise KeyError(f"map {self.root} has no place {index} (places: {self._idx.min() if len(self) else '-'}"
                           f"..{self._idx.max() if len(self) else '-'})")
        with self._lock:
            if index in self._cache:
                self._hits += 1
                self._cache.move_to_end(index)
                return self._cache[index]
            self._misses += 1
        meta = self.places[index]
        data = decode_place(self._read_place_bytes(meta), self.root / meta.file, index)
        for a in (data.landmarks, data.covariances, data.classifier_ids, *data.bank_arrays.values(),
                  *data.points.values()):
            a.flags.writeable = False  # cached and shared: a caller's in-place edit must not leak
        with self._lock:
            if self._cache_size:
                self._cache[index] = data
                self._cache.move_to_end(index)
                while len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
        return data

    def cache_info(self) -> CacheInfo:
        """Hits, misses and size of the place cache."""
        with self._lock:
            return CacheInfo(self._hits, self._misses, len(self._cache), self._cache_size)

    def nearest_place(self, query, max_heading_diff: float | None = np.pi / 2) -> int:
        """Index of the place nearest a position or pose.

        Parameters
        ----------
        query : (2,) or (3,) position, or (4, 4) pose ``T_world_vehicle``
            With a pose, only places whose heading is within ``max_heading_diff`` of the query's count
            (a place passed in the opposite direction sees a different scene); if none is, the nearest
            place by position is returned.
        max_heading_diff : float or None
            Radians; None ignores heading.
        """
        if len(self) == 0:
            raise ValueError(f"map {self.root} has no places")
        q = np.asarray(query, dtype=float)
        if q.shape == (4, 4):
            xy, yaw = q[:2, 3], float(yaw_of(q))
        elif q.shape in ((2,), (3,)):
            xy, yaw = q[:2], None
        else:
            raise ValueError(f"query must be a position (2,)/(3,) or a 4x4 pose, got shape {q.shape}")
        d = np.linalg.norm(self._xyz[:, :2] - xy, axis=1)
        if yaw is not None and max_heading_diff is not None:
            dyaw = np.abs(np.angle(np.exp(1j * (self._yaw - yaw))))
            ok = dyaw <= max_heading_diff
            if ok.any():
                d = np.where(ok, d, np.inf)
        return int(self._idx[np.argmin(d)])


def _validate_manifest(doc, path: Path) -> None:
    if not isinstance(doc, dict):
        raise DataError(path, "manifest must be a JSON object")
    if doc.get("format") != FORMAT_NAME:
        raise DataError(path, f"not a scenesig map manifest (format is {doc.get('format')!r}, expected "
                              f"{FORMAT_NAME!r})")
    version = doc.get("format_version")
    if version not in READABLE_VERSIONS:
        raise DataError(path, f"map format version {version!r} is not supported: this scenesig "
                              f"({software_version()}) reads version {FORMAT_VERSION}; rebuild the map "
                              f"(built by scenesig {doc.get('software', '?')})")
    for key in ("software", "camera", "T_vehicle_camera", "params", "places"):
        if key not in doc:
            raise DataError(path, f"manifest lacks '{key}'")
    try:
        Camera.from_dict(doc["camera"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(path, f"bad camera entry: {exc!r}") from None
    if np.asarray(doc["T_vehicle_camera"], dtype=float).shape != (4, 4):
        raise DataError(path, "T_vehicle_camera must be a 4x4 matrix")
    if not isinstance(doc["places"], list):
        raise DataError(path, "'places' must be a list")
    seen = set()
    for i, p in enumerate(doc["places"]):
        need = {"index", "T_world_place", "neighbours", "file", "sha256", "bytes"}
        if not isinstance(p, dict) or not need <= set(p):
            raise DataError(path, f"places[{i}] lacks {sorted(need - set(p or {}))}")
        try:
            ok = np.asarray(p["T_world_place"], dtype=float).shape == (4, 4)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise DataError(path, f"places[{i}] (place {p['index']}): T_world_place must be a 4x4 matrix")
        if p["index"] in seen:
            raise DataError(path, f"place {p['index']} listed twice")
        seen.add(p["index"])
        if Path(p["file"]).is_absolute() or ".." in Path(p["file"]).parts:
            raise DataError(path, f"place {p['index']}: file {p['file']!r} must be inside the map folder")
    for p in doc["places"]:
        bad = [n for n in p["neighbours"] if n not in seen]
        if bad:
            raise DataError(path, f"place {p['index']}: neighbours {bad} are not places of this map")


def verify_summary(root) -> dict:
    """Open the map at ``root`` verifying every place's checksum; a summary of it (``scenesig map verify``)."""
    store = MapStore.open(root, verify=True)
    sizes = [m.bytes for m in store.places.values()]
    sigs = [m.signatures for m in store.places.values()]
    return {"map": str(store.root), "format_version": store.format_version, "software": store.software,
            "places": len(store), "bytes_per_place_mean": float(np.mean(sizes)) if sizes else 0.0,
            "signatures_per_place_mean": float(np.mean(sigs)) if sigs else 0.0,
            "checksums": "ok"}
