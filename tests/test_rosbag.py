"""ROS bags: a simulated run written as ROS 1, ROS 2 (sqlite3) and MCAP bags imports back as the same run; bags
built message by message with rosbags' own writer check the conventions (header stamps, tf chains, CameraInfo,
Bayer patterns); bad bags (missing topic, corrupt image, non-monotonic or empty stamps) give a clear error or a
counted skip; a localisation exported as a bag reads back with its trajectory.tum poses."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from build_world import tiny_runs
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import (
    CAMERA_FROM_VEHICLE_AXES,
    invert,
    make_pose,
    pose_to_xyzquat,
    rot_z,
    xyzquat_to_pose,
)
from scenesig.surveys.importers import rosbag as rb
from scenesig.surveys.run import read_run, write_run
from scenesig.surveys.tum import write_tum

pytest.importorskip("scenesig.surveys.sim.simulate")


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """The tiny world's sunny run (simulated once per session, shared with the map tests)."""
    return tiny_runs(tmp_path_factory.getbasetemp())[0]


def _cli(argv):
    from scenesig import cli

    return cli.main(argv)


def _topics(images: str, odometry_as: str) -> dict:
    return {"image_topic": "/camera/image_raw" if images == "raw" else "/camera/image_raw/compressed",
            "camera_info_topic": "/camera/camera_info", "odom_topic": "/odom" if odometry_as == "odometry" else "/tf",
            "gt_topic": "/ins", "truth_topic": "/truth"}


def _assert_same_run(src, back, images: str):
    assert back.name == src.name and back.conditions == src.conditions
    assert back.camera == src.camera
    # the extrinsic travels as a quaternion (/tf_static): equal to rounding
    np.testing.assert_allclose(back.T_vehicle_camera, src.T_vehicle_camera, atol=1e-15)
    for k in ("frame", "odometry", "groundtruth", "truth"):
        # times to the nanosecond (the run files' 9 decimals), poses to rounding
        np.testing.assert_array_equal(getattr(back, f"{k}_times"), getattr(src, f"{k}_times"), err_msg=k)
        if k != "frame":
            np.testing.assert_allclose(getattr(back, f"{k}_poses"), getattr(src, f"{k}_poses"), atol=1e-12, err_msg=k)
    # the simulator states nominal rates; the import measures them from the stamps (9-decimal times: within 1e-6)
    for k in ("camera_hz", "odometry_hz", "ins_hz"):
        assert back.rates[k] == pytest.approx(src.rates[k], rel=1e-6), k
    assert back.metadata["skipped"] == {} and back.metadata["gaps"] == []
    assert back.metadata["stamps"] == "header stamps"
    for i in range(len(src)):
        if images == "jpeg":  # the simulator's JPEG files travel as they are
            assert (back.root / back.frame_files[i]).read_bytes() == (src.root / src.frame_files[i]).read_bytes()
        else:                 # raw and PNG: lossless, the same pixels
            np.testing.assert_array_equal(back.image(i), src.image(i))


