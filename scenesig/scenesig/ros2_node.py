"""A ROS 2 localisation node over :class:`scenesig.Session`: ``scenesig ros2 node --map MAP``.

It localises a robot against a scenesig map as AMCL localises against an occupancy grid, with the frames of
REP 105 (``map``, ``odom``, ``base_link``):

Subscribes
    an image topic (``sensor_msgs/Image`` -- mono8, bgr8, rgb8, ... -- or ``sensor_msgs/CompressedImage``
    JPEG/PNG), its ``sensor_msgs/CameraInfo``, the robot's odometry (``nav_msgs/Odometry``, ``odom`` ->
    ``base_link``), ``/tf_static`` (the camera's pose on the robot, unless given) and, optionally, a GNSS
    prior: ``sensor_msgs/NavSatFix`` (with a datum: latitude, longitude, altitude of the map's origin; the
    heading is taken along the path between fixes) or a pose topic (``nav_msgs/Odometry``,
    ``geometry_msgs/PoseStamped`` or ``PoseWithCovarianceStamped`` in the map frame, e.g. an INS).  A GNSS
    prior starts the localiser and resets it after a failure (the paper's protocol, McManus et al. 2015
    §4.3); it is never used to localise.  Without one the session localises itself globally.
Publishes
    ``nav_msgs/Odometry`` in ``map`` (child ``base_link``) at every processed image once the session has a
    world pose -- the estimate at the image's time, as ``scenesig localise`` writes it per frame -- with
    its covariance (x, y, z, roll, pitch, yaw in the map frame: the session's vehicle-frame covariance
    rotated into it); the ``map -> odom`` transform on ``/tf`` (AMCL's convention: ``T_map_odom =
    T_map_base(t) · T_odom_base(t)⁻¹``, re-sent with every odometry message so that it stays fresh); and a
    ``diagnostic_msgs/DiagnosticArray`` whose status carries the session's state (``tracking`` OK;
    ``searching`` WARN; ``lost``, ``alert`` -- the integrity monitor refuses the map's fixes -- ERROR) with
    the place, inliers, integrity and 95 % lateral bound.

The node is built for testing without ROS: :class:`LocalisationNode` is plain Python.  Its callbacks are
methods taking message objects (rclpy's, or the ``rosbags`` dataclasses a bag reader gives) and it
publishes through an injected ``publish(topic, message)`` with message classes from an injected
``types(name)`` (rclpy's generated classes, or a ``rosbags`` typestore's).  Only :func:`run` imports
``rclpy``; where ROS 2 is absent the command exits 2 naming it.
"""
from __future__ import annotations

import argparse
import math
from collections import deque
from decimal import Decimal
from typing import Callable

import numpy as np

from scenesig.surveys.extras import MissingExtraError
from scenesig.surveys.geometry import Camera, interpolate_poses, invert, pose_to_xyzquat, xyzquat_to_pose

__all__ = ["LocalisationNode", "ros_covariance", "stamp_seconds", "DEFAULT_TOPICS", "RclpyMissingError", "run"]

#: Output topics (AMCL and robot_localization publish on names of this kind).
DEFAULT_TOPICS = {"odometry": "/scenesig/odometry", "tf": "/tf", "diagnostics": "/diagnostics"}

_LEVEL = {"tracking": "OK", "searching": "WARN", "lost": "ERROR", "alert": "ERROR"}
_WGS84_A, _WGS84_E2 = 6378137.0, 6.69437999014e-3


def stamp_seconds(stamp) -> float:
    """A ``builtin_interfaces/Time`` as float seconds, correctly rounded (the run files' 9-decimal times)."""
    return float(Decimal(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)).scaleb(-9))


def _ns(t: float) -> int:
    return int(f"{t:.9f}".replace(".", ""))


