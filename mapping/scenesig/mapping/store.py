"""The map store: one folder per map, one file per place, a manifest written last.

Layout of ``maps/NAME/``::

    manifest.json            format version, camera, T_vehicle_camera, build parameters, software version,
                             places (pose T_world_place, neighbours, file, sha256, size) -- written last
    places/place_0007.npz    one place: the signature bank's arrays (opaque), landmarks (N,3) in the place
                             frame, covariances (N,3,3), classifier ids (N,), a small keyframe (JPEG bytes),
                             per-place metadata and, optionally, the point-feature map (``points/``: ORB/SIFT
                             keypoints, descriptors and 3D points of the reference keyframe)
    journal.jsonl            only while a build runs: header + one line per place written (for resume)
    places/place_0007.g0001.npz   the place as rewritten by lifelong update generation 1 (mapping.update);
                             the manifest's ``generation``, ``history`` and places' ``extra["experiences"]``
                             say which runs went into it
    update.jsonl             only while a lifelong update runs (mapping.update)

Guarantees:

* every file is written atomically (:func:`scenesig.surveys.io.atomic_write_bytes`: temp file in the same folder,
  fsync, ``os.replace``, fsync folder);
* place files are byte-deterministic (a zip written entry by entry in sorted key order with a fixed
  timestamp; ``np.savez`` would stamp the current time), so a local build, a distributed build and an
  interrupted-then-resumed build give the same bytes;
* re-opening a :class:`MapWriter` on an interrupted build keeps every place whose file matches its journal
  checksum, so ``has_place`` lets the builder skip it;
* :class:`MapStore` checks the format version and every file's sha256, and raises
  :class:`scenesig.surveys.errors.DataError` naming the file; places load lazily through a small LRU cache.

How one place becomes bytes (smallest float types within a tolerance, float16 byte planes, LZMA zip
entries) is :mod:`scenesig.mapping.codec`; the atomic writes are :mod:`scenesig.surveys.io`.

The store only knows the bank as a ``dict[str, np.ndarray]`` (``Bank.to_arrays()`` /
``Bank.from_arrays()``), so it does not depend on how signatures are represented.

``scenesig map verify maps/NAME`` verifies a map and prints a summary (:func:`verify_summary`).
"""
from __future__ import annotations

import hashlib
import json
import threading
from collections import namedtuple
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from scenesig.surveys.cache import LRUCache
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import Camera, yaw_of
from scenesig.surveys.io import append_line, atomic_write_bytes, fsync_dir, make_dirs, remove_stale_temps
from scenesig.surveys.validation import check_pose

from .codec import (  # noqa: F401
    FORMAT_NAME,
    FORMAT_VERSION,
    READABLE_VERSIONS,
    PlaceData,
    decode_keyframe,
    decode_place,
    encode_keyframe,
    encode_place,
)
from .identity import map_id_of, new_map_id

__all__ = ["verify_summary", "FORMAT_NAME", "FORMAT_VERSION", "PlaceData", "PlaceMeta", "MapWriter", "MapStore",
           "encode_keyframe", "decode_keyframe", "place_file_name", "write_manifest", "atomic_write_bytes",
           "software_version"]

MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"
PLACES_DIR = "places"
CacheInfo = namedtuple("CacheInfo", "hits misses size maxsize")


def software_version() -> str:
    """The installed scenesig version (recorded in the manifest)."""
    try:
        from importlib.metadata import version
        return version("scenesig")
    except Exception:  # running from a source tree that is not installed
        return "unknown"


def place_file_name(index: int, generation: int = 0) -> str:
    """Relative path of a place's file, e.g. ``places/place_0007.npz``; a place rewritten by a lifelong
    update (:mod:`scenesig.mapping.update`) gets a new file per map generation, ``places/place_0007.g0002.npz``, so
    the file an older manifest lists is never overwritten."""
    if int(generation) == 0:
        return f"{PLACES_DIR}/place_{int(index):04d}.npz"
    return f"{PLACES_DIR}/place_{int(index):04d}.g{int(generation):04d}.npz"