@pytest.mark.parametrize("fmt,out,images,odometry_as", [
    ("ros1", "run.bag", "raw", "odometry"),
    ("ros2", "run_db3", "jpeg", "tf"),
    ("mcap", "run_mcap", "png", "odometry"),
    ("mcap", "run.mcap", "raw", "tf"),
])
def test_simulated_run_round_trips_through_a_bag(source, tmp_path, fmt, out, images, odometry_as):
    bag = rb.write_run_bag(source, tmp_path / out, fmt, images=images, odometry_as=odometry_as, progress=False)
    assert rb.bag_format([bag]) == {"ros1": "ros1", "ros2": "ros2-sqlite3", "mcap": "ros2-mcap"}[fmt]
    assert not list(tmp_path.glob(".*tmp*")) and not list(tmp_path.glob("*.tmp"))
    listing = rb.list_topics(bag)
    img_topic = _topics(images, odometry_as)["image_topic"]
    assert listing["topics"][img_topic]["count"] == len(source)
    assert listing["topics"][img_topic]["rate_hz"] == pytest.approx(source.rates["camera_hz"], rel=1e-3)
    conf = {**_topics(images, odometry_as), "name": source.name, "conditions": source.conditions}
    back = read_run(rb.import_rosbag(bag, tmp_path / "back", conf, progress=False))
    _assert_same_run(source, back, images)
    assert back.metadata["extrinsic"] == "/tf_static base_link -> camera_optical"
    assert back.metadata["bag_format"] == rb.bag_format([bag])
    if images == "jpeg":
        # what build-map and localise read is byte for byte the source run's with its poses once through a
        # quaternion (how a ROS message carries them): the round trip adds nothing else
        import dataclasses

        def q(P):
            return xyzquat_to_pose(pose_to_xyzquat(P)).reshape(P.shape)

        ctl = write_run(dataclasses.replace(source, T_vehicle_camera=q(source.T_vehicle_camera),
                                            odometry_poses=q(source.odometry_poses),
                                            groundtruth_poses=q(source.groundtruth_poses),
                                            truth_poses=q(source.truth_poses)), tmp_path / "ctl", images=None)
        for f in ["frames.csv", "odometry.csv", "groundtruth.tum", "truth.tum"] + back.frame_files:
            assert (ctl / f).read_bytes() == (back.root / f).read_bytes(), f
        assert read_run(ctl).T_vehicle_camera.tobytes() == back.T_vehicle_camera.tobytes()


# --------------------------------------------------------------------------------------- hand-built bags
class BagBuilder:
    """A bag written message by message with rosbags' writer (ROS 1 field names where the format has them)."""

    def __init__(self, path: Path, fmt: str = "ros2"):
        self.path, self.fmt = path, fmt
        self.ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types
        self.msgs = []

    def header(self, ns, frame):
        kw = {"stamp": self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), "frame_id": frame}
        if self.fmt == "ros1":
            kw["seq"] = 0
        return self.T["std_msgs/msg/Header"](**kw)

    def add(self, topic, msg, ns):
        self.msgs.append((ns, topic, msg))

    def pose(self, P):
        x, y, z, qx, qy, qz, qw = pose_to_xyzquat(P)
        q = self.T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
        return self.T["geometry_msgs/msg/Pose"](position=self.T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                               orientation=q)

    def transform(self, stamp, parent, child, P):
        x, y, z, qx, qy, qz, qw = pose_to_xyzquat(P)
        return self.T["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp, parent), child_frame_id=child,
            transform=self.T["geometry_msgs/msg/Transform"](
                translation=self.T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                rotation=self.T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))

    def tf(self, stamp, parent, child, P):
        return self.T["tf2_msgs/msg/TFMessage"](transforms=[self.transform(stamp, parent, child, P)])

    def image(self, stamp, frame, img, encoding):
        h, w = img.shape[:2]
        return self.T["sensor_msgs/msg/Image"](header=self.header(stamp, frame), height=h, width=w, encoding=encoding,
                                               is_bigendian=0, step=img.size // h, data=img.reshape(-1))

    def compressed(self, stamp, frame, data: bytes, fmt="jpeg"):
        return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp, frame), format=fmt,
                                                         data=np.frombuffer(data, np.uint8))

    def camera_info(self, stamp, frame, w, h, K, D, P=None, model="plumb_bob"):
        cls = self.T["sensor_msgs/msg/CameraInfo"]
        arrays = {"d": np.asarray(D, float), "k": np.asarray(K, float).ravel(), "r": np.eye(3).ravel(),
                  "p": (np.hstack([np.asarray(K, float), np.zeros((3, 1))]) if P is None
                        else np.asarray(P, float)).ravel()}
        if "K" in cls.__dataclass_fields__:
            arrays = {k.upper(): v for k, v in arrays.items()}
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return cls(header=self.header(stamp, frame), height=h, width=w, distortion_model=model, binning_x=0,
                   binning_y=0, roi=roi, **arrays)

    def write(self):
        ser = self.ts.serialize_ros1 if self.fmt == "ros1" else self.ts.serialize_cdr
        if self.fmt == "ros1":
            w = Writer1(self.path)
        else:
            w = Writer2(self.path, version=9,
                        storage_plugin=StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3)
        with w:
            conns = {}
            for ns, topic, msg in sorted(self.msgs, key=lambda m: m[0]):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=self.ts)
                w.write(conns[topic], ns, ser(msg, msg.__msgtype__))
        return self.path


