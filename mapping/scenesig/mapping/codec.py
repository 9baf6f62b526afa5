"""The place file codec: one place (:class:`PlaceData`) to deterministic bytes and back.

A place file is an ``.npz`` (a zip of ``.npy`` entries) written entry by entry in sorted key order with
a fixed timestamp, so the same place gives the same bytes on every machine (``np.savez`` would stamp
the current time).  Float arrays are stored in the smallest float type whose rounding error stays below
a tolerance, measured per array (and, for the bank, optionally on the detection scores themselves), and
restored to their original dtype on load; large float16 arrays (the classifier filters) keep only the
mantissa bits the tolerance needs and are written as byte planes, and zip entries are LZMA-compressed
(map format version 2; version 1 files, deflated plain float16, still load).  The folder, manifest,
journal and checksums around the files are :mod:`scenesig.mapping.store`.
"""
from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from scenesig.surveys.errors import DataError
from scenesig.surveys.validation import check_image

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "PlaceData", "encode_place", "decode_place", "encode_keyframe", "decode_keyframe",
           "FLOAT16_MIN_MANTISSA_BITS", "GEOMETRY_TOL"]

FORMAT_NAME = "scenesig-map"
#: Version of the map format (place files and manifest) this code writes.
FORMAT_VERSION = 2
#: Versions this code reads (1: float16 arrays stored as such; 2: as byte planes, fewer mantissa bits).
READABLE_VERSIONS = (1, 2)
#: float16 arrays keep at least this many of their 10 mantissa bits.
FLOAT16_MIN_MANTISSA_BITS = 4
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # the earliest date zip can store; fixed so bytes repeat
# LZMA zip entries (np.load reads them through zipfile): 4.5 % smaller places than deflate on the demo
# map (252.8 -> 241.4 kB), lossless; loading a place takes ~20 ms instead of ~5 ms, once per place.
_ZIP_COMPRESSION = zipfile.ZIP_LZMA
_BANK_PREFIX = "bank/"
_POINTS_PREFIX = "points/"

#: Relative rounding error (per row, L2) tolerated when storing landmarks and covariances.
GEOMETRY_TOL = 1e-6

# --------------------------------------------------------------------------------------------------------
# keyframes
# --------------------------------------------------------------------------------------------------------
def encode_keyframe(image: np.ndarray, width: int = 160, quality: int = 90) -> bytes:
    """A small gray JPEG of ``image`` (BGR or gray uint8) for figures, ``width`` pixels wide."""
    import cv2

    img = check_image(image, "keyframe", uint8=True)
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
        (:func:`scenesig.mapping.pointmap.build_point_features`: keyframe keypoints, descriptors, 3D points).
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
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise DataError(path, f"bad JSON in the place file's format/meta entry: {exc}") from None
    if not isinstance(fmt, dict) or not isinstance(meta, dict):
        raise DataError(path, "the place file's format/meta entries must be JSON objects")
    if fmt.get("format") != FORMAT_NAME or fmt.get("format_version") not in READABLE_VERSIONS:
        raise DataError(path, f"place file is {fmt.get('format')!r} version {fmt.get('format_version')!r}; "
                              f"this scenesig reads {FORMAT_NAME!r} versions {list(READABLE_VERSIONS)}")
    if index is not None and fmt.get("place") != index:
        raise DataError(path, f"place file holds place {fmt.get('place')}, expected place {index}")
    dtypes = fmt.get("dtypes", {})
    planes = fmt.get("float16_planes", {})
    if not isinstance(dtypes, dict) or not isinstance(planes, dict):
        raise DataError(path, "bad 'dtypes' or 'float16_planes' in the place file's format entry")
    for k, enc in planes.items():
        try:
            arrays[k] = _from_planes(arrays[k], enc["shape"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(path, f"bad float16 planes for {k!r}: {exc}") from None
    try:
        restore = {k: (v.astype(dtypes[k]) if k in dtypes and str(v.dtype) != dtypes[k] else v)
                   for k, v in arrays.items()}
    except (TypeError, ValueError) as exc:
        raise DataError(path, f"bad dtype in the place file's format entry: {exc}") from None
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