def write_manifest(root, doc: dict) -> Path:
    """Write ``manifest.json`` atomically (sorted keys, so the same map gives the same bytes)."""
    path = Path(root) / MANIFEST
    atomic_write_bytes(path, (json.dumps(doc, sort_keys=True, indent=1, allow_nan=False) + "\n").encode())
    return path


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _pose_list(T) -> list:
    return [[float(x) for x in row] for row in check_pose(T, "a place pose")]


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
        make_dirs(self.root / PLACES_DIR)
        self.map_id: str | None = None        # set by _resume: the identity of the map being written
        self._done: dict[int, dict] = {}
        self._remove_stale_temp_files()
        if overwrite:
            self._clear()
        self._resume()

    # -- resume -------------------------------------------------------------------------------------------
    def _remove_stale_temp_files(self):
        # Left by a killed writer: never renamed, so never part of the map.
        for folder in (self.root, self.root / PLACES_DIR):
            remove_stale_temps(folder)

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
            self.map_id = map_id_of(doc)
        elif journal.exists():
            header, records = _read_journal(journal)
            bad = self._header_mismatch(header)
            if bad:
                raise DataError(journal, f"an interrupted build here used a different {bad}; resume it with "
                                         f"the same settings, or use overwrite=True to start again")
            self.map_id = header.get("map_id") if isinstance(header.get("map_id"), str) else None
        # a new map gets its identity now; a resumed build keeps the one its journal recorded
        self.map_id = self.map_id or new_map_id()
        for r in records:
            if self._verified(r):
                self._done[int(r["index"])] = r
        # Start a fresh, compact journal holding only the verified places.
        lines = [_canonical({"header": {**self.header, "map_id": self.map_id}})] + [_canonical(r) for _, r in sorted(self._done.items())]
        atomic_write_bytes(journal, ("\n".join(lines) + "\n").encode())

    def discard(self) -> None:
        """Remove every place written so far and the journal: for a build that must leave no map behind."""
        self._clear()
        self._done.clear()

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
        append_line(self.root / JOURNAL, _canonical(record))
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
        doc = {**self.header, "map_id": self.map_id, "places": places}
        path = write_manifest(self.root, doc)
        (self.root / JOURNAL).unlink(missing_ok=True)
        fsync_dir(self.root)
        return path


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataError(path, f"invalid JSON: {exc.msg}", line=exc.lineno) from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text: {exc}") from None
    except (ValueError, RecursionError) as exc:   # e.g. a 5000-digit integer, nesting too deep
        raise DataError(path, f"invalid JSON: {exc}") from None


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
    map_id : str
        The map's identity (:mod:`scenesig.mapping.identity`): drawn when it was built, kept by updates; derived from
        the manifest for a map built before identities existed (``map_id_derived`` is then True).
    generation : int
        0 for a built map, +1 per lifelong update (:mod:`scenesig.mapping.update`).
    history : list of dict
        One entry per update: ``generation``, ``runs``, ``places`` updated, ``inputs`` digest.

    Notes
    -----
    A lifelong update replaces the manifest while the map may be open.  A place whose file the
    opened manifest lists no longer matches (or is gone) is loaded through the new manifest instead
    (:meth:`refresh`), so a reader sees the old or the new place, never a failure.
    """

    def __init__(self, root: Path, doc: dict, cache_size: int):
        self.root = root
        self.manifest_path = root / MANIFEST
        self._cache = LRUCache(cache_size)       # decoded places (surveys.cache)
        self._lock = threading.Lock()
        self._set_doc(doc)

    def _set_doc(self, doc: dict) -> None:
        self.map_id = map_id_of(doc)
        self.map_id_derived = not isinstance(doc.get("map_id"), str)
        self.generation = int(doc.get("generation", 0))
        self.history = list(doc.get("history", []))
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

    def place_bytes(self, index: int) -> bytes:
        """The checksum-verified bytes of place ``index``'s file (e.g. to copy the map)."""
        return self._read_place_bytes(self.places[int(index)])

    def refresh(self) -> bool:
        """Re-read the manifest if a lifelong update replaced it; True if the map changed generation.

        Places keep their indices and poses through an update, so only place files, checksums and
        experiences change; the cache drops the places whose file changed.
        """
        doc = _read_json(self.manifest_path)
        _validate_manifest(doc, self.manifest_path)
        if int(doc.get("generation", 0)) == self.generation:
            return False
        old = dict(self.places)
        with self._lock:
            self._set_doc(doc)
            for i in self._cache.keys():
                if i not in self.places or old.get(i) is None or old[i].sha256 != self.places[i].sha256:
                    self._cache.discard(i)
        return True

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
        cached = self._cache.get(index)
        if cached is not None:
            return cached
        meta = self.places[index]
        try:
            raw = self._read_place_bytes(meta)
        except DataError:
            # replaced by a lifelong update since the manifest was read: load the new generation's file
            if not self.refresh() or index not in self.places:
                raise
            meta = self.places[index]
            raw = self._read_place_bytes(meta)
        data = decode_place(raw, self.root / meta.file, index)
        for a in (data.landmarks, data.covariances, data.classifier_ids, *data.bank_arrays.values(),
                  *data.points.values()):
            a.flags.writeable = False  # cached and shared: a caller's in-place edit must not leak
        self._cache.put(index, data)
        return data

    def cache_info(self) -> CacheInfo:
        """Hits, misses and size of the place cache."""
        c = self._cache
        return CacheInfo(c.hits, c.misses, len(c), c.size)

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