T0 = 1_700_000_000_000_000_000  # ns
LAG = 30_000_000                # record time - header stamp: 30 ms of transport delay
W, H = 40, 30
K = [[60.0, 0, 19.5], [0, 61.0, 14.5], [0, 0, 1]]
D = [0.1, -0.02, 0.001, 0.002, 0.0]
T_BASE_LINK = make_pose(None, [0.5, 0.0, 1.0])                  # base_link -> camera_link (static)
T_LINK_OPT = make_pose(CAMERA_FROM_VEHICLE_AXES)                # camera_link -> camera_optical (static)
T_FOOT_BASE = make_pose(None, [0.0, 0.0, 0.1])                  # base_footprint -> base_link (static)


def _vehicle_pose(k):
    return make_pose(rot_z(0.05 * k), [1.0 * k, 0.2 * k, 0.0])


def _textured(k, rng=np.random.default_rng(0)):
    return rng.integers(0, 255, (H, W, 3), dtype=np.uint8)


def hand_bag(path: Path, fmt="ros2", n=10, encoding="bgr8", compressed=False, odom="pose", stamps=None,
             corrupt=(), zero_stamp=(), drop=(), camera_info=True):
    """A bag of ``n`` frames at 10 Hz (header stamps ``stamps``; record times 30 ms later), the vehicle on
    ``_vehicle_pose``: odometry as PoseStamped of base_link (``odom="pose"``) or as the /tf chain odom ->
    base_footprint -> base_link (``"tf"``); INS as Odometry of base_footprint (a static hop from base_link);
    the camera two static hops from base_link. Returns the bag and the images as sent (BGR)."""
    import cv2

    b = BagBuilder(path, fmt)
    stamps = [T0 + k * 100_000_000 for k in range(n)] if stamps is None else stamps
    b.add("/tf_static", b.T["tf2_msgs/msg/TFMessage"](transforms=[
        b.transform(T0, "base_link", "camera_link", T_BASE_LINK),
        b.transform(T0, "camera_link", "camera_optical", T_LINK_OPT),
        b.transform(T0, "base_footprint", "base_link", T_FOOT_BASE)]), T0 - 1)
    sent = []
    for k, s in enumerate(stamps):
        if k in drop:
            continue
        img = _textured(k)
        sent.append(img)
        if compressed:
            data = cv2.imencode(".jpg", img)[1].tobytes()
            if k in corrupt:
                data = data[: len(data) // 2]   # a truncated JPEG
            msg = b.compressed(s if k not in zero_stamp else 0, "camera_optical", data)
            topic = "/cam/image_raw/compressed"
        else:
            data = _encode_raw(img, encoding)
            msg = b.image(s if k not in zero_stamp else 0, "camera_optical", data, encoding)
            topic = "/cam/image_raw"
        b.add(topic, msg, s + LAG)
        if camera_info:
            b.add("/cam/camera_info", b.camera_info(s, "camera_optical", W, H, K, D), s + LAG)
        P = _vehicle_pose(k)
        if odom == "pose":
            b.add("/odom_pose", b.T["geometry_msgs/msg/PoseStamped"](header=b.header(s, "odom"), pose=b.pose(P)),
                  s + LAG)
        else:
            b.add("/tf", b.tf(s, "odom", "base_footprint", P @ invert(T_FOOT_BASE)), s + LAG)
        ins = make_pose(None, [100.0, 50.0, 0.0]) @ P @ invert(T_FOOT_BASE)
        b.add("/ins", b.T["nav_msgs/msg/Odometry"](
            header=b.header(s, "map"), child_frame_id="base_footprint",
            pose=b.T["geometry_msgs/msg/PoseWithCovariance"](pose=b.pose(ins), covariance=np.zeros(36)),
            twist=b.T["geometry_msgs/msg/TwistWithCovariance"](
                twist=b.T["geometry_msgs/msg/Twist"](linear=b.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                                     angular=b.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36))), s + LAG)
    return b.write(), sent


def _encode_raw(img, encoding):
    import cv2

    if encoding == "bgr8":
        return img
    if encoding == "rgb8":
        return img[:, :, ::-1].copy()
    if encoding == "mono8":
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if encoding.startswith("bayer_"):
        pattern = encoding[6:10]  # e.g. rggb: the colours of the 2x2 cell, row by row
        chan = {"r": 2, "g": 1, "b": 0}
        out = np.empty(img.shape[:2], np.uint8)
        for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern):
            out[dy::2, dx::2] = img[dy::2, dx::2, chan[c]]
        return out
    raise ValueError(encoding)


