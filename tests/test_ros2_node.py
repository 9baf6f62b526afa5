"""The ROS 2 node (``scenesig ros2 node``, :mod:`scenesig.ros2_node`) without ROS: its callbacks driven with the
``rosbags`` message objects of a bag written by ``scenesig export rosbag`` (:func:`write_run_bag`), publishing
through an injected publisher with rosbags' message classes.  The published poses are the replay's; the
``map -> odom`` transform follows AMCL's convention; the diagnostics carry the integrity state; the command
exits 2 naming rclpy where ROS 2 is absent, and only the node module imports rclpy."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

ROOT = Path(__file__).resolve().parents[1]


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


class _Recorder:
    """The injected publisher: every (topic, message) published, in order."""

    def __init__(self):
        self.sent: list = []

    def __call__(self, topic, msg):
        self.sent.append((topic, msg))

    def on(self, topic):
        return [m for t, m in self.sent if t == topic]


def _drive(node, bag: Path):
    """Replay a bag's messages, in record order, into the node's callbacks (as rclpy's executor would)."""
    from rosbags.highlevel import AnyReader

    callbacks = {"/camera/image_raw": node.on_image, "/camera/image_raw/compressed": node.on_compressed_image,
                 "/camera/camera_info": node.on_camera_info, "/odom": node.on_odometry,
                 "/tf_static": node.on_tf_static}
    with AnyReader([bag], default_typestore=_typestore()) as r:
        conns = [c for c in r.connections if c.topic in callbacks]
        for c, _, raw in r.messages(connections=conns):
            callbacks[c.topic](r.deserialize(raw, c.msgtype))
    node.flush()


def _pose(msg) -> np.ndarray:
    from scenesig.surveys.geometry import xyzquat_to_pose

    p = msg.position if hasattr(msg, "position") else msg.translation
    q = msg.orientation if hasattr(msg, "orientation") else msg.rotation
    return xyzquat_to_pose([p.x, p.y, p.z, q.x, q.y, q.z, q.w])


def test_published_poses_are_the_replays(tiny_world, tmp_path):
    """A simulated run exported as a bag (JPEG images, CameraInfo, /odom, /tf_static), its messages fed to the
    node in record order: a nav_msgs/Odometry in map at every frame the replay has a pose for, equal to the
    replay's pose and covariance; map -> odom = T_map_base inv(T_odom_base) at each of them."""
    import scenesig
    from scenesig.localiser.replay import localise_run
    from scenesig.ros2_node import LocalisationNode, ros_covariance, stamp_seconds
    from scenesig.surveys.importers.rosbag import write_run_bag

    runs, root = tiny_world
    run = next(r for r in runs if r.conditions[0] == "overcast")
    bag = write_run_bag(run, tmp_path / "bag", fmt="ros2", images="jpeg")
    result, store = localise_run(root, run.root, "orb", every=1, oracle="none", progress=False)
    ts = _typestore()
    pub = _Recorder()
    made = []

    def make_session(camera, T_vc):
        assert camera == run.camera and np.allclose(T_vc, run.T_vehicle_camera, atol=1e-12)
        made.append(scenesig.Session(store, camera, T_vc, "orb", oracle=None))
        return made[-1]

    node = LocalisationNode(make_session, pub, lambda n: ts.types[n])
    _drive(node, bag)
    made[0].close()

    odo = pub.on("/scenesig/odometry")
    assert odo and all(m.header.frame_id == "map" and m.child_frame_id == "base_link" for m in odo)
    times = np.array([stamp_seconds(m.header.stamp) for m in odo])
    idx = np.searchsorted(run.frame_times, times)
    assert np.array_equal(run.frame_times[idx], times)             # one message per frame, at its time
    valid = np.asarray(result.valid, bool)
    assert np.array_equal(np.isin(np.arange(len(run)), idx), valid) and valid.sum() > 10
    for m, i in zip(odo, idx):
        T = _pose(m.pose.pose)
        assert np.allclose(T, result.poses[i], atol=1e-9), i
        C = np.asarray(m.pose.covariance).reshape(6, 6)
        assert np.allclose(C, ros_covariance(result.poses[i], result.covariances[i]), rtol=1e-6, atol=1e-12)
    # AMCL's map -> odom: composed with the odometry at the same stamp it gives the published pose
    odom_t, odom_T = run.odometry_times, run.odometry_poses
    tf = [m.transforms[0] for m in pub.on("/tf")]
    assert all(t.header.frame_id == "map" and t.child_frame_id == "odom" for t in tf)
    by_time = {stamp_seconds(t.header.stamp): _pose(t.transform) for t in tf}
    from scenesig.surveys.geometry import interpolate_poses

    for m, i in zip(odo, idx):
        T_map_odom = by_time[stamp_seconds(m.header.stamp)]
        T_odom_base = interpolate_poses(odom_t, odom_T, float(run.frame_times[i]))
        assert np.allclose(T_map_odom @ T_odom_base, result.poses[i], atol=1e-6)
    # a diagnostic per processed frame, with the session's state
    diag = pub.on("/diagnostics")
    assert len(diag) == node.frames_processed >= len(odo)
    states = {kv.value for d in diag for kv in d.status[0].values if kv.key == "state"}
    assert "tracking" in states and states <= {"tracking", "searching", "lost", "alert"}


# ---------------------------------------------------------------------------------------- mechanics
class _FakeSession:
    """A stand-in with Session's surface, for the node's own mechanics (no map): every image is a fix at a
    pose 10 m east of the odometry's, frames newer than the odometry are held until it reaches them."""

    def __init__(self, camera, T_vc, state="tracking"):
        from types import SimpleNamespace

        self.camera, self.T_vc, self.state = camera, T_vc, state
        self.method = SimpleNamespace(color=False)
        self.last_frame, self.t_odometry, self.T_odom = None, None, np.eye(4)
        self.held, self.gnss, self.images = None, [], []
        self.frames_dropped = self.frames_too_late = 0

    def add_odometry(self, t, inc):
        self.T_odom = self.T_odom @ inc
        self.t_odometry = t
        if self.held is not None and self.held[0] <= t:
            self._frame(*self.held)
            self.held = None

    def add_gnss(self, t, T):
        self.gnss.append((t, T))

    def add_image(self, t, img):
        self.images.append(img)
        if self.t_odometry is None or t > self.t_odometry:
            self.held = (t, img)
            return None
        self._frame(t, img)

    def _frame(self, t, img):
        from types import SimpleNamespace

        self.last_frame = SimpleNamespace(t=t, place=3, accepted=True, measurement=SimpleNamespace(inliers=42),
                                          fix=SimpleNamespace(integrity="trusted"))

    def flush(self):
        pass

    def pose(self, t):
        from types import SimpleNamespace

        T = np.eye(4)
        T[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]           # the map is the odometry frame turned by 90 degrees,
        T[0, 3] = 10.0                                   # 10 m east
        return SimpleNamespace(pose=T @ self.T_odom, covariance=np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.04, 0.09]),
                               lateral_bound_95_m=0.5, distance_since_localisation=0.0)


