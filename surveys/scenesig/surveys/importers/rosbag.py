"""ROS bags <-> survey runs and localisations: ROS 1 ``.bag``, ROS 2 sqlite3 ``.db3`` and MCAP, through ``rosbags``.

``rosbags`` (Ternaris; pure Python, no ROS installation) reads and writes all three containers; it is an
optional extra (``pip install 'scenesig[ros]'``) and every entry point says so when it is missing.

Import (:func:`load_rosbag`, ``scenesig import rosbag``) -- what becomes what:

* frames: the messages of ``image_topic``, ``sensor_msgs/Image`` (``mono8``, ``bgr8``, ``rgb8``, ``bgra8``,
  ``rgba8``, ``8UC1``, ``8UC3`` and ``bayer_{rggb,bggr,gbrg,grbg}8``, demosaiced as ``cv_bridge`` does) or
  ``sensor_msgs/CompressedImage`` (JPEG or PNG). Raw images are stored as PNG -- lossless, so the pixels
  are the message's -- and compressed ones byte for byte; each is decoded strictly once
  (:func:`scenesig.surveys.images.decode_image`).
* times: **header stamps** (the time the sensor saw the data), not the bag's record times (the time the
  recorder received it, later by the transport delay); ``stamps="record"`` uses record times for drivers
  that leave the header empty. How far the two differ per topic goes to ``[metadata] record_minus_header_s``.
  A message whose stamp does not increase on its topic (a duplicate or a late, reordered message) is
  skipped and counted (``[metadata] skipped``); dropped messages stay gaps (``gaps``, ``odometry_gaps``,
  ``groundtruth_gaps``), never interpolated.
* camera: ``sensor_msgs/CameraInfo`` (``K`` and ``plumb_bob`` / ``rational_polynomial`` distortion; for a
  rectified image topic ``P`` and no distortion), or ``intrinsics`` given.
* ``T_vehicle_camera``: the static transform ``base_frame`` -> the images' ``frame_id`` in ``/tf_static``
  (any chain of static transforms), or ``extrinsic`` given. ROS camera frames are optical frames (x right,
  y down, z forward), as ours; the vehicle frame is ``base_frame`` (REP-103: x forward, y left, z up).
* ``odometry.csv``: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped`` or
  ``TransformStamped`` poses, or with ``odom_topic="/tf"`` the tf chain ``odom_frame`` -> ``base_frame``.
* ``groundtruth.tum`` (INS / GPS-aided poses): another such topic (``gt_topic``; over ``/tf`` the chain
  ``gt_frame`` -> ``base_frame``); ``truth.tum`` (a simulator's exact poses) likewise from ``truth_topic``.
  Without an odometry topic the odometry is the ground truth (not an independent sensor, as the other
  importers say).

Export: :func:`export_trajectory_bag` writes a localisation (``trajectory.tum``) as ``nav_msgs/Odometry``
(with the pose covariance where the localiser states one, else all zeros: ROS's "unknown") and ``/tf``;
:func:`write_run_bag` writes a whole survey run as a bag (images, camera info, odometry, INS, truth,
``/tf_static``), so a simulated run can be played in RViz / Foxglove and round-tripped through the importer.
"""
from __future__ import annotations

import logging
import math
import os
import re
import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CorruptImageError, DataError
from ..geometry import Camera, interpolate_poses, invert, pose_to_xyzquat, xyzquat_to_pose
from ..io import atomic_folder, atomic_path
from ..run import SurveyRun
from ..settings import merge_settings
from .common import find_gaps, odometry_from_groundtruth, odometry_note, odometry_with_noise, ticks_to_seconds

__all__ = ["default_config", "require_rosbags", "camera_from_info", "bag_paths", "bag_format", "list_topics", "suggest_arguments",
           "load_rosbag", "import_rosbag", "write_run_bag", "export_trajectory_bag", "read_bag_poses",
           "read_pose_covariances", "raw_image", "IMAGE", "COMPRESSED_IMAGE", "CAMERA_INFO", "ODOMETRY",
           "POSE_STAMPED", "POSE_COV_STAMPED", "TRANSFORM_STAMPED", "TF_MESSAGE", "FORMATS"]

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED, TRANSFORM_STAMPED, TF_MESSAGE)
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
#: export formats: ROS 1 bag file, ROS 2 bag (sqlite3), ROS 2 bag (MCAP; a bare ``.mcap`` file when OUT ends so)
FORMATS = ("ros1", "ros2", "mcap")

default_config = {
    "image_topic": None,          # required: sensor_msgs/Image or sensor_msgs/CompressedImage
    "camera_info_topic": None,    # sensor_msgs/CameraInfo; or "intrinsics"
    "odom_topic": None,           # Odometry / PoseStamped / PoseWithCovarianceStamped / TransformStamped, or "/tf"
    "gt_topic": None,             # INS / GPS-aided poses -> groundtruth.tum (same types)
    "truth_topic": None,          # a simulator's exact poses -> truth.tum (same types)
    "intrinsics": None,           # [fx, fy, cx, cy(, k1, k2, p1, p2(, k3))] instead of CameraInfo
    "extrinsic": None,            # 4x4 T_vehicle_camera instead of /tf_static
    "base_frame": None,           # vehicle frame; default the odometry's child_frame_id, else base_link
    "odom_frame": "odom",         # parent of the odometry chain when odom_topic is /tf
    "gt_frame": "map",            # parent of the ground-truth chain when gt_topic is /tf
    "stamps": "header",           # header | record
    "rectified": None,            # images rectified (use CameraInfo P, no distortion); None: topic name has "rect"
    "skip_corrupt": False,        # leave out (and count) corrupt image messages instead of stopping
    "name": None,                 # run name (default: the bag's name)
    "conditions": [],
    "odometry_noise": 0.0,
    "odometry_seed": 0,
    "gap_factor": 1.5,
}

_MISSING = ("reading and writing ROS bags needs the optional package rosbags: "
            "pip install 'scenesig[ros]' (or pip install rosbags)")


def require_rosbags(path=None):
    """Import ``rosbags`` or raise a :class:`DataError` (naming ``path``) that says how to install it."""
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.rosbag1  # noqa: F401
        import rosbags.rosbag2  # noqa: F401
        import rosbags.typesys  # noqa: F401
    except ImportError:
        raise DataError(path, _MISSING) from None
    import rosbags

    return rosbags


# --------------------------------------------------------------------------------------- opening bags
def bag_paths(bag) -> list[Path]:
    """The bag as ``rosbags`` opens it: one or more ROS 1 ``.bag`` files (a split recording), or one ROS 2
    bag (a folder with ``metadata.yaml``, or a bare ``.db3`` / ``.mcap`` file)."""
    paths = [Path(p) for p in (bag if isinstance(bag, (list, tuple)) else [bag])]
    for p in paths:
        if not p.exists():
            raise DataError(p, "bag not found")
    ros1 = [p for p in paths if p.suffix == ".bag"]
    if ros1 and len(ros1) != len(paths):
        raise DataError(paths[0], "mixes ROS 1 .bag files with other paths: give the ROS 1 files of one recording, "
                                  "or one ROS 2 bag")
    if not ros1:
        if len(paths) > 1:
            raise DataError(paths[1], "a ROS 2 bag is one folder (or one .db3 / .mcap file)")
        p = paths[0]
        if p.is_dir() and not (p / "metadata.yaml").is_file():
            raise DataError(p / "metadata.yaml", "not found: a ROS 2 bag folder has metadata.yaml "
                                                 "(or give the .db3 / .mcap file itself)")
        if p.is_file() and p.suffix not in (".db3", ".mcap"):
            raise DataError(p, "not a ROS bag: expected a ROS 1 .bag file, a ROS 2 bag folder, or a .db3 / .mcap file")
    return paths