HAND = {"image_topic": "/cam/image_raw", "camera_info_topic": "/cam/camera_info", "odom_topic": "/odom_pose",
        "gt_topic": "/ins", "base_frame": "base_link"}


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_hand_built_bag_conventions(tmp_path, fmt):
    """Header stamps (not record times), CameraInfo K and D, the extrinsic through two static hops, INS poses
    of another frame carried to the vehicle frame, PoseStamped odometry."""
    bag, sent = hand_bag(tmp_path / ("b.bag" if fmt == "ros1" else "b"), fmt)
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", HAND, progress=False))
    stamps = T0 + np.arange(10) * 100_000_000
    np.testing.assert_array_equal(run.frame_times, [float(f"{s // 10**9}.{s % 10**9:09d}") for s in stamps])
    assert run.metadata["record_minus_header_s"]["images"]["median"] == pytest.approx(0.03)
    assert run.camera.K.tolist() == K and run.camera.distortion == tuple(D)
    assert (run.camera.width, run.camera.height) == (W, H)
    np.testing.assert_allclose(run.T_vehicle_camera, T_BASE_LINK @ T_LINK_OPT, atol=1e-12)
    poses = np.stack([_vehicle_pose(k) for k in range(10)])
    np.testing.assert_allclose(run.odometry_poses, poses, atol=1e-12)
    np.testing.assert_allclose(run.groundtruth_poses, make_pose(None, [100.0, 50.0, 0.0]) @ poses, atol=1e-9)
    assert run.rates == {"camera_hz": 10.0, "odometry_hz": 10.0, "ins_hz": 10.0}
    for i, img in enumerate(sent):
        np.testing.assert_array_equal(run.image(i), img)


def test_odometry_from_a_tf_chain(tmp_path):
    bag, _ = hand_bag(tmp_path / "b", odom="tf")
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", {**HAND, "odom_topic": "/tf"}, progress=False))
    np.testing.assert_allclose(run.odometry_poses, np.stack([_vehicle_pose(k) for k in range(10)]), atol=1e-12)
    assert run.odometry_source == "rosbag:/tf" and run.metadata["odometry_frame"] == "odom"
    # a chain that is not there is named
    with pytest.raises(DataError, match="no tf chain 'nowhere' -> 'base_link'"):
        rb.load_rosbag(bag, {**HAND, "odom_topic": "/tf", "odom_frame": "nowhere"})


@pytest.mark.parametrize("encoding", ["rgb8", "mono8", "bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8"])
def test_raw_encodings(tmp_path, encoding):
    import cv2

    bag, sent = hand_bag(tmp_path / "b", n=4, encoding=encoding)
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", HAND, progress=False))
    if encoding == "rgb8":
        np.testing.assert_array_equal(run.image(0), sent[0])
    elif encoding == "mono8":
        np.testing.assert_array_equal(run.image(0, gray=True), cv2.cvtColor(sent[0], cv2.COLOR_BGR2GRAY))
    # a flat colour mosaiced in each Bayer pattern demosaics to that colour: the pattern names are mapped right
    flat = np.empty((8, 8, 3), np.uint8)
    flat[:] = (10, 100, 200)
    msg = type("M", (), {"encoding": encoding, "height": 8, "width": 8, "step": 8 if encoding != "rgb8" else 24,
                         "data": _encode_raw(flat, encoding).reshape(-1)})
    out = rb.raw_image(msg)
    if encoding.startswith("bayer"):
        np.testing.assert_array_equal(out[2:6, 2:6], flat[2:6, 2:6])