def _msgs():
    from scenesig.surveys.geometry import Camera, make_pose, rot_z
    from scenesig.surveys.importers.rosbag import _camera_info_msg, _odometry_msg, _tf_msg

    ts = _typestore()
    cam = Camera(100.0, 100.0, 31.5, 23.5, 64, 48)
    T_vc = make_pose(rot_z(0.0), [1.2, 0.0, 1.5])
    odom = [_odometry_msg(ts, 1_000_000_000 + k * 100_000_000, "odom", "base_link",
                          make_pose(rot_z(0.05 * k), [1.0 * k, 0.0, 0.0])) for k in range(5)]
    return ts, cam, T_vc, odom, _camera_info_msg(ts, 1_000_000_000, "camera", cam), \
        _tf_msg(ts, 1_000_000_000, "base_link", "camera", T_vc)


def _raw(ts, ns, img):
    from scenesig.surveys.importers.rosbag import _header

    return ts.types["sensor_msgs/msg/Image"](header=_header(ts, ns, "camera"), height=img.shape[0],
                                             width=img.shape[1], encoding="mono8", is_bigendian=0,
                                             step=img.shape[1], data=img.ravel())


def test_node_mechanics_without_a_map():
    """The session is made once CameraInfo and /tf_static are known; a frame newer than the odometry is
    published when the odometry reaches it; map -> odom is AMCL's and re-sent with each odometry message;
    the covariance is rotated into the map frame; diagnostics map the state to a level."""
    from scenesig.ros2_node import LocalisationNode, stamp_seconds

    ts, cam, T_vc, odom, info, tf_static = _msgs()
    pub, made = _Recorder(), []
    node = LocalisationNode(lambda c, T: made.append(_FakeSession(c, T)) or made[-1], pub, lambda n: ts.types[n])
    img = np.full((48, 64), 7, np.uint8)
    node.on_image(_raw(ts, 1_000_000_000, img))            # no calibration yet: dropped
    node.on_odometry(odom[0])
    assert node.session is None and not pub.sent
    node.on_camera_info(info)
    node.on_tf_static(tf_static)
    node.on_odometry(odom[1])                              # the session starts here
    assert node.session is made[0] and made[0].camera == cam and np.allclose(made[0].T_vc, T_vc)
    node.on_image(_raw(ts, 1_150_000_000, img))            # newer than the odometry: held
    assert not pub.on("/scenesig/odometry")
    node.on_odometry(odom[2])                              # reaches it: published at the frame's time
    (o,) = pub.on("/scenesig/odometry")
    assert stamp_seconds(o.header.stamp) == 1.15
    est = made[0].pose(1.15)
    assert np.allclose(_pose(o.pose.pose), est.pose)
    C = np.asarray(o.pose.covariance).reshape(6, 6)
    # vehicle-frame GTSAM (r, t) -> map-frame (t, r): the vehicle heads about north, so x and y swap
    R = est.pose[:3, :3]
    assert np.allclose(C[:3, :3], R @ np.diag([0.01, 0.04, 0.09]) @ R.T)
    assert np.allclose(C[3:, 3:], R @ np.diag([1e-4, 2e-4, 3e-4]) @ R.T)
    tfs = [m.transforms[0] for m in pub.on("/tf")]
    assert len(tfs) == 2                                   # the fix's, then re-sent with odometry 2
    from scenesig.surveys.geometry import interpolate_poses

    T_ob = interpolate_poses(np.array([1.1, 1.2]), np.stack([_pose(odom[k].pose.pose) for k in (1, 2)]), 1.15)
    T_mo = _pose(tfs[0].transform)
    assert np.allclose(T_mo @ T_ob, est.pose, atol=1e-9)
    assert stamp_seconds(tfs[1].header.stamp) == 1.2 and np.allclose(_pose(tfs[1].transform), T_mo)
    (d,) = pub.on("/diagnostics")
    st = d.status[0]
    values = {kv.key: kv.value for kv in st.values}
    assert st.level == st.OK and st.message == "tracking"
    assert values["state"] == "tracking" and values["place"] == "3" and values["inliers"] == "42"
    assert values["integrity"] == "trusted" and values["lateral_bound_95_m"] == "0.500"
    made[0].state = "alert"
    node.on_odometry(odom[3])
    node.on_image(_raw(ts, 1_300_000_000, img))
    assert pub.on("/diagnostics")[-1].status[0].level == st.ERROR
    assert pub.on("/diagnostics")[-1].status[0].message == "alert"