def ros_covariance(T_world_vehicle: np.ndarray, C: np.ndarray) -> np.ndarray:
    """A session covariance -- 6x6, vehicle frame, GTSAM order (rx, ry, rz, tx, ty, tz) -- as ROS's
    ``pose.covariance``: (x, y, z, roll, pitch, yaw) in the parent (map) frame.  The perturbation
    ``T exp(ξ)`` in the vehicle frame is ``R ξ`` in the map frame, for rotation and translation alike."""
    perm = [3, 4, 5, 0, 1, 2]
    R = np.asarray(T_world_vehicle, float)[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = J[3:, 3:] = R
    Cp = np.asarray(C, float)[np.ix_(perm, perm)]
    out = J @ Cp @ J.T
    return 0.5 * (out + out.T)


def _geodetic_to_ecef(lat, lon, alt) -> np.ndarray:
    la, lo = math.radians(lat), math.radians(lon)
    n = _WGS84_A / math.sqrt(1.0 - _WGS84_E2 * math.sin(la) ** 2)
    return np.array([(n + alt) * math.cos(la) * math.cos(lo), (n + alt) * math.cos(la) * math.sin(lo),
                     (n * (1.0 - _WGS84_E2) + alt) * math.sin(la)])


def _enu(datum, lat, lon, alt) -> np.ndarray:
    """Local east-north-up metres of a WGS-84 position about ``datum`` (lat, lon, alt)."""
    la, lo = math.radians(datum[0]), math.radians(datum[1])
    d = _geodetic_to_ecef(lat, lon, alt) - _geodetic_to_ecef(*datum)
    R = np.array([[-math.sin(lo), math.cos(lo), 0.0],
                  [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                  [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])
    return R @ d


def _pose_of(p) -> np.ndarray:
    return xyzquat_to_pose([p.position.x, p.position.y, p.position.z,
                            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])


class LocalisationNode:
    """The node's logic, without ROS (module docstring).

    Parameters
    ----------
    make_session : ``f(camera, T_vehicle_camera) -> session`` -- a :class:`scenesig.Session` (or any object
        with its ``add_odometry``, ``add_image``, ``add_gnss``, ``pose``, ``state``, ``last_frame``), made when
        the camera's calibration and extrinsic are known.
    publish : ``publish(topic, message)``.
    types : ``types("nav_msgs/msg/Odometry") -> message class``.
    camera : the camera, instead of waiting for CameraInfo.
    T_vehicle_camera : (4,4) the camera on the robot, instead of ``/tf_static``.
    map_frame, odom_frame, base_frame : REP 105 frame names.
    topics : output topic names (:data:`DEFAULT_TOPICS` by default).
    datum : (lat, lon, alt) of the map's origin, for NavSatFix.
    rectified : CameraInfo's P (rectified images) rather than K and D.

    Attributes
    ----------
    session : the session, once made.
    frames_processed : images the session localised or searched with.
    """

    def __init__(self, make_session: Callable, publish: Callable, types: Callable, camera: Camera | None = None,
                 T_vehicle_camera=None, map_frame: str = "map", odom_frame: str = "odom",
                 base_frame: str = "base_link", topics: dict | None = None, datum=None, rectified: bool = False,
                 history: int = 4000):
        self._make, self._publish, self._types = make_session, publish, types
        self.camera = camera
        self.T_vehicle_camera = None if T_vehicle_camera is None else np.asarray(T_vehicle_camera, float)
        self.map_frame, self.odom_frame, self.base_frame = map_frame, odom_frame, base_frame
        self.topics = {**DEFAULT_TOPICS, **(topics or {})}
        self.datum = None if datum is None else tuple(float(v) for v in datum)
        self.rectified = bool(rectified)
        self.session = None
        self.frames_processed = 0
        self._odom_t: deque = deque(maxlen=history)      # T_odom_base history, for map -> odom at past times
        self._odom_T: deque = deque(maxlen=history)
        self._tf_static: dict = {}                        # child -> (parent, T_parent_child)
        self._camera_frame: str | None = None
        self._last_report = None
        self._T_map_odom: np.ndarray | None = None
        self._gnss_pending: list = []                     # GNSS poses before the session exists
        self._navsat_prev: np.ndarray | None = None

    # ------------------------------------------------------------------------------ inputs
    def on_camera_info(self, msg) -> None:
        """``sensor_msgs/CameraInfo``: the calibration (the first one is kept)."""
        if self.camera is None:
            from pathlib import Path

            from scenesig.surveys.importers.rosbag import camera_from_info

            self.camera = camera_from_info(msg, Path("camera_info"), "camera_info", self.rectified)
        if self._camera_frame is None and msg.header.frame_id:
            self._camera_frame = msg.header.frame_id

    def on_tf_static(self, msg) -> None:
        """``tf2_msgs/TFMessage`` on ``/tf_static``: the camera's pose on the robot, through the chain."""
        for ts in msg.transforms:
            tr = ts.transform
            T = xyzquat_to_pose([tr.translation.x, tr.translation.y, tr.translation.z,
                                 tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w])
            self._tf_static[ts.child_frame_id] = (ts.header.frame_id, T)

    def _extrinsic(self) -> np.ndarray | None:
        if self.T_vehicle_camera is not None or self._camera_frame is None:
            return self.T_vehicle_camera
        T, frame, seen = np.eye(4), self._camera_frame, set()
        while frame != self.base_frame:
            if frame not in self._tf_static or frame in seen:
                return None
            seen.add(frame)
            parent, T_pc = self._tf_static[frame]
            T, frame = T_pc @ T, parent
        return T

    def _ensure_session(self) -> bool:
        if self.session is not None:
            return True
        T_vc = self._extrinsic()
        if self.camera is None or T_vc is None:
            return False
        self.T_vehicle_camera = T_vc
        self.session = self._make(self.camera, T_vc)
        for t, T in self._gnss_pending:
            self.session.add_gnss(t, T)
        self._gnss_pending.clear()
        return True

    def on_odometry(self, msg) -> None:
        """``nav_msgs/Odometry`` (``odom`` -> ``base_link``): the increment since the previous message."""
        t = stamp_seconds(msg.header.stamp)
        T = _pose_of(msg.pose.pose)
        if self._odom_t and t <= self._odom_t[-1]:
            return                       # a repeated or older stamp: the session takes samples in time order
        prev = self._odom_T[-1] if self._odom_T else None
        self._odom_t.append(t)
        self._odom_T.append(T)
        if not self._ensure_session():
            # no session yet (no calibration or extrinsic): it starts with the first sample it sees
            self._odom_t.clear()
            self._odom_T.clear()
            return
        self.session.add_odometry(t, np.eye(4) if prev is None else invert(prev) @ T)
        self._after_step()
        if self._T_map_odom is not None:
            self._publish_tf(t, self._T_map_odom)

    def on_image(self, msg) -> None:
        """``sensor_msgs/Image`` (raw)."""
        from scenesig.surveys.importers.rosbag import raw_image

        self._image(msg, raw_image(msg))

    def on_compressed_image(self, msg) -> None:
        """``sensor_msgs/CompressedImage`` (JPEG or PNG), decoded strictly (grey when the method wants grey)."""
        from scenesig.surveys.images import decode_image

        if self._camera_frame is None and msg.header.frame_id:
            self._camera_frame = msg.header.frame_id
        if not self._ensure_session():
            return
        color = bool(getattr(getattr(self.session, "method", None), "color", True))
        data = bytes(np.asarray(msg.data, dtype=np.uint8))
        self._image(msg, decode_image(data, f"compressed image at {stamp_seconds(msg.header.stamp):.9f}",
                                      gray=not color))

    def _image(self, msg, img: np.ndarray) -> None:
        if self._camera_frame is None and msg.header.frame_id:
            self._camera_frame = msg.header.frame_id
        if not self._ensure_session():
            return
        self.session.add_image(stamp_seconds(msg.header.stamp), img)
        self._after_step()

    def on_gnss_pose(self, msg) -> None:
        """An INS/GNSS pose in the map frame (``nav_msgs/Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped``)."""
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        self._gnss(stamp_seconds(msg.header.stamp), _pose_of(pose))

    def on_navsatfix(self, msg) -> None:
        """``sensor_msgs/NavSatFix``: a position about the datum; the heading is along the path since the
        previous fix at least 1 m away (no pose until the robot has moved)."""
        if self.datum is None:
            raise ValueError("NavSatFix needs the datum of the map (latitude, longitude, altitude of its origin)")
        if int(msg.status.status) < 0 or not all(math.isfinite(v) for v in (msg.latitude, msg.longitude, msg.altitude)):
            return                       # STATUS_NO_FIX
        p = _enu(self.datum, msg.latitude, msg.longitude, msg.altitude)
        if self._navsat_prev is None or np.linalg.norm(p[:2] - self._navsat_prev[:2]) < 1.0:
            self._navsat_prev = p if self._navsat_prev is None else self._navsat_prev
            return
        d = p - self._navsat_prev
        yaw = math.atan2(d[1], d[0])
        self._navsat_prev = p
        T = np.eye(4)
        T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        T[:3, 3] = p
        self._gnss(stamp_seconds(msg.header.stamp), T)

    def _gnss(self, t: float, T: np.ndarray) -> None:
        if self.session is None:
            self._gnss_pending.append((t, T))
        else:
            self.session.add_gnss(t, T)

    def flush(self) -> None:
        """End of the data: the session processes a frame it still holds (and publishes it)."""
        if self.session is not None:
            self.session.flush()
            self._after_step()

    # ------------------------------------------------------------------------------ outputs
    def _odom_base(self, t: float) -> np.ndarray | None:
        if not self._odom_t:
            return None
        return interpolate_poses(np.fromiter(self._odom_t, float), np.stack(self._odom_T), float(t))

    def _after_step(self) -> None:
        """Publish what the latest processed image gave (once per image)."""
        rep = self.session.last_frame
        if rep is None or rep is self._last_report:
            return
        self._last_report = rep
        self.frames_processed += 1
        est = self.session.pose(rep.t)
        if est is not None:
            self._publish_odometry(rep.t, est.pose, est.covariance)
            T_ob = self._odom_base(rep.t)
            if T_ob is not None:
                self._T_map_odom = est.pose @ invert(T_ob)
                self._publish_tf(rep.t, self._T_map_odom)
        self._publish_diagnostics(rep, est)

    def _header(self, t: float, frame: str):
        ns = _ns(t)
        Time, Header = self._types("builtin_interfaces/msg/Time"), self._types("std_msgs/msg/Header")
        return Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame)

    def _pose_msg(self, T: np.ndarray, kind: str):
        x, y, z, qx, qy, qz, qw = (float(v) for v in pose_to_xyzquat(T))
        q = self._types("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw)
        if kind == "pose":
            P = self._types("geometry_msgs/msg/Point")(x=x, y=y, z=z)
            return self._types("geometry_msgs/msg/Pose")(position=P, orientation=q)
        V = self._types("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)
        return self._types("geometry_msgs/msg/Transform")(translation=V, rotation=q)

    def _publish_odometry(self, t: float, T: np.ndarray, C: np.ndarray) -> None:
        ty = self._types
        zero = ty("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        msg = ty("nav_msgs/msg/Odometry")(
            header=self._header(t, self.map_frame), child_frame_id=self.base_frame,
            pose=ty("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose_msg(T, "pose"),
                                                            covariance=ros_covariance(T, C).reshape(36)),
            twist=ty("geometry_msgs/msg/TwistWithCovariance")(
                twist=ty("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=np.zeros(36)))
        self._publish(self.topics["odometry"], msg)

    def _publish_tf(self, t: float, T_map_odom: np.ndarray) -> None:
        ty = self._types
        st = ty("geometry_msgs/msg/TransformStamped")(header=self._header(t, self.map_frame),
                                                      child_frame_id=self.odom_frame,
                                                      transform=self._pose_msg(T_map_odom, "transform"))
        self._publish(self.topics["tf"], ty("tf2_msgs/msg/TFMessage")(transforms=[st]))

    def _publish_diagnostics(self, rep, est) -> None:
        ty = self._types
        Status, KeyValue = ty("diagnostic_msgs/msg/DiagnosticStatus"), ty("diagnostic_msgs/msg/KeyValue")
        state = self.session.state
        fix = getattr(rep, "fix", None)
        nan = est is None
        values = {"state": state, "integrity": fix.integrity if fix is not None else "none",
                  "place": str(int(rep.place)), "inliers": str(int(getattr(rep.measurement, "inliers", 0))),
                  "localised": str(bool(rep.accepted)).lower(),
                  "lateral_bound_95_m": "nan" if nan else f"{est.lateral_bound_95_m:.3f}",
                  "distance_since_localisation_m": "nan" if nan else f"{est.distance_since_localisation:.2f}",
                  "frames_processed": str(self.frames_processed),
                  "frames_dropped": str(int(getattr(self.session, "frames_dropped", 0))),
                  "frames_too_late": str(int(getattr(self.session, "frames_too_late", 0)))}
        status = Status(level=getattr(Status, _LEVEL[state]), name="scenesig: localisation",
                        message=state, hardware_id="scenesig",
                        values=[KeyValue(key=k, value=v) for k, v in values.items()])
        msg = ty("diagnostic_msgs/msg/DiagnosticArray")(header=self._header(rep.t, self.map_frame), status=[status])
        self._publish(self.topics["diagnostics"], msg)


# ---------------------------------------------------------------------------------------- rclpy
class RclpyMissingError(MissingExtraError):
    """ROS 2's ``rclpy`` is not importable: it comes with a ROS 2 install, not from pip (the CLI exits 2)."""

    def __init__(self):
        ImportError.__init__(self, "scenesig ros2 node needs ROS 2's Python client library 'rclpy', which is not "
                                   "importable: it comes with a ROS 2 install, not from pip (e.g. apt install "
                                   "ros-humble-rclpy, then source /opt/ros/humble/setup.bash); the ros extra "
                                   "(pip install \"scenesig[ros]\") brings the rest", name="rclpy")
        self.extra, self.feature = "ros", "scenesig ros2 node"


def _rclpy_types(name: str):
    """The rclpy message class of ``pkg/msg/Name``."""
    import importlib

    pkg, _, cls = name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), cls)


def run(args: argparse.Namespace) -> int:
    """Spin the node (``scenesig ros2 node``): needs ROS 2's ``rclpy`` (exit 2 naming it where absent)."""
    try:
        import rclpy
        from rclpy.qos import qos_profile_sensor_data
    except ImportError:
        raise RclpyMissingError() from None
    import scenesig

    rclpy.init()
    ros = rclpy.create_node("scenesig_localiser")
    pubs: dict = {}

    def publish(topic, msg):
        if topic not in pubs:
            pubs[topic] = ros.create_publisher(type(msg), topic, 10)
        pubs[topic].publish(msg)

    oracle = "gnss" if (args.navsat_topic or args.gnss_pose_topic) else None

    def make_session(camera, T_vc):
        return scenesig.Session(args.map, camera, T_vc, method=args.method, oracle=oracle, preset=args.preset)

    node = LocalisationNode(make_session, publish, _rclpy_types, T_vehicle_camera=args.extrinsic,
                            map_frame=args.map_frame, odom_frame=args.odom_frame, base_frame=args.base_frame,
                            topics={"odometry": args.output_topic}, datum=args.datum, rectified=args.rectified)
    ty = _rclpy_types
    compressed = args.image_topic.endswith("compressed")
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    on_image = node.on_compressed_image if compressed else node.on_image
    ros.create_subscription(ty(image_type), args.image_topic, on_image, qos_profile_sensor_data)
    ros.create_subscription(ty("sensor_msgs/msg/CameraInfo"), args.camera_info_topic, node.on_camera_info, 10)
    ros.create_subscription(ty("nav_msgs/msg/Odometry"), args.odom_topic, node.on_odometry, 50)
    if args.extrinsic is None:
        from rclpy.qos import DurabilityPolicy, QoSProfile

        latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        ros.create_subscription(ty("tf2_msgs/msg/TFMessage"), "/tf_static", node.on_tf_static, latched)
    if args.navsat_topic:
        ros.create_subscription(ty("sensor_msgs/msg/NavSatFix"), args.navsat_topic, node.on_navsatfix, 10)
    if args.gnss_pose_topic:
        ros.create_subscription(ty("nav_msgs/msg/Odometry"), args.gnss_pose_topic, node.on_gnss_pose, 10)
    try:
        rclpy.spin(ros)
    except KeyboardInterrupt:
        pass
    finally:
        node.flush()
        if node.session is not None:
            node.session.close()
        ros.destroy_node()
        rclpy.try_shutdown()
    return 0