def test_compressed_images_travel_as_they_are(tmp_path):
    import cv2

    bag, sent = hand_bag(tmp_path / "b.bag", "ros1", compressed=True)
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", {**HAND, "image_topic": "/cam/image_raw/compressed"},
                                    progress=False))
    assert run.frame_files[0].endswith(".jpg")
    assert (run.root / run.frame_files[3]).read_bytes() == cv2.imencode(".jpg", sent[3])[1].tobytes()


# --------------------------------------------------------------------------------------- bad bags
def test_missing_topic_is_named(tmp_path):
    bag, _ = hand_bag(tmp_path / "b")
    with pytest.raises(DataError, match=r"no topic '/camera/image' \(images\) in this bag; its topics: "
                                        r"/cam/camera_info, /cam/image_raw"):
        rb.load_rosbag(bag, {**HAND, "image_topic": "/camera/image"})
    with pytest.raises(DataError, match=r"topic '/cam/camera_info' \(odometry\) is sensor_msgs/msg/CameraInfo"):
        rb.load_rosbag(bag, {**HAND, "odom_topic": "/cam/camera_info"})
    # no /tf_static path from the vehicle frame to the camera: named, with what to do
    with pytest.raises(DataError, match="no /tf_static transform 'vehicle' -> 'camera_optical'.*--extrinsic"):
        rb.load_rosbag(bag, {**HAND, "base_frame": "vehicle", "odom_topic": None})
    assert not (tmp_path / "run").exists()


def test_wrong_type_is_named(tmp_path):
    bag, _ = hand_bag(tmp_path / "b")
    with pytest.raises(DataError, match=r"topic '/ins' \(camera info\) is nav_msgs/msg/Odometry, expected "
                                        r"sensor_msgs/msg/CameraInfo"):
        rb.load_rosbag(bag, {**HAND, "camera_info_topic": "/ins"})


def test_corrupt_image_stops_or_is_counted(tmp_path):
    bag, _ = hand_bag(tmp_path / "b", compressed=True, corrupt=(4,))
    conf = {**HAND, "image_topic": "/cam/image_raw/compressed"}
    with pytest.raises(DataError, match=r"/cam/image_raw/compressed: message 4 \(stamp 1700000000\.400000000\): "
                                        r"corrupt or truncated JPEG.*--skip-corrupt"):
        rb.import_rosbag(bag, tmp_path / "run", conf, progress=False)
    assert not (tmp_path / "run").exists() and not (tmp_path / "run.tmp").exists()  # nothing half-written
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", {**conf, "skip_corrupt": True}, progress=False))
    assert len(run) == 9 and run.metadata["skipped"] == {"images_corrupt": 1}
    assert run.metadata["corrupt_messages"] == [[4, 1700000000.4]]
    assert run.metadata["gaps"] == [[1700000000.3, 1700000000.5]]  # the left-out frame is a gap


def test_non_monotonic_stamp_is_skipped_and_counted(tmp_path):
    stamps = [T0 + k * 100_000_000 for k in range(10)]
    stamps[5] = stamps[3]  # a late, reordered message: its stamp is older than the previous one's
    bag, _ = hand_bag(tmp_path / "b", stamps=stamps)
    run = read_run(rb.import_rosbag(bag, tmp_path / "run", HAND, progress=False))
    assert len(run) == 9 and len(run.odometry_times) == 9
    assert run.metadata["skipped"] == {"images_non_monotonic_stamp": 1, "odometry_non_monotonic_stamp": 1,
                                       "groundtruth_non_monotonic_stamp": 1}
    assert np.all(np.diff(run.frame_times) > 0)


def test_zero_header_stamp_is_an_error_unless_record_times(tmp_path):
    bag, _ = hand_bag(tmp_path / "b", zero_stamp=(2,))
    with pytest.raises(DataError, match=r"/cam/image_raw: message 2 has a zero header stamp.*--stamps record"):
        rb.load_rosbag(bag, HAND)
    run, _ = rb.load_rosbag(bag, {**HAND, "stamps": "record"})
    assert run.frame_times[0] == pytest.approx(1700000000.03) and run.metadata["stamps"].startswith("record")