def bag_format(paths: list[Path]) -> str:
    """``ros1``, ``ros2-sqlite3`` or ``ros2-mcap``."""
    p = paths[0]
    if p.suffix == ".bag":
        return "ros1"
    if p.is_dir():
        return "ros2-mcap" if any(p.glob("*.mcap")) else "ros2-sqlite3"
    return "ros2-mcap" if p.suffix == ".mcap" else "ros2-sqlite3"


@contextmanager
def _reader(paths: list[Path]):
    """An open ``AnyReader``; a bag it cannot read is a DataError naming it."""
    require_rosbags(paths[0])
    from rosbags.highlevel import AnyReader, AnyReaderError

    default = _typestore("ros1" if paths[0].suffix == ".bag" else "ros2")
    try:
        reader = AnyReader(paths, default_typestore=default)
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise DataError(paths[0], f"not a readable ROS bag ({type(exc).__name__}: {exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def _deserialize(reader, raw, msgtype: str, path: Path, topic: str, k: int):
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as exc:  # rosbags raises several types for a malformed message
        raise DataError(path, f"{topic}: message {k} does not deserialise as {msgtype} ({exc})") from None


def _sec(ns) -> float:
    return float(ticks_to_seconds([int(ns)])[0])


def _ns(t: float) -> int:
    """Seconds -> integer nanoseconds through the 9-decimal text the run files use (an exact round trip)."""
    return int(f"{t:.9f}".replace(".", ""))


# --------------------------------------------------------------------------------------- --list
def list_topics(bag) -> dict:
    """``{topic: {"type", "count", "rate_hz", "first_s", "last_s"}}`` (rates from record times) and the
    bag's ``format``, ``duration_s`` and ``tf`` frames (``{child: parent}``, static and dynamic)."""
    paths = bag_paths(bag)
    out = {}
    tf = {}
    with _reader(paths) as r:
        conns = {}
        for c in r.connections:
            conns.setdefault(c.topic, []).append(c)
        for topic, cs in sorted(conns.items()):
            times = []
            for c, t, raw in r.messages(connections=cs):
                times.append(t)
                if c.msgtype == TF_MESSAGE and len(tf) < 200:
                    msg = _deserialize(r, raw, c.msgtype, paths[0], topic, len(times) - 1)
                    for ts in msg.transforms:
                        tf.setdefault(ts.child_frame_id, (ts.header.frame_id, topic))
            types = sorted({c.msgtype for c in cs})
            n = len(times)
            dur = (times[-1] - times[0]) / 1e9 if n > 1 else 0.0
            out[topic] = {"type": types[0] if len(types) == 1 else types, "count": n,
                          "rate_hz": round((n - 1) / dur, 3) if dur > 0 else None,
                          "first_s": _sec(times[0]) if n else None, "last_s": _sec(times[-1]) if n else None}
        duration = r.duration / 1e9 if r.message_count else 0.0
    return {"bag": [str(p) for p in paths], "format": bag_format(paths), "duration_s": duration, "topics": out,
            "tf": {child: {"parent": p, "topic": t} for child, (p, t) in sorted(tf.items())}}


def suggest_arguments(listing: dict) -> tuple[list[str], list[str]]:
    """Suggested ``scenesig import rosbag`` arguments for a :func:`list_topics` listing, and notes on them."""
    topics = listing["topics"]

    def of(*types):
        return [t for t, d in topics.items() if d["type"] in types]

    args, notes = [], []
    images = of(*IMAGE_TYPES)
    if images:
        img = images[0]
        ns = img.rsplit("/", 1)[0]
        infos = [t for t in of(CAMERA_INFO) if t.rsplit("/", 1)[0] in (ns, ns.rsplit("/", 1)[0])] or of(CAMERA_INFO)
        args += [f"--image-topic {img}", f"--camera-info-topic {infos[0]}" if infos else "--intrinsics FX,FY,CX,CY"]
        if len(images) > 1:
            notes.append("other image topics: " + ", ".join(images[1:]))
    else:
        notes.append("no sensor_msgs/Image or CompressedImage topic: this bag has no camera to import")
    poses = of(ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED, TRANSFORM_STAMPED)
    odo = [t for t in poses if "odom" in t.lower()] or poses
    frames = listing.get("tf", {})
    if odo:
        args.append(f"--odom-topic {odo[0]}")
    elif "/tf" in topics and any(v["parent"] == "odom" for v in frames.values()):
        args.append("--odom-topic /tf --odom-frame odom")
    rest = [t for t in poses if t not in odo[:1]]
    if rest:
        args.append(f"--gt-topic {rest[0]}")
        notes.append(f"--gt-topic {rest[0]}: if it holds INS / GPS-aided poses (build-map needs them)")
    if "/tf_static" not in topics:
        args.append("--extrinsic X,Y,Z,QX,QY,QZ,QW")
        notes.append("no /tf_static: give the camera's pose on the vehicle with --extrinsic")
    return args, notes


# ROS encoding -> (channels, OpenCV conversion to BGR or None); Bayer names as cv_bridge maps them
_RAW_ENCODINGS = {"mono8": (1, None), "8UC1": (1, None), "bgr8": (3, None), "8UC3": (3, None),
                  "rgb8": (3, "COLOR_RGB2BGR"), "bgra8": (4, "COLOR_BGRA2BGR"), "rgba8": (4, "COLOR_RGBA2BGR"),
                  "bayer_rggb8": (1, "COLOR_BayerBG2BGR"), "bayer_bggr8": (1, "COLOR_BayerRG2BGR"),
                  "bayer_gbrg8": (1, "COLOR_BayerGR2BGR"), "bayer_grbg8": (1, "COLOR_BayerGB2BGR")}


def raw_image(msg) -> np.ndarray:
    """A ``sensor_msgs/Image`` as a uint8 array (grey (h,w) or BGR (h,w,3)); ValueError saying what is wrong."""
    import cv2

    enc = msg.encoding
    if enc not in _RAW_ENCODINGS:
        raise ValueError(f"image encoding {enc!r} not supported ({', '.join(_RAW_ENCODINGS)} are)")
    ch, conv = _RAW_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise ValueError(f"empty image ({w}x{h})")
    if step < w * ch:
        raise ValueError(f"step {step} is less than width x channels = {w * ch}")
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < step * h:
        raise ValueError(f"truncated image data: {data.size} bytes for {h} rows of {step}")
    img = data[:step * h].reshape(h, step)[:, :w * ch]
    img = img.reshape(h, w, ch) if ch > 1 else img
    if conv is not None:
        img = cv2.cvtColor(np.ascontiguousarray(img), getattr(cv2, conv))
    return np.ascontiguousarray(img)


def _compressed_kind(msg) -> str:
    from ..images import image_kind

    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise ValueError(f"format {msg.format!r}: depth images are not camera frames")
    kind = image_kind(bytes(np.asarray(msg.data[:8], dtype=np.uint8)))
    if kind not in ("jpeg", "png"):
        raise ValueError(f"format {msg.format!r}: the data is neither JPEG nor PNG")
    return kind


@dataclass
class _Frames:
    """What the first pass over the image topic found: the kept messages and why others were left out."""

    index: list = field(default_factory=list)     # position of each kept message in the topic's stream
    stamps: list = field(default_factory=list)    # ns, header (or record) stamps
    exts: list = field(default_factory=list)      # ".png" / ".jpg"
    size: tuple | None = None
    frame_id: str | None = None
    encodings: set = field(default_factory=set)
    corrupt: list = field(default_factory=list)   # [(message index, stamp s, reason)]


# --------------------------------------------------------------------------------------- tf
class _TfTree:
    """Transforms from ``/tf_static`` and ``/tf``: each child frame has one parent (tf's rule)."""

    def __init__(self):
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}     # child -> T_parent_child
        self.dynamic: dict[str, tuple[list, list]] = {}
        self.skipped = 0

    def add(self, path: Path, topic: str, parent: str, child: str, T: np.ndarray, ns: int, static: bool):
        parent, child = parent.lstrip("/"), child.lstrip("/")
        old = self.parent.get(child)
        if old is not None and old != parent:
            raise DataError(path, f"{topic}: frame {child!r} has two parents, {old!r} and {parent!r} (tf allows one)")
        self.parent[child] = parent
        if static:
            self.static[child] = T
            return
        ts, Ts = self.dynamic.setdefault(child, ([], []))
        if ts and ns <= ts[-1]:
            self.skipped += 1
            return
        ts.append(ns)
        Ts.append(T)

    def _up(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self.parent and len(chain) < 100:
            chain.append(self.parent[chain[-1]])
        return chain

    def path(self, a: str, b: str):
        """Edges from ``a`` to ``b``: ``[(child, +1 | -1)]`` (+1 descends parent -> child), or None."""
        a, b = a.lstrip("/"), b.lstrip("/")
        ua, ub = self._up(a), self._up(b)
        common = next((f for f in ua if f in ub), None)
        if common is None:
            return None
        return [(f, -1) for f in ua[:ua.index(common)]] + [(f, +1) for f in reversed(ub[:ub.index(common)])]

    def static_transform(self, a: str, b: str) -> np.ndarray | None:
        """``T_a_b`` through static transforms only, or None."""
        edges = self.path(a, b)
        if edges is None or any(c not in self.static for c, _ in edges):
            return None
        T = np.eye(4)
        for c, d in edges:
            T = T @ (self.static[c] if d > 0 else invert(self.static[c]))
        return T

    def series(self, a: str, b: str):
        """``(ns, T_a_b)`` at the stamps of the chain's busiest dynamic transform (others interpolated within
        their span), or None when ``a`` and ``b`` are not connected through at least one dynamic transform."""
        edges = self.path(a, b)
        if edges is None:
            return None
        dyn = [c for c, _ in edges if c in self.dynamic and c not in self.static]
        if not dyn or any(c not in self.static and c not in self.dynamic for c, _ in edges):
            return None
        lead = max(dyn, key=lambda c: len(self.dynamic[c][0]))
        ns = np.asarray(self.dynamic[lead][0], dtype=np.int64)
        for c in dyn:
            t = self.dynamic[c][0]
            ns = ns[(ns >= t[0]) & (ns <= t[-1])]
        if not len(ns):
            return None
        T = np.tile(np.eye(4), (len(ns), 1, 1))
        for c, d in edges:
            if c in self.static:
                E = np.broadcast_to(self.static[c], T.shape)
            elif c == lead:
                idx = np.searchsorted(self.dynamic[c][0], ns)
                E = np.asarray(self.dynamic[c][1])[idx]
            else:
                t0 = ns[0]  # interpolate in seconds from the first stamp (float64 keeps nanoseconds there)
                E = interpolate_poses((np.asarray(self.dynamic[c][0]) - t0) / 1e9, np.asarray(self.dynamic[c][1]),
                                      (ns - t0) / 1e9)
            T = T @ (E if d > 0 else invert(E))
        return ns, T


def _pose_from(position, orientation, path: Path, topic: str, k: int) -> np.ndarray:
    v = [position.x, position.y, position.z, orientation.x, orientation.y, orientation.z, orientation.w]
    if not all(math.isfinite(x) for x in v):
        raise DataError(path, f"{topic}: message {k} has a NaN or infinite pose")
    if math.sqrt(sum(x * x for x in v[3:])) < 1e-9:
        raise DataError(path, f"{topic}: message {k} has a zero quaternion")
    return xyzquat_to_pose(v)


def _poses_of(msg, msgtype: str, path: Path, topic: str, k: int):
    """``[(header, parent frame, child frame or None, T_parent_child)]`` of a pose message."""
    if msgtype == ODOMETRY:
        p = msg.pose.pose
        return [(msg.header, msg.header.frame_id, msg.child_frame_id,
                 _pose_from(p.position, p.orientation, path, topic, k))]
    if msgtype == POSE_STAMPED:
        return [(msg.header, msg.header.frame_id, None,
                 _pose_from(msg.pose.position, msg.pose.orientation, path, topic, k))]
    if msgtype == POSE_COV_STAMPED:
        p = msg.pose.pose
        return [(msg.header, msg.header.frame_id, None, _pose_from(p.position, p.orientation, path, topic, k))]
    if msgtype == TRANSFORM_STAMPED:
        tr = msg.transform
        return [(msg.header, msg.header.frame_id, msg.child_frame_id,
                 _pose_from(tr.translation, tr.rotation, path, topic, k))]
    if msgtype == TF_MESSAGE:
        return [x for ts in msg.transforms for x in _poses_of(ts, TRANSFORM_STAMPED, path, topic, k)]
    raise ValueError(msgtype)


@dataclass
class _Series:
    """One pose topic as read: stamps (ns), poses, and what was left out."""

    ns: list = field(default_factory=list)
    poses: list = field(default_factory=list)
    record_minus_header: list = field(default_factory=list)
    parent: str | None = None
    child: str | None = None
    non_monotonic: int = 0


# --------------------------------------------------------------------------------------- import
def _check_topic(path: Path, topics: dict, topic: str | None, types: tuple, what: str, needed: bool = True):
    if topic is None:
        return None
    if topic not in topics:
        have = ", ".join(sorted(topics)) or "none"
        raise DataError(path, f"no topic {topic!r} ({what}) in this bag; its topics: {have} "
                              "(`scenesig import rosbag BAG --list` shows them with types)")
    t = topics[topic].msgtype
    if t not in types:
        raise DataError(path, f"topic {topic!r} ({what}) is {t}, expected {' or '.join(types)}")
    if needed and not topics[topic].msgcount:
        raise DataError(path, f"topic {topic!r} ({what}) has no messages")
    return t


def camera_from_info(msg, path, topic: str, rectified: bool = False) -> Camera:
    """A ``sensor_msgs/CameraInfo`` message as a :class:`Camera` (P when ``rectified``, else K and D);
    :class:`DataError` naming ``path`` and ``topic`` when it holds no usable calibration."""
    return _camera_from_info(msg, Path(path), topic, rectified)


def _camera_from_info(msg, path: Path, topic: str, rectified: bool) -> Camera:
    def get(a):       # ROS 2 names the fields k, d, p; ROS 1 K, D, P
        return getattr(msg, a) if hasattr(msg, a) else getattr(msg, a.upper())
    K, D, P = (np.asarray(get(a), dtype=float) for a in ("k", "d", "p"))
    w, h = int(msg.width), int(msg.height)
    if w <= 0 or h <= 0 or K.size != 9 or P.size != 12 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0:
        raise DataError(path, f"{topic}: CameraInfo has no calibration (size {w}x{h}, K {K.tolist()})")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
        raise DataError(path, f"{topic}: binned images (binning {msg.binning_x}x{msg.binning_y}) are not supported")
    roi = msg.roi
    if int(roi.width) and (int(roi.width), int(roi.height)) != (w, h):
        raise DataError(path, f"{topic}: region-of-interest images ({roi.width}x{roi.height} of {w}x{h}) are not "
                              "supported")
    if rectified:
        if P[0] <= 0 or P[5] <= 0:
            raise DataError(path, f"{topic}: CameraInfo P is not a projection for rectified images")
        return Camera(float(P[0]), float(P[5]), float(P[2]), float(P[6]), w, h)
    model = msg.distortion_model
    d = [float(v) for v in D]
    if model in ("plumb_bob", "rational_polynomial") or (not model and not any(d)):
        if any(d[5:]):
            raise DataError(path, f"{topic}: rational_polynomial distortion with k4..k6 is not supported")
        d = d[:5]
    else:
        raise DataError(path, f"{topic}: distortion model {model!r} not supported (plumb_bob, rational_polynomial)")
    return Camera(float(K[0]), float(K[4]), float(K[2]), float(K[5]), w, h, tuple(d) if any(d) else ())


def _intrinsics(values, size) -> Camera:
    v = [float(x) for x in values]
    if len(v) not in (4, 8, 9) or v[0] <= 0 or v[1] <= 0:
        raise ValueError(f"intrinsics: fx, fy, cx, cy (fx, fy > 0) and optionally k1, k2, p1, p2(, k3); got {values}")
    return Camera(v[0], v[1], v[2], v[3], int(size[0]), int(size[1]), tuple(v[4:]) if any(v[4:]) else ())


def _scan(paths: list[Path], conf: dict):
    """One pass over the bag: the image topic's stamps (each image decoded strictly), the camera info, the
    pose topics and tf. Returns everything :func:`load_rosbag` turns into a run."""
    from tqdm import tqdm

    from ..images import decode_image

    path = paths[0]
    use_header = conf["stamps"] == "header"
    if conf["stamps"] not in ("header", "record"):
        raise ValueError(f"stamps must be 'header' or 'record', not {conf['stamps']!r}")
    if not conf["image_topic"]:
        raise ValueError("image_topic is required (`scenesig import rosbag BAG --list` shows the topics)")
    with _reader(paths) as r:
        topics = r.topics
        img_type = _check_topic(path, topics, conf["image_topic"], IMAGE_TYPES, "images")
        _check_topic(path, topics, conf["camera_info_topic"], (CAMERA_INFO,), "camera info")
        pose_topics = {}
        for key, what in (("odom_topic", "odometry"), ("gt_topic", "ground truth"), ("truth_topic", "truth")):
            if conf[key] is not None:
                pose_topics[conf[key]] = _check_topic(path, topics, conf[key], POSE_TYPES, what)
        read = {conf["image_topic"], *pose_topics}
        if conf["camera_info_topic"]:
            read.add(conf["camera_info_topic"])
        # /tf_static for the extrinsic and frame changes; /tf only where a pose chain is asked of it
        for tf_topic in ("/tf_static", "/tf"):
            if tf_topic in topics and topics[tf_topic].msgtype == TF_MESSAGE and (tf_topic == "/tf_static"
                                                                                  or tf_topic in pose_topics):
                read.add(tf_topic)
        conns = [c for c in r.connections if c.topic in read]

        frames = _Frames()
        series = {t: _Series() for t in pose_topics if pose_topics[t] != TF_MESSAGE}
        tree = _TfTree()
        info = None
        img_offsets = []
        counts = {}
        bar = tqdm(total=topics[conf["image_topic"]].msgcount, desc=f"read {path.name}", unit="frame",
                   disable=not conf.get("_progress", False))
        for c, rec, raw in r.messages(connections=conns):
            topic = c.topic
            k = counts[topic] = counts.get(topic, -1) + 1
            if topic == conf["image_topic"]:
                bar.update()
                msg = _deserialize(r, raw, c.msgtype, path, topic, k)
                stamp = _stamp_ns_of(msg.header) if use_header else rec
                where = f"{topic}: message {k} (stamp {stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d})"
                if use_header and stamp == 0:
                    raise DataError(path, f"{topic}: message {k} has a zero header stamp (the driver did not fill "
                                          "it in); pass --stamps record to use the bag's record times")
                if frames.stamps and stamp <= frames.stamps[-1]:
                    counts[(topic, "non_monotonic")] = counts.get((topic, "non_monotonic"), 0) + 1
                    continue
                if img_type == IMAGE and msg.encoding not in _RAW_ENCODINGS:  # the topic's format, not one bad frame
                    raise DataError(path, f"{where}: image encoding {msg.encoding!r} not supported "
                                          f"({', '.join(_RAW_ENCODINGS)} are)")
                try:
                    if img_type == IMAGE:
                        frames.encodings.add(msg.encoding)
                        img = raw_image(msg)
                        ext = ".png"
                    else:
                        kind = _compressed_kind(msg)
                        frames.encodings.add(f"compressed {kind}")
                        img = decode_image(bytes(msg.data), where)
                        ext = ".jpg" if kind == "jpeg" else ".png"
                except (ValueError, CorruptImageError) as exc:
                    reason = exc.message if isinstance(exc, CorruptImageError) else str(exc)
                    if not conf["skip_corrupt"]:
                        raise DataError(path, f"{where}: {reason} (--skip-corrupt leaves such frames out)") from None
                    frames.corrupt.append((k, _sec(stamp), reason))
                    continue
                size = (img.shape[1], img.shape[0])
                if frames.size is None:
                    frames.size, frames.frame_id = size, msg.header.frame_id.lstrip("/")
                elif size != frames.size:
                    raise DataError(path, f"{where}: image is {size[0]}x{size[1]}, earlier ones {frames.size[0]}x"
                                          f"{frames.size[1]}")
                elif msg.header.frame_id.lstrip("/") != frames.frame_id:
                    raise DataError(path, f"{where}: frame_id {msg.header.frame_id!r}, earlier images "
                                          f"{frames.frame_id!r}: one camera per import")
                frames.index.append(k)
                frames.stamps.append(stamp)
                frames.exts.append(ext)
                img_offsets.append(rec - _stamp_ns_of(msg.header))
            elif topic == conf["camera_info_topic"]:
                msg = _deserialize(r, raw, c.msgtype, path, topic, k)
                if info is None:
                    info = msg
                elif (msg.width, msg.height) != (info.width, info.height) or not np.array_equal(
                        np.asarray(getattr(msg, "k", getattr(msg, "K", None))),
                        np.asarray(getattr(info, "k", getattr(info, "K", None)))):
                    raise DataError(path, f"{topic}: message {k} changes the calibration; import each calibration's "
                                          "part of the log separately")
            elif topic in ("/tf", "/tf_static"):
                msg = _deserialize(r, raw, c.msgtype, path, topic, k)
                for hdr, parent, child, T in _poses_of(msg, TF_MESSAGE, path, topic, k):
                    stamp = _stamp_ns_of(hdr) if use_header else rec
                    tree.add(path, topic, parent, child, T, stamp, topic == "/tf_static")
            if topic in series:
                msg = _deserialize(r, raw, c.msgtype, path, topic, k)
                s = series[topic]
                for hdr, parent, child, T in _poses_of(msg, c.msgtype, path, topic, k):
                    stamp = _stamp_ns_of(hdr) if use_header else rec
                    if use_header and stamp == 0:
                        raise DataError(path, f"{topic}: message {k} has a zero header stamp; pass --stamps record "
                                              "to use the bag's record times")
                    if s.ns and stamp <= s.ns[-1]:
                        s.non_monotonic += 1
                        continue
                    s.parent, s.child = s.parent or parent, s.child or child
                    s.ns.append(stamp)
                    s.poses.append(T)
                    s.record_minus_header.append(rec - _stamp_ns_of(hdr))
        bar.close()
    skipped_img = counts.get((conf["image_topic"], "non_monotonic"), 0)
    return frames, info, series, tree, img_offsets, skipped_img, pose_topics


def _stamp_ns_of(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _rate(ns) -> float:
    """Nominal rate (Hz) from the median interval in integer nanoseconds (exact: 50 000 000 ns is 20 Hz)."""
    d = np.diff(np.asarray(ns, dtype=np.int64))
    return float(1e9 / np.median(d)) if len(d) else 1.0


def _offset_stats(offsets) -> dict:
    o = np.asarray(offsets, dtype=float) / 1e9
    return {"median": float(np.median(o)), "min": float(o.min()), "max": float(o.max())} if len(o) else {}


def _poses_for(topic, pose_topics, series, tree, base: str, chain_parent: str, path: Path, what: str):
    """``(ns (int64), T_parent_base, parent frame)`` of a pose topic, expressed for the vehicle frame ``base``."""
    if pose_topics[topic] == TF_MESSAGE:
        got = tree.series(chain_parent, base)
        if got is None:
            raise DataError(path, f"{topic}: no tf chain {chain_parent!r} -> {base!r} with a moving transform "
                                  f"({what}); frames seen: "
                              + ", ".join(f"{p}->{c}" for c, p in sorted(tree.parent.items())))
        return got[0], got[1], chain_parent
    s = series[topic]
    if not s.ns:
        raise DataError(path, f"{topic}: no usable {what} message")
    P = np.asarray(s.poses)
    child = (s.child or "").lstrip("/")
    if child and child != base:
        T_child_base = tree.static_transform(child, base)
        if T_child_base is None:
            raise DataError(path, f"{topic}: poses are of frame {child!r}, not the vehicle frame {base!r}, and "
                                  f"/tf_static has no transform between them")
        P = P @ T_child_base
    return np.asarray(s.ns, dtype=np.int64), P, (s.parent or "").lstrip("/")


def load_rosbag(bag, config: dict | None = None, progress: bool = False):
    """Read a camera, its calibration and the pose topics of a ROS bag into a :class:`SurveyRun` (no writing).

    Returns ``(run, images)``: ``images(transform=None)`` yields each frame's encoded bytes in frame order
    (a second pass over the image topic). See the module docstring for what becomes what.
    """
    conf = merge_settings(default_config, config, "rosbag import")
    conf["_progress"] = progress
    paths = bag_paths(bag)
    path = paths[0]
    if conf["odom_topic"] is None and conf["gt_topic"] is None:
        raise ValueError("give --odom-topic, --gt-topic or both (a survey run needs odometry, and "
                         "build-map needs INS poses)")
    frames, info, series, tree, img_offsets, skipped_img, pose_topics = _scan(paths, conf)
    if not frames.stamps:
        raise DataError(path, f"{conf['image_topic']}: no usable image (all {len(frames.corrupt)} corrupt)")

    # camera
    rect = conf["rectified"]
    if rect is None:  # image_transport names rectified streams image_rect, image_rect_color (.../compressed)
        rect = any(part.startswith("image_rect") for part in conf["image_topic"].split("/"))
    if conf["intrinsics"] is not None:
        camera, intr_source = _intrinsics(conf["intrinsics"], frames.size), "given (--intrinsics)"
    elif info is not None:
        camera = _camera_from_info(info, path, conf["camera_info_topic"], bool(rect))
        intr_source = f"{conf['camera_info_topic']} ({'P, rectified' if rect else 'K and D'})"
    elif conf["camera_info_topic"]:
        raise DataError(path, f"{conf['camera_info_topic']}: no CameraInfo message")
    else:
        raise ValueError("give --camera-info-topic or --intrinsics: the camera's calibration")
    if camera.size != frames.size:
        raise DataError(path, f"{conf['image_topic']}: images are {frames.size[0]}x{frames.size[1]} but the "
                              f"calibration says {camera.width}x{camera.height}")

    # vehicle frame and extrinsic
    base = conf["base_frame"]
    if base is None:
        odo = conf["odom_topic"]
        child = series[odo].child if odo in series else None
        base = (child or "base_link").lstrip("/")
    if conf["extrinsic"] is not None:
        T_vc = np.asarray(conf["extrinsic"], dtype=float).reshape(4, 4)
        ext_source = "given (--extrinsic)"
    else:
        T_vc = tree.static_transform(base, frames.frame_id)
        if T_vc is None:
            raise DataError(path, f"no /tf_static transform {base!r} -> {frames.frame_id!r} (the images' frame_id): "
                                  "pass --extrinsic X,Y,Z,QX,QY,QZ,QW (the camera's pose on the vehicle) or "
                                  "--base-frame")
        ext_source = f"/tf_static {base} -> {frames.frame_id}"

    # poses
    gt_t = gt_P = truth_t = truth_P = None
    note, meta_frames = {}, {"vehicle_frame": base, "camera_frame": frames.frame_id}
    if conf["gt_topic"] is not None:
        gt_ns, gt_P, parent = _poses_for(conf["gt_topic"], pose_topics, series, tree, base, conf["gt_frame"], path,
                                         "ground truth")
        gt_t = ticks_to_seconds(gt_ns)
        meta_frames["groundtruth_frame"] = parent
    if conf["truth_topic"] is not None:
        ns, truth_P, _ = _poses_for(conf["truth_topic"], pose_topics, series, tree, base, conf["gt_frame"], path,
                                    "truth")
        truth_t = ticks_to_seconds(ns)
    noise = float(conf["odometry_noise"])
    if conf["odom_topic"] is not None:
        odo_ns, odo_P, parent = _poses_for(conf["odom_topic"], pose_topics, series, tree, base, conf["odom_frame"],
                                           path, "odometry")
        odo_t = ticks_to_seconds(odo_ns)
        meta_frames["odometry_frame"] = parent
        odo_source = "rosbag:" + conf["odom_topic"]
        if noise:
            odo_P = odometry_with_noise(odo_P, noise, int(conf["odometry_seed"]))
            note = odometry_note(f"{conf['odom_topic']} in the bag", conf)
            odo_source += "+noise"
        else:
            note = {"odometry": f"{conf['odom_topic']} in the bag ({pose_topics[conf['odom_topic']]})"}
    else:
        odo_P, odo_source, note = odometry_from_groundtruth(gt_P, conf, f"the ground truth topic {conf['gt_topic']}")
        odo_t, odo_ns = gt_t, gt_ns

    frame_times = ticks_to_seconds(frames.stamps)
    # per role, not per topic: topic names are not TOML keys
    roles = {conf[k]: r for k, r in (("truth_topic", "truth"), ("gt_topic", "groundtruth"), ("odom_topic", "odometry"))
             if conf[k] is not None}
    offsets = {"images": _offset_stats(img_offsets)}
    for t, s in series.items():
        offsets[roles[t]] = _offset_stats(s.record_minus_header)
    skipped = {}
    if skipped_img:
        skipped["images_non_monotonic_stamp"] = skipped_img
    if frames.corrupt:
        skipped["images_corrupt"] = len(frames.corrupt)
    for t, s in series.items():
        if s.non_monotonic:
            skipped[f"{roles[t]}_non_monotonic_stamp"] = s.non_monotonic
    if tree.skipped:
        skipped["tf_non_monotonic_stamp"] = tree.skipped
    for role, st in offsets.items():
        if conf["stamps"] == "header" and st and max(abs(st["min"]), abs(st["max"])) > 0.05:
            log.warning("%s: %s: times are header stamps; the record times differ by %.3f s (median; %.3f to "
                        "%.3f s)", path, role, st["median"], st["min"], st["max"])
    for what, n in skipped.items():
        log.warning("%s: %d message(s) left out (%s)", path, n, what.replace("_", " "))
    for k, stamp, reason in frames.corrupt[:5]:
        log.warning("%s: %s message %d (stamp %.9f) left out: %s", path, conf["image_topic"], k, stamp, reason)

    files = [f"images/{i:06d}{ext}" for i, ext in enumerate(frames.exts)]
    metadata = {
        "source": "rosbag", "source_path": [str(p.resolve()) for p in paths], "bag_format": bag_format(paths),
        "topics": {k: conf[k] for k in ("image_topic", "camera_info_topic", "odom_topic", "gt_topic", "truth_topic")
                   if conf[k] is not None},
        "stamps": "header stamps" if conf["stamps"] == "header" else "record times (--stamps record)",
        "record_minus_header_s": {t: v for t, v in offsets.items() if v},
        "image_encodings": sorted(frames.encodings), "intrinsics": intr_source, "extrinsic": ext_source,
        **meta_frames, **note, "skipped": skipped,
        "corrupt_messages": [[k, stamp] for k, stamp, _ in frames.corrupt],
        "gaps": find_gaps(frame_times, conf["gap_factor"]),
        "odometry_gaps": find_gaps(odo_t, conf["gap_factor"]),
    }
    if gt_t is not None:
        metadata["groundtruth_gaps"] = find_gaps(gt_t, conf["gap_factor"])
    rates = {"camera_hz": _rate(frames.stamps), "odometry_hz": _rate(odo_ns)}
    if gt_t is not None:
        rates["ins_hz"] = _rate(gt_ns)
    name = conf["name"] or (paths[0].stem if paths[0].is_file() else paths[0].name)
    run = SurveyRun(
        name=name, conditions=list(conf["conditions"]), camera=camera, T_vehicle_camera=T_vc, rates=rates,
        frame_times=frame_times, frame_files=files, odometry_times=odo_t, odometry_poses=odo_P,
        odometry_source=odo_source, groundtruth_times=gt_t, groundtruth_poses=gt_P, truth_times=truth_t,
        truth_poses=truth_P, metadata=metadata,
    )
    keep = dict(zip(frames.index, frames.exts))

    def images(transform=None):
        """Each kept frame's encoded bytes, in frame order: raw images as PNG, compressed ones as they are."""
        import cv2

        from ..images import decode_image

        topic = conf["image_topic"]
        with _reader(paths) as r:
            conns = [c for c in r.connections if c.topic == topic]
            i = 0
            for k, (c, _, raw) in enumerate(r.messages(connections=conns)):
                if k not in keep:
                    continue
                msg = _deserialize(r, raw, c.msgtype, path, topic, k)
                if c.msgtype == COMPRESSED_IMAGE and transform is None:
                    yield bytes(msg.data)
                else:
                    img = raw_image(msg) if c.msgtype == IMAGE else decode_image(bytes(msg.data), path)
                    if transform is not None:
                        img = transform(i, img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
                    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if keep[k] == ".jpg" else []
                    ok, enc = cv2.imencode(keep[k], img, params)
                    if not ok:
                        raise OSError(f"{path}: {topic} message {k}: could not encode the image")
                    yield enc.tobytes()
                i += 1
            if i != len(keep):
                raise DataError(path, f"{topic}: {len(keep)} images on the first read, {i} on the second "
                                      "(the bag changed while importing?)")

    return run, images


def import_rosbag(bag, out, config: dict | None = None, overwrite: bool = False, progress: bool = True,
                  photometric: str | dict | None = None) -> Path:
    """Import a camera and its poses from a ROS bag as the survey run ``out``, written atomically
    (:func:`scenesig.surveys.run.write_run`: a failed import leaves nothing and keeps an old run)."""
    from tqdm import tqdm

    from ..run import write_run

    run, images = load_rosbag(bag, config, progress)
    transform = None
    if photometric is not None:
        from .photometric import photometric_transform

        transform, desc = photometric_transform(photometric)
        run.metadata["photometric_transform"] = desc
    stream = tqdm(images(transform), total=len(run), desc=f"import {run.name}", unit="frame", disable=not progress)
    return write_run(run, out, images=stream, overwrite=overwrite)


# --------------------------------------------------------------------------------------- writing bags
def _typestore(fmt: str):
    """rosbags' message types for ROS 1 Noetic or ROS 2 Humble; Noetic's set lacks tf2_msgs/TFMessage (/tf),
    which is registered from its ROS 1 definition."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    if TF_MESSAGE not in ts.types:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    return ts


@contextmanager
def _bag_writer(out, fmt: str, overwrite: bool):
    """``(add(topic, type) -> connection, write(connection, ns, message))`` into the bag ``out``, written
    atomically: a ROS 1 file or bare ``.mcap`` through a temporary file, a ROS 2 folder through a
    temporary folder, renamed into place when complete."""
    require_rosbags(out)
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    out = Path(out)
    if fmt not in FORMATS:
        raise ValueError(f"bag format must be one of {', '.join(FORMATS)}, not {fmt!r}")
    if fmt == "ros1" and out.suffix != ".bag":
        raise ValueError(f"{out}: a ROS 1 bag's name must end in .bag")
    if fmt != "ros1" and out.suffix == ".bag":
        raise ValueError(f"{out}: a .bag name is for ROS 1 (--format ros1)")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: bag already exists (pass overwrite=True to replace it)")
    ts = _typestore(fmt)
    ser = ts.serialize_ros1 if fmt == "ros1" else ts.serialize_cdr

    def session(writer):
        conns = {}

        def add(topic, msgtype):
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            return conns[topic]

        def write(topic, ns, msg):
            writer.write(conns[topic], int(ns), ser(msg, msg.__msgtype__))

        return ts, add, write

    if fmt == "ros1":
        with atomic_path(out) as tmp:
            with Writer1(tmp) as w:
                yield session(w)
        return
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    if fmt == "mcap" and out.suffix == ".mcap":  # a bare MCAP file (self-describing: Foxglove opens it)
        if out.is_dir():
            raise ValueError(f"{out}: is a folder; a bare .mcap output must be a file")
        with atomic_path(out) as tmp:
            inner = tmp.with_name(tmp.name + ".d")
            shutil.rmtree(inner, ignore_errors=True)
            try:
                with Writer2(inner, version=9, storage_plugin=plugin) as w:
                    yield session(w)
                os.replace(next(inner.glob("*.mcap")), tmp)
            finally:
                shutil.rmtree(inner, ignore_errors=True)
        return
    with atomic_folder(out, overwrite, "ROS 2 bag") as tmp:
        inner = tmp / out.name
        with Writer2(inner, version=9, storage_plugin=plugin) as w:
            yield session(w)
        for f in inner.iterdir():
            os.replace(f, tmp / f.name)
        inner.rmdir()


def _header(ts, ns: int, frame_id: str):
    T = ts.types
    kw = {"stamp": T["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000)),
          "frame_id": frame_id}
    if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__:
        kw["seq"] = 0
    return T["std_msgs/msg/Header"](**kw)


def _geometry(ts, T4: np.ndarray, kind: str):
    T = ts.types
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose_to_xyzquat(T4))
    q = T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    if kind == "pose":
        return T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z), orientation=q)
    return T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=q)


def _odometry_msg(ts, ns, frame_id, child, T4, cov=None):
    T = ts.types
    c = np.zeros(36) if cov is None else np.asarray(cov, dtype=float).reshape(36)
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T[ODOMETRY](
        header=_header(ts, ns, frame_id), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=_geometry(ts, T4, "pose"), covariance=c),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                         covariance=np.zeros(36)))


def _tf_msg(ts, ns, parent, child, T4):
    T = ts.types
    st = T[TRANSFORM_STAMPED](header=_header(ts, ns, parent), child_frame_id=child,
                              transform=_geometry(ts, T4, "transform"))
    return T[TF_MESSAGE](transforms=[st])


def _camera_info_msg(ts, ns, frame_id, cam: Camera):
    T = ts.types
    cls = T[CAMERA_INFO]
    d = list(cam.distortion) + [0.0] * (5 - len(cam.distortion)) if cam.distortion else [0.0] * 5
    K = cam.K.ravel()
    P = np.hstack([cam.K, np.zeros((3, 1))]).ravel()
    arrays = {"d": np.asarray(d[:5], float), "k": K, "r": np.eye(3).ravel(), "p": P}
    if "K" in cls.__dataclass_fields__:
        arrays = {k.upper(): v for k, v in arrays.items()}
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return cls(header=_header(ts, ns, frame_id), height=cam.height, width=cam.width, distortion_model="plumb_bob",
               binning_x=0, binning_y=0, roi=roi, **arrays)


def write_run_bag(run: SurveyRun, out, fmt: str = "ros2", images: str = "raw", odometry_as: str = "odometry",
                  overwrite: bool = False, progress: bool = True, camera_frame: str = "camera_optical",
                  base_frame: str = "base_link") -> Path:
    """Write a survey run (read from its folder) as a ROS bag ``out``, atomically.

    Topics: ``/camera/image_raw`` (``sensor_msgs/Image`` bgr8, ``images="raw"``) or
    ``/camera/image_raw/compressed`` (``images="jpeg"`` / ``"png"``: the run's files as they are where
    they are already of that kind); ``/camera/camera_info``; ``/odom`` (``nav_msgs/Odometry`` ``odom`` ->
    ``base_frame``) or, with ``odometry_as="tf"``, the same poses on ``/tf``; ``/ins`` (``groundtruth.tum``,
    ``map`` -> ``base_frame``); ``/truth`` (``truth.tum``, ``world`` -> ``base_frame``); ``/tf_static``
    (``base_frame`` -> ``camera_frame``: the extrinsic). Header stamps are the run's times (exact to the
    nanosecond) and so are record times.
    """
    from tqdm import tqdm

    if images not in ("raw", "jpeg", "png"):
        raise ValueError(f"images must be raw, jpeg or png, not {images!r}")
    if odometry_as not in ("odometry", "tf"):
        raise ValueError(f"odometry_as must be 'odometry' or 'tf', not {odometry_as!r}")
    if run.root is None:
        raise ValueError("the run has no folder to take its images from")
    import cv2

    from ..images import image_kind

    out = Path(out)
    with _bag_writer(out, fmt, overwrite) as (ts, add, write):
        T = ts.types
        img_topic = "/camera/image_raw" if images == "raw" else "/camera/image_raw/compressed"
        add(img_topic, IMAGE if images == "raw" else COMPRESSED_IMAGE)
        add("/camera/camera_info", CAMERA_INFO)
        add("/tf_static", TF_MESSAGE)
        add("/odom" if odometry_as == "odometry" else "/tf", ODOMETRY if odometry_as == "odometry" else TF_MESSAGE)
        if run.groundtruth_times is not None:
            add("/ins", ODOMETRY)
        if run.truth_times is not None:
            add("/truth", ODOMETRY)
        t0 = min(_ns(run.frame_times[0]), _ns(run.odometry_times[0]))
        write("/tf_static", t0, _tf_msg(ts, t0, base_frame, camera_frame, run.T_vehicle_camera))
        # the poses and the images, each message at its own stamp (a bag is ordered by record time)
        events = [(_ns(t), 1, "/odom", i) for i, t in enumerate(run.odometry_times)]
        if run.groundtruth_times is not None:
            events += [(_ns(t), 2, "/ins", i) for i, t in enumerate(run.groundtruth_times)]
        if run.truth_times is not None:
            events += [(_ns(t), 3, "/truth", i) for i, t in enumerate(run.truth_times)]
        events += [(_ns(t), 0, img_topic, i) for i, t in enumerate(run.frame_times)]
        events.sort()
        bar = tqdm(total=len(run), desc=f"bag {run.name}", unit="frame", disable=not progress)
        for ns, _, topic, i in events:
            if topic == img_topic:
                hdr = _header(ts, ns, camera_frame)
                if images == "raw":
                    img = run.image(i)
                    msg = T[IMAGE](header=hdr, height=img.shape[0], width=img.shape[1], encoding="bgr8",
                                   is_bigendian=0, step=img.shape[1] * 3, data=img.reshape(-1))
                else:
                    data = (run.root / run.frame_files[i]).read_bytes()
                    if image_kind(data) != images:
                        ok, enc = cv2.imencode(".jpg" if images == "jpeg" else ".png", run.image(i),
                                               [cv2.IMWRITE_JPEG_QUALITY, 95] if images == "jpeg" else [])
                        data = enc.tobytes()
                    msg = T[COMPRESSED_IMAGE](header=hdr, format=images, data=np.frombuffer(data, np.uint8))
                write(topic, ns, msg)
                write("/camera/camera_info", ns, _camera_info_msg(ts, ns, camera_frame, run.camera))
                bar.update()
            elif topic == "/odom":
                P = run.odometry_poses[i]
                if odometry_as == "odometry":
                    write("/odom", ns, _odometry_msg(ts, ns, "odom", base_frame, P))
                else:
                    write("/tf", ns, _tf_msg(ts, ns, "odom", base_frame, P))
            elif topic == "/ins":
                write("/ins", ns, _odometry_msg(ts, ns, "map", base_frame, run.groundtruth_poses[i]))
            else:
                write("/truth", ns, _odometry_msg(ts, ns, "world", base_frame, run.truth_poses[i]))
        bar.close()
    return out


# --------------------------------------------------------------------------------------- localisations out
_AXES = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5, "heading": 5, "rx": 3, "ry": 4, "rz": 5}
_BODY = {"longitudinal": 0, "lateral": 1, "vertical": 2}
_UNIT = r"(?:_(?:m|rad|m2|rad2))?"
_COV_COLUMN = re.compile(rf"^(var|cov|std|sigma)_([a-z]+?){_UNIT}(?:_([a-z]+?){_UNIT})?$")


def read_pose_covariances(path, times: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The localiser's per-frame pose covariances (``covariances.csv`` beside ``trajectory.tum``) as ROS
    ``pose.covariance`` matrices: (N, 6, 6) in the order x, y, z, roll, pitch, yaw of the map frame, and a
    (N,) mask of the trajectory's poses that have one.

    The file is CSV with a header: a ``time`` (or ``timestamp``) column matching ``trajectory.tum``'s times
    (to 1 µs), then columns named ``AB`` (two axis names run together, the localiser's ``xx, xy, xyaw, yy,
    yyaw, yawyaw``: the upper triangle of the planar covariance in the map frame), or ``var_A``, ``std_A`` /
    ``sigma_A`` (squared) or ``cov_A_B``, each with an
    optional unit suffix (``_m``, ``_rad``, ``_m2``, ``_rad2``), where A, B are map-frame axes (``x``, ``y``,
    ``z``, ``roll``, ``pitch``, ``yaw`` / ``heading``) or vehicle axes (``longitudinal``, ``lateral``,
    ``vertical``), which are rotated into the map frame by the pose's rotation. Other columns (e.g. 95 %
    bounds) are ignored; a file with no covariance column is an error naming it.
    """
    from .common import numbers, read_rows

    path = Path(path)
    rows = read_rows(path, 2)
    header = [h.lower() for h in rows[0][1]]
    if header[0] not in ("time", "timestamp", "t"):
        raise DataError(path, f"first column must be 'time', found {rows[0][1][0]!r}", rows[0][0])
    cols = []
    for j, h in enumerate(header[1:], start=1):
        m = _COV_COLUMN.match(h)
        pair = [(h[:i], h[i:]) for i in range(1, len(h)) if h[:i] in _AXES and h[i:] in _AXES]
        if pair:  # the localiser's own layout: "xx", "xy", "xyaw", "yy", "yyaw", "yawyaw" (map-frame axes)
            kind, (a, b) = "cov", pair[0]
        elif m:
            kind, a, b = m.group(1), m.group(2), m.group(3) or m.group(2)
        else:
            continue
        if (a not in _AXES and a not in _BODY) or (b not in _AXES and b not in _BODY):
            continue
        if (a in _BODY) != (b in _BODY):
            raise DataError(path, f"column {h!r} mixes vehicle and map axes", rows[0][0])
        cols.append((j, kind, a, b))
    if not cols:
        raise DataError(path, "no covariance column (var_x, std_lateral, cov_x_y, ... see docs/rosbag.md) in "
                              f"{', '.join(rows[0][1])}", rows[0][0])
    N = len(times)
    out = np.zeros((N, 6, 6))
    have = np.zeros(N, bool)
    for n, f in rows[1:]:
        if len(f) != len(header):
            raise DataError(path, f"expected {len(header)} columns, found {len(f)}", n)
        if f[0] == "" or any(f[j] == "" for j, *_ in cols):
            continue  # a frame without a stated uncertainty
        vals = numbers(path, n, [f[0]] + [f[j] for j, *_ in cols])
        i = int(np.searchsorted(times, vals[0] - 1e-6))
        if i >= N or abs(times[i] - vals[0]) > 1e-6:
            continue  # no pose at that time (not localised): nothing to attach it to
        C, B = np.zeros((6, 6)), np.zeros((3, 3))
        for (j, kind, a, b), v in zip(cols, vals[1:]):
            if kind in ("std", "sigma"):
                v = v * v
            if kind in ("var", "std", "sigma") and v < 0:
                raise DataError(path, f"negative variance in {header[j]!r}", n)
            if a in _BODY:
                B[_BODY[a], _BODY[b]] = B[_BODY[b], _BODY[a]] = v
            else:
                C[_AXES[a], _AXES[b]] = C[_AXES[b], _AXES[a]] = v
        if B.any():
            R = poses[i][:3, :3]
            C[:3, :3] += R @ B @ R.T
        out[i], have[i] = C, True
    return out, have


def export_trajectory_bag(times, poses, out, fmt: str = "ros2", covariances=None, topic: str = "/scenesig/odometry",
                          frame_id: str = "map", child_frame_id: str = "scenesig/base_link",
                          overwrite: bool = False) -> Path:
    """Write a localised trajectory as a bag: ``nav_msgs/Odometry`` on ``topic`` (``frame_id`` ->
    ``child_frame_id``, pose covariance from ``covariances`` (N,6,6) where given, else zeros: unknown) and
    the same transforms on ``/tf``. Header and record stamps are the frame times, exact to the nanosecond."""
    times = np.asarray(times, dtype=float)
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    if len(times) != len(poses):
        raise ValueError(f"{len(times)} times but {len(poses)} poses")
    out = Path(out)
    with _bag_writer(out, fmt, overwrite) as (ts, add, write):
        add(topic, ODOMETRY)
        add("/tf", TF_MESSAGE)
        for i, (t, P) in enumerate(zip(times, poses)):
            ns = _ns(t)
            cov = None if covariances is None else covariances[i]
            write(topic, ns, _odometry_msg(ts, ns, frame_id, child_frame_id, P, cov))
            write("/tf", ns, _tf_msg(ts, ns, frame_id, child_frame_id, P))
    return out


def read_bag_poses(bag, topic: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(times (s), poses T_parent_child, covariances (N,6,6) or None)`` of a pose topic of a bag, by header
    stamp -- to check an exported bag against its ``trajectory.tum``."""
    paths = bag_paths(bag)
    with _reader(paths) as r:
        conns = [c for c in r.connections if c.topic == topic]
        if not conns:
            raise DataError(paths[0], f"no topic {topic!r} in this bag")
        ns, P, C = [], [], []
        for k, (c, _, raw) in enumerate(r.messages(connections=conns)):
            msg = _deserialize(r, raw, c.msgtype, paths[0], topic, k)
            for hdr, _, _, T in _poses_of(msg, c.msgtype, paths[0], topic, k):
                ns.append(_stamp_ns_of(hdr))
                P.append(T)
            if c.msgtype in (ODOMETRY, POSE_COV_STAMPED):
                C.append(np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6))
    return ticks_to_seconds(ns), np.asarray(P).reshape(-1, 4, 4), (np.asarray(C) if C else None)