def test_navsatfix_and_gnss_pose_reach_the_session():
    """NavSatFix is turned into a map-frame pose about the datum (heading along the path, after 1 m); a pose
    topic is passed as it is; both wait for the session."""
    from scenesig.ros2_node import LocalisationNode
    from scenesig.surveys.geometry import make_pose
    from scenesig.surveys.importers.rosbag import _header, _odometry_msg

    ts, cam, T_vc, odom, info, tf_static = _msgs()
    made = []
    node = LocalisationNode(lambda c, T: made.append(_FakeSession(c, T)) or made[-1], _Recorder(),
                            lambda n: ts.types[n], camera=cam, T_vehicle_camera=T_vc, datum=(51.5, -1.25, 60.0))
    Fix, Status = ts.types["sensor_msgs/msg/NavSatFix"], ts.types["sensor_msgs/msg/NavSatStatus"]

    def fix(ns, lat, lon):
        return Fix(header=_header(ts, ns, "gps"), status=Status(status=0, service=1), latitude=lat, longitude=lon,
                   altitude=60.0, position_covariance=np.zeros(9), position_covariance_type=0)

    node.on_navsatfix(fix(1_000_000_000, 51.5, -1.25))
    node.on_navsatfix(fix(1_100_000_000, 51.5 + 2e-6, -1.25))      # 0.2 m: not yet a heading
    node.on_navsatfix(fix(1_200_000_000, 51.5 + 2e-5, -1.25))      # ~2.2 m north
    node.on_gnss_pose(_odometry_msg(ts, 1_300_000_000, "map", "base_link", make_pose(None, [5.0, 6.0, 0.0])))
    assert node.session is None
    node.on_odometry(odom[0])
    g = made[0].gnss
    assert [t for t, _ in g] == [1.2, 1.3]
    T = g[0][1]
    assert abs(T[0, 3]) < 1e-3 and 2.1 < T[1, 3] < 2.3 and abs(T[2, 3]) < 1e-3
    assert np.isclose(np.arctan2(T[1, 0], T[0, 0]), np.pi / 2, atol=1e-3)   # heading north (ENU)
    assert np.allclose(g[1][1][:3, 3], [5.0, 6.0, 0.0])
    bare = LocalisationNode(lambda c, T: None, _Recorder(), lambda n: ts.types[n])
    with pytest.raises(ValueError, match="datum"):
        bare.on_navsatfix(fix(1_000_000_000, 51.5, -1.25))


def test_command_without_ros2_exits_2_naming_rclpy(monkeypatch, capsys):
    from scenesig import cli

    monkeypatch.setitem(sys.modules, "rclpy", None)        # absent, even where ROS 2 is sourced
    assert cli.main(["ros2", "node", "--map", "maps/none"]) == 2
    err = capsys.readouterr().err
    assert "rclpy" in err and "ROS 2" in err


def test_only_the_node_module_imports_rclpy():
    """rclpy is imported in scenesig/ros2_node.py only: the rest of the package runs without ROS 2."""
    offenders = []
    for folder in ("scenesig", "surveys", "signatures", "mapping", "localiser", "aerial", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.is_symlink() or any(p.is_symlink() for p in path.parents if ROOT in p.parents):
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                if any(n == "rclpy" or n.startswith("rclpy.") for n in names):
                    offenders.append(str(path.relative_to(ROOT)))
    assert sorted(set(offenders)) == ["scenesig/scenesig/ros2_node.py"]