def test_gaps_are_kept(tmp_path):
    bag, _ = hand_bag(tmp_path / "b", drop=(4, 5))
    run, _ = rb.load_rosbag(bag, HAND)
    assert len(run) == 8 and run.metadata["gaps"] == [[1700000000.3, 1700000000.6]]


def test_not_a_bag(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"not a bag at all")
    with pytest.raises(DataError, match="x.bag: not a readable ROS bag"):
        rb.list_topics(tmp_path / "x.bag")
    with pytest.raises(DataError, match="nowhere.bag: bag not found"):
        rb.list_topics(tmp_path / "nowhere.bag")
    (tmp_path / "folder").mkdir()
    with pytest.raises(DataError, match="metadata.yaml: not found"):
        rb.list_topics(tmp_path / "folder")


def test_missing_rosbags_says_how_to_install(monkeypatch, tmp_path, capsys):
    for name in ("rosbags", "rosbags.highlevel", "rosbags.rosbag1", "rosbags.rosbag2", "rosbags.typesys"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(DataError, match=r"needs the optional package rosbags: pip install 'scenesig\[ros\]'"):
        rb.require_rosbags(tmp_path / "b.bag")
    (tmp_path / "b.bag").write_bytes(b"")
    assert _cli(["import", "rosbag", str(tmp_path / "b.bag"), "--list"]) == 2
    assert "pip install 'scenesig[ros]'" in capsys.readouterr().err


# --------------------------------------------------------------------------------------- export
def _locdir(tmp_path, n=12, with_cov=True):
    """A localisation folder: trajectory.tum (frames 3, 7 unlocalised) and covariances.csv."""
    loc = tmp_path / "loc"
    loc.mkdir()
    times = np.array([1405342801.0 + 0.1 * k for k in range(n) if k not in (3, 7)])
    poses = np.stack([make_pose(rot_z(0.3 * k), [2.0 * k, -1.0 * k, 0.1]) for k in range(len(times))])
    write_tum(loc / "trajectory.tum", times, poses)
    if with_cov:
        lines = ["time,lateral_bound_95_m,var_longitudinal_m2,var_lateral_m2,cov_longitudinal_lateral,var_yaw_rad2"]
        for k, t in enumerate(times):
            lines.append(f"{t:.9f},1.0,{0.04 + k * 0.01},{0.01 + k * 0.001},0.002,{1e-4}")
        (loc / "covariances.csv").write_text("\n".join(lines) + "\n")
    return loc, times, poses


@pytest.mark.parametrize("out,fmt", [("loc.bag", "ros1"), ("loc_db3", "ros2"), ("loc.mcap", "mcap")])
def test_exported_localisation_reads_back(tmp_path, capsys, out, fmt):
    loc, times, poses = _locdir(tmp_path)
    assert _cli(["export", "rosbag", str(loc), "--out", str(tmp_path / out)]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["format"] == fmt and res["poses"] == len(times) and res["with_covariance"] == len(times)
    assert res["read_back"]["max_position_difference_m"] <= 1e-12
    bt, bp, bc = rb.read_bag_poses(tmp_path / out, "/scenesig/odometry")
    np.testing.assert_array_equal(bt, times)
    np.testing.assert_allclose(bp, poses, atol=1e-12)
    # the body-frame covariance, rotated into the map frame; yaw variance on the diagonal; the rest zero
    k = 4
    B = np.array([[0.04 + k * 0.01, 0.002, 0], [0.002, 0.01 + k * 0.001, 0], [0, 0, 0]])
    R = poses[k][:3, :3]
    np.testing.assert_allclose(bc[k][:3, :3], R @ B @ R.T, atol=1e-15)
    assert bc[k][5, 5] == 1e-4 and not bc[k][3:5].any()
    # read with rosbags alone (not the importer's reader): the numbers trajectory.tum holds
    from rosbags.highlevel import AnyReader

    paths = [tmp_path / out]
    with AnyReader(paths) as r:
        conns = [c for c in r.connections if c.topic == "/scenesig/odometry"]
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    got = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z,
                     m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                     m.pose.pose.orientation.w] for m in msgs])
    want = np.loadtxt(loc / "trajectory.tum")
    np.testing.assert_array_equal([float(f"{m.header.stamp.sec}.{m.header.stamp.nanosec:09d}") for m in msgs],
                                  want[:, 0])
    np.testing.assert_array_equal(got[:, :3], want[:, 1:4])
    np.testing.assert_allclose(got[:, 3:] * np.sign(got[:, 6:7] * want[:, 7:8]), want[:, 4:], atol=1e-15)
    assert {m.header.frame_id for m in msgs} == {"map"} and {m.child_frame_id for m in msgs} == {"scenesig/base_link"}
    # and on /tf, the same poses
    tt, tp, _ = rb.read_bag_poses(tmp_path / out, "/tf")
    np.testing.assert_array_equal(tt, times)
    np.testing.assert_allclose(tp, poses, atol=1e-12)
    # refused when it exists
    assert _cli(["export", "rosbag", str(loc), "--out", str(tmp_path / out)]) == 2
    assert "already exists" in capsys.readouterr().err