def _matrix44(v) -> bool:
    """True if ``v`` is a finite 4x4 matrix (nested lists of numbers)."""
    try:
        m = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return False
    return m.shape == (4, 4) and bool(np.isfinite(m).all())


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _validate_manifest(doc, path: Path) -> None:
    """Every field :class:`MapStore` uses has the right type and shape; DataError naming ``path``."""
    if not isinstance(doc, dict):
        raise DataError(path, "manifest must be a JSON object")
    if doc.get("format") != FORMAT_NAME:
        raise DataError(path, f"not a scenesig map manifest (format is {doc.get('format')!r}, expected "
                              f"{FORMAT_NAME!r})")
    version = doc.get("format_version")
    if not _is_int(version) or version not in READABLE_VERSIONS:
        raise DataError(path, f"map format version {version!r} is not supported: this scenesig "
                              f"({software_version()}) reads version {FORMAT_VERSION}; rebuild the map "
                              f"(built by scenesig {doc.get('software', '?')})")
    for key in ("software", "camera", "T_vehicle_camera", "params", "places"):
        if key not in doc:
            raise DataError(path, f"manifest lacks '{key}'")
    cam = doc["camera"]
    try:
        c = Camera.from_dict(cam)
        ok = all(np.isfinite([c.fx, c.fy, c.cx, c.cy])) and c.fx > 0 and c.fy > 0 and c.width > 0 and c.height > 0
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise DataError(path, f"bad camera entry: {exc!r}") from None
    if not ok:
        raise DataError(path, "bad camera entry: focal lengths and size must be positive and finite")
    if not _matrix44(doc["T_vehicle_camera"]):
        raise DataError(path, "T_vehicle_camera must be a finite 4x4 matrix")
    if not isinstance(doc["params"], dict):
        raise DataError(path, "'params' must be an object")
    if "map_id" in doc and not (isinstance(doc["map_id"], str) and doc["map_id"]):
        raise DataError(path, f"bad 'map_id' {str(doc['map_id'])[:60]!r}: must be a non-empty string")
    if not isinstance(doc["places"], list):
        raise DataError(path, "'places' must be a list")
    seen = set()
    need = {"index": _is_int, "T_world_place": _matrix44, "neighbours": lambda v: isinstance(v, list),
            "file": lambda v: isinstance(v, str) and bool(v), "sha256": lambda v: isinstance(v, str),
            "bytes": _is_int, "signatures": _is_int, "extra": lambda v: isinstance(v, dict)}
    optional = {"signatures", "extra"}
    for i, p in enumerate(doc["places"]):
        if not isinstance(p, dict):
            raise DataError(path, f"places[{i}] must be an object")
        missing = sorted(set(need) - optional - set(p))
        if missing:
            raise DataError(path, f"places[{i}] lacks {missing}")
        for key, valid in need.items():
            if key in p and not valid(p[key]):
                raise DataError(path, f"places[{i}] (place {p['index']!r}): bad '{key}' {str(p[key])[:60]!r}")
        if p["index"] in seen:
            raise DataError(path, f"place {p['index']} listed twice")
        seen.add(p["index"])
        if Path(p["file"]).is_absolute() or ".." in Path(p["file"]).parts:
            raise DataError(path, f"place {p['index']}: file {p['file']!r} must be inside the map folder")
    for p in doc["places"]:
        bad = [n for n in p["neighbours"] if not _is_int(n) or n not in seen]
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