def test_export_without_covariances_states_unknown(tmp_path, capsys):
    loc, times, poses = _locdir(tmp_path, with_cov=False)
    assert _cli(["export", "rosbag", str(loc), "--out", str(tmp_path / "b")]) == 0
    assert json.loads(capsys.readouterr().out)["with_covariance"] == 0
    _, _, bc = rb.read_bag_poses(tmp_path / "b", "/scenesig/odometry")
    assert not bc.any()  # all zeros: ROS's "covariance unknown"


def test_covariances_without_a_covariance_column_are_named(tmp_path):
    loc, times, poses = _locdir(tmp_path, with_cov=False)
    (loc / "covariances.csv").write_text("time,lateral_bound_95_m\n1405342801.0,1.0\n")
    with pytest.raises(DataError, match="covariances.csv:1: no covariance column"):
        rb.read_pose_covariances(loc / "covariances.csv", times, poses)


def test_cli_list_and_import(source, tmp_path, capsys):
    bag = rb.write_run_bag(source, tmp_path / "s.bag", "ros1", images="jpeg", progress=False)
    assert _cli(["import", "rosbag", str(bag), "--list"]) == 0
    text = capsys.readouterr().out
    assert "/camera/image_raw/compressed  sensor_msgs/CompressedImage" in text
    assert ("scenesig import rosbag " + str(bag) + " --image-topic /camera/image_raw/compressed --camera-info-topic "
            "/camera/camera_info --odom-topic /odom --gt-topic /ins") in text
    assert _cli(["import", "rosbag", str(bag), "--image-topic", "/camera/image_raw/compressed", "--camera-info-topic",
                 "/camera/camera_info", "--odom-topic", "/odom", "--gt-topic", "/ins", "--truth-topic", "/truth",
                 "--name", source.name, "--conditions", ",".join(source.conditions), "--out", str(tmp_path / "r")]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == len(source) and res["skipped"] == {} and res["stamps"] == "header stamps"
    _assert_same_run(source, read_run(tmp_path / "r"), "jpeg")
    assert _cli(["import", "rosbag", str(bag), "--image-topic", "/nope", "--camera-info-topic", "/camera/camera_info",
                 "--odom-topic", "/odom", "--out", str(tmp_path / "r2")]) == 2
    assert "no topic '/nope' (images) in this bag" in capsys.readouterr().err
    # a survey run exported as a bag by the command reads back with its odometry
    assert _cli(["export", "rosbag", str(tmp_path / "r"), "--out", str(tmp_path / "again.mcap")]) == 0
    assert json.loads(capsys.readouterr().out)["source"] == "survey run"


def test_record_times_far_from_header_stamps_are_stated(tmp_path, monkeypatch, caplog):
    monkeypatch.setitem(globals(), "LAG", 200_000_000)  # a recorder 0.2 s behind the sensors
    bag, _ = hand_bag(tmp_path / "b", n=5)
    with caplog.at_level("WARNING", logger="scenesig.surveys.importers.rosbag"):
        run, _ = rb.load_rosbag(bag, HAND)
    assert run.frame_times[0] == 1700000000.0  # the header stamp, not the record time
    assert run.metadata["record_minus_header_s"]["odometry"]["median"] == pytest.approx(0.2)
    assert "images: times are header stamps; the record times differ by 0.200 s" in caplog.text


def test_the_localisers_covariances_csv_layout(tmp_path):
    """The localiser writes the planar (x, y, yaw) covariance's upper triangle in the map frame:
    time,xx,xy,xyaw,yy,yyaw,yawyaw -- it lands in the x, y, yaw entries of the 6x6."""
    loc, times, poses = _locdir(tmp_path, with_cov=False)
    rows = ["time,xx,xy,xyaw,yy,yyaw,yawyaw"] + [f"{t:.9f},0.04,0.01,0.001,0.09,0.002,0.0004" for t in times[:-1]]
    (loc / "covariances.csv").write_text("\n".join(rows) + "\n")
    cov, have = rb.read_pose_covariances(loc / "covariances.csv", times, poses)
    assert have.tolist() == [True] * (len(times) - 1) + [False]
    want = np.zeros((6, 6))
    for (a, b), v in {(0, 0): 0.04, (0, 1): 0.01, (0, 5): 0.001, (1, 1): 0.09, (1, 5): 0.002, (5, 5): 0.0004}.items():
        want[a, b] = want[b, a] = v
    np.testing.assert_array_equal(cov[0], want)
    assert not cov[-1].any()


def test_cli_says_what_is_missing(tmp_path, capsys):
    bag, _ = hand_bag(tmp_path / "b", n=3)
    img, info, odo = ["--image-topic", "/cam/image_raw"], ["--camera-info-topic", "/cam/camera_info"], \
        ["--odom-topic", "/odom_pose"]
    for argv, what in ((odo + info, "--image-topic is required"), (img + info, "give --odom-topic, --gt-topic"),
                       (img + odo, "give --camera-info-topic or --intrinsics")):
        with pytest.raises(SystemExit) as exc:
            _cli(["import", "rosbag", str(bag), *argv, "--out", str(tmp_path / "r")])
        assert exc.value.code == 2 and what in capsys.readouterr().err
    # --intrinsics and --extrinsic instead of CameraInfo and /tf_static
    assert _cli(["import", "rosbag", str(bag), "--image-topic", "/cam/image_raw", "--odom-topic", "/odom_pose",
                 "--base-frame", "base_link", "--intrinsics", "50,50,19.5,14.5", "--extrinsic",
                 "1,0,2,-0.5,0.5,-0.5,0.5", "--out", str(tmp_path / "r")]) == 0
    run = read_run(tmp_path / "r")
    assert run.camera.K.tolist() == [[50, 0, 19.5], [0, 50, 14.5], [0, 0, 1]] and run.camera.size == (W, H)
    np.testing.assert_allclose(run.T_vehicle_camera, make_pose(CAMERA_FROM_VEHICLE_AXES, [1, 0, 2]), atol=1e-12)
    assert run.metadata["extrinsic"] == "given (--extrinsic)" and run.odometry_source == "rosbag:/odom_pose"


def test_unsupported_encoding_is_an_error_even_when_skipping_corrupt_frames(tmp_path):
    b = BagBuilder(tmp_path / "c")
    b.add("/cam/image_raw", b.T["sensor_msgs/msg/Image"](header=b.header(T0, "camera_optical"), height=2, width=2,
                                                       encoding="mono16", is_bigendian=0, step=4,
                                                       data=np.zeros(8, np.uint8)), T0)
    b.add("/odom_pose", b.T["geometry_msgs/msg/PoseStamped"](header=b.header(T0, "odom"), pose=b.pose(np.eye(4))), T0)
    b.write()
    with pytest.raises(DataError, match=r"message 0 .*image encoding 'mono16' not supported"):
        rb.load_rosbag(tmp_path / "c", {**HAND, "skip_corrupt": True, "camera_info_topic": None,
                                        "intrinsics": [1, 1, 1, 1], "gt_topic": None})
