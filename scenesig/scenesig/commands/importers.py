"""``scenesig import kitti-raw|kapture|tum-rgbd|euroc|rosbag|images`` and ``scenesig export kapture|rosbag``: the
formats users hold.

The parsers only; the work is in :mod:`scenesig.surveys.importers` (one module per format, conf dicts).
Each import prints a JSON summary (run, frames, seconds, frames_per_second, gaps) on stdout.
"""
from __future__ import annotations

import argparse
import json
import time


def _noise(text: str) -> float:
    v = float(text)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < v < float("inf"):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def _conditions(text: str) -> list[str]:
    return [c.strip() for c in text.split(",") if c.strip()]


def _common(p, noise_help: str, out_required: bool = True) -> None:
    p.add_argument("--out", required=out_required, metavar="RUN", help="survey-run folder to write (atomically)")
    p.add_argument("--name", default=None, help="run name (default from the source folder)")
    p.add_argument("--conditions", type=_conditions, default=None, metavar="TAG[,TAG]",
                   help="condition tags for run.toml, e.g. day,overcast")
    p.add_argument("--odometry-noise", type=_noise, default=0.0, metavar="F", help=noise_help)
    p.add_argument("--odometry-seed", type=int, default=0, help="seed of the odometry drift (default 0)")
    p.add_argument("--photometric", choices=["night", "dusk", "haze"], default=None,
                   help="darken the images (a photometric transform of day images, not real night; recorded "
                        "in run.toml)")
    p.add_argument("--overwrite", action="store_true", help="replace RUN if it exists (default: refuse)")


_DRIFT = ("make the odometry drift as a real odometer's: factor on the simulator's VO error model "
          "(1 = 0.5%% scale bias, 0.4°/100 m heading drift); default 0 = ")


def register(groups) -> None:
    imp, exp = groups["import"], groups["export"]
    k = imp.add_parser("kitti-raw", help="a KITTI raw drive (images, OXTS, calib_*.txt)",
                       description="Import one camera of a KITTI raw drive. Odometry is the OXTS velocities and yaw "
                                   "rate integrated: NOT independent of the INS ground truth.")
    k.add_argument("drive", metavar="DRIVE_DIR")
    k.add_argument("--camera", type=int, choices=[0, 1, 2, 3], default=2, help="2 = left colour, 3 = right colour")
    _common(k, _DRIFT + "the clean OXTS signal")
    k.set_defaults(_run=run_kitti_raw)

    ka = imp.add_parser("kapture", help="one camera of a kapture folder (text format 1.1)",
                        description="Import one camera of a kapture folder. Without records_odometry.txt the odometry "
                                    "is derived from the trajectory (not an independent sensor).")
    ka.add_argument("kapture", metavar="DIR")
    ka.add_argument("--camera", default=None, metavar="ID", help="sensor id in sensors.txt (default: the only camera)")
    ka.add_argument("--timestamp-unit", choices=["ns", "us", "ms", "s"], default=None,
                    help="unit of kapture's integer timestamps (default: scenesig_run.toml's, else ns)")
    _common(ka, _DRIFT + "the trajectory as it is")
    ka.set_defaults(_run=run_kapture)

    t = imp.add_parser("tum-rgbd", help="a TUM RGB-D sequence (rgb.txt + groundtruth.txt)",
                       description="Import a TUM RGB-D sequence. Odometry is the ground truth (not independent).")
    t.add_argument("folder", metavar="DIR")
    t.add_argument("--intrinsics", type=_intrinsics, default=None, metavar="fr1|fr2|fr3|fx,fy,cx,cy[,k1,k2,p1,p2,k3]",
                   help="camera calibration (default: from 'freiburgN' in the folder name)")
    _common(t, _DRIFT + "the ground truth as it is")
    t.set_defaults(_run=run_tum_rgbd)

    e = imp.add_parser("euroc", help="a EuRoC MAV sequence (ASL folders)",
                       description="Import one camera of a EuRoC sequence. Odometry is the ground truth (not independent).")
    e.add_argument("folder", metavar="DIR")
    e.add_argument("--camera", type=int, choices=[0, 1], default=0)
    _common(e, _DRIFT + "the ground truth as it is")
    e.set_defaults(_run=run_euroc)

    rb = imp.add_parser("rosbag", help="a camera and its poses from a ROS 1 / ROS 2 bag (.bag, .db3, MCAP)",
                        description="Import one camera of a ROS bag (ROS 1 .bag files, or one ROS 2 bag: a folder "
                                    "with metadata.yaml or a .db3 / .mcap file). Times are header stamps. Needs the "
                                    "optional package rosbags (pip install 'scenesig[ros]'). Start with --list.")
    rb.add_argument("bag", nargs="+", metavar="BAG", help="the bag (several .bag files: one split ROS 1 recording)")
    rb.add_argument("--list", action="store_true", help="print the topics (type, count, rate) and suggested "
                                                        "arguments, and stop")
    rb.add_argument("--image-topic", metavar="T", help="sensor_msgs/Image or CompressedImage topic (required)")
    rb.add_argument("--camera-info-topic", metavar="T", help="sensor_msgs/CameraInfo topic (or --intrinsics)")
    rb.add_argument("--odom-topic", metavar="T", help="odometry: nav_msgs/Odometry, geometry_msgs/PoseStamped, "
                                                      "PoseWithCovarianceStamped or TransformStamped, or /tf for the "
                                                      "chain --odom-frame -> --base-frame")
    rb.add_argument("--gt-topic", metavar="T", help="ground truth / INS poses (same types; /tf: --gt-frame -> "
                                                    "--base-frame) -> groundtruth.tum")
    rb.add_argument("--truth-topic", metavar="T", help="a simulator's exact poses (same types) -> truth.tum")
    rb.add_argument("--intrinsics", type=_numbers((4, 8, 9)), default=None, metavar="fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]",
                    help="camera calibration instead of CameraInfo (image size from the images)")
    rb.add_argument("--extrinsic", type=_extrinsic, default=None, metavar="x,y,z,qx,qy,qz,qw",
                    help="the camera's pose on the vehicle, T_vehicle_camera (default: /tf_static base frame -> "
                         "the images' frame_id)")
    rb.add_argument("--base-frame", default=None, metavar="F",
                    help="vehicle frame (default: the odometry's child_frame_id, else base_link)")
    rb.add_argument("--odom-frame", default="odom", metavar="F", help="odometry frame of the /tf chain (default odom)")
    rb.add_argument("--gt-frame", default="map", metavar="F", help="ground-truth frame of the /tf chain (default map)")
    rb.add_argument("--stamps", choices=["header", "record"], default="header",
                    help="message times: header stamps (default) or the bag's record times (for drivers that leave "
                         "the header stamp empty)")
    rb.add_argument("--rectified", action=argparse.BooleanOptionalAction, default=None,
                    help="the images are rectified: CameraInfo P, no distortion (default: when the topic name "
                         "contains 'rect')")
    rb.add_argument("--skip-corrupt", action="store_true",
                    help="leave out (and count) image messages that do not decode, instead of stopping")
    _common(rb, _DRIFT + "the odometry topic as it is", out_required=False)
    rb.set_defaults(_run=run_rosbag, _parser=rb)

    im = imp.add_parser("images", help="an ordered image folder (no odometry, no truth)",
                        description="Import an ordered folder of images (natural order of the file names) as a survey "
                                    "run without odometry: frame i at i / HZ seconds. Localised by place recognition "
                                    "with sequence constraints (scenesig bench sequence); see docs/sequences.md.")
    im.add_argument("folder", metavar="FOLDER")
    im.add_argument("--hz", type=_positive, required=True, metavar="H", help="frame rate of the sequence (Hz)")
    im.add_argument("--positions", default=None, metavar="CSV",
                    help="per-frame positions, header frame,x,y[,z] or file,x,y[,z] (metres) -> gps.csv, and "
                         "groundtruth.tum when every frame has one")
    im.add_argument("--aligned-with", default=None, metavar="RUN",
                    help="an imported run of the same route whose frame i is this run's frame i (the evaluation "
                         "truth of traverses without positions)")
    im.add_argument("--intrinsics", type=_numbers((4, 8, 9)), default=None, metavar="fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]",
                    help="camera calibration (default: a pinhole of --hfov degrees, recorded as assumed)")
    im.add_argument("--hfov", type=_positive, default=60.0, metavar="DEG",
                    help="assumed horizontal field of view without --intrinsics (default 60)")
    im.add_argument("--out", required=True, metavar="RUN", help="survey-run folder to write (atomically)")
    im.add_argument("--name", default=None, help="run name (default: the folder's name)")
    im.add_argument("--conditions", type=_conditions, default=None, metavar="TAG[,TAG]",
                    help="condition tags for run.toml, e.g. winter,snow")
    im.add_argument("--overwrite", action="store_true", help="replace RUN if it exists (default: refuse)")
    im.set_defaults(_run=run_images)

    x = exp.add_parser("kapture", help="a survey run as a kapture folder (text format 1.1)",
                       description="Export a survey run as kapture: sensors, rigs, trajectories, records_camera, "
                                   "and scenesig's odometry/GPS records; atomically.")
    x.add_argument("run", metavar="RUN")
    x.add_argument("--out", required=True, metavar="DIR")
    x.add_argument("--camera-id", default="cam", help="sensor id of the camera (default cam)")
    x.add_argument("--overwrite", action="store_true", help="replace DIR if it exists (default: refuse)")
    x.set_defaults(_run=run_export_kapture)

    xb = exp.add_parser("rosbag", help="a localisation (or a survey run) as a ROS 1 / ROS 2 / MCAP bag",
                        description="Write a localisation folder (trajectory.tum, and covariances.csv where the "
                                    "localiser wrote one) as nav_msgs/Odometry and /tf, to play beside the original "
                                    "log in RViz or Foxglove; or a survey run (run.toml) as images, camera info, "
                                    "odometry, INS and /tf_static. Atomic; read back and checked against the source. "
                                    "Needs the optional package rosbags (pip install 'scenesig[ros]').")
    xb.add_argument("source", metavar="LOCDIR", help="a `scenesig localise` output folder, or a survey run")
    xb.add_argument("--out", required=True, metavar="BAG",
                    help="X.bag (ROS 1), a folder (ROS 2), or X.mcap (a bare MCAP file)")
    xb.add_argument("--format", choices=["ros1", "ros2", "mcap"], default=None,
                    help="default from BAG's name: .bag -> ros1, .mcap -> mcap, else ros2 (sqlite3)")
    xb.add_argument("--topic", default="/scenesig/odometry", help="Odometry topic of a localisation")
    xb.add_argument("--frame-id", default="map", help="parent frame of the localised poses (default map)")
    xb.add_argument("--child-frame-id", default="scenesig/base_link",
                    help="frame of the localised vehicle (default scenesig/base_link: beside the log's own "
                         "base_link, not a second parent of it)")
    xb.add_argument("--images", choices=["raw", "jpeg", "png"], default="raw",
                    help="a survey run's images as sensor_msgs/Image (raw, default) or CompressedImage")
    xb.add_argument("--odometry-as", choices=["odometry", "tf"], default="odometry",
                    help="a survey run's odometry as nav_msgs/Odometry on /odom (default) or on /tf")
    xb.add_argument("--overwrite", action="store_true", help="replace BAG if it exists (default: refuse)")
    xb.set_defaults(_run=run_export_rosbag)


def _conf(args, **extra) -> dict:
    conf = {"name": args.name, "odometry_noise": args.odometry_noise, "odometry_seed": args.odometry_seed, **extra}
    if args.conditions is not None:
        conf["conditions"] = args.conditions
    return conf


def _refuse_existing(out, overwrite: bool) -> None:
    from pathlib import Path

    from scenesig.surveys.errors import DataError

    if Path(out).exists() and not overwrite:
        raise DataError(out, "already exists; pass --overwrite to replace it")


def _summary(fn, source, args, conf) -> int:
    from scenesig.surveys.run import read_run

    _refuse_existing(args.out, args.overwrite)
    t0 = time.perf_counter()
    out = fn(source, args.out, conf, overwrite=args.overwrite, photometric=args.photometric)
    seconds = time.perf_counter() - t0
    run = read_run(out, check_images=False)
    extra = {k: run.metadata[k] for k in ("skipped", "stamps") if k in run.metadata}
    print(json.dumps({"run": str(out), "name": run.name, "frames": len(run), "seconds": round(seconds, 3),
                      "frames_per_second": round(len(run) / seconds, 1), "odometry_source": run.odometry_source,
                      "gaps": len(run.metadata.get("gaps", [])), **extra}, indent=1))
    return 0


def run_kitti_raw(args) -> int:
    from scenesig.surveys.importers.kitti_raw import import_kitti_raw

    return _summary(import_kitti_raw, args.drive, args, _conf(args, camera=args.camera))


def run_kapture(args) -> int:
    from scenesig.surveys.importers.kapture import import_kapture

    return _summary(import_kapture, args.kapture, args,
                    _conf(args, camera=args.camera, timestamp_unit=args.timestamp_unit))


def _intrinsics(text: str):
    """--intrinsics: a TUM preset name, or fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] for a 640x480 camera."""
    from scenesig.surveys.geometry import Camera

    if text in ("fr1", "fr2", "fr3"):
        return text
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: fr1|fr2|fr3 or fx,fy,cx,cy[,k1,k2,p1,p2[,k3]]") from None
    if len(v) not in (4, 8, 9):
        raise argparse.ArgumentTypeError(f"needs 4, 8 or 9 numbers, got {len(v)}")
    return Camera(v[0], v[1], v[2], v[3], 640, 480, tuple(v[4:]))


def run_tum_rgbd(args) -> int:
    from scenesig.surveys.importers.tum_rgbd import import_tum_rgbd

    return _summary(import_tum_rgbd, args.folder, args, _conf(args, intrinsics=args.intrinsics))


def run_euroc(args) -> int:
    from scenesig.surveys.importers.euroc import import_euroc

    return _summary(import_euroc, args.folder, args, _conf(args, camera=args.camera))


def run_images(args) -> int:
    from scenesig.surveys.importers.image_folder import import_image_folder
    from scenesig.surveys.run import read_run

    _refuse_existing(args.out, args.overwrite)
    conf = {"hz": args.hz, "name": args.name, "positions": args.positions, "aligned_with": args.aligned_with,
            "intrinsics": args.intrinsics, "hfov_deg": args.hfov}
    if args.conditions is not None:
        conf["conditions"] = args.conditions
    t0 = time.perf_counter()
    out = import_image_folder(args.folder, args.out, conf, overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    run = read_run(out, check_images=False)
    print(json.dumps({"run": str(out), "name": run.name, "frames": len(run), "seconds": round(seconds, 3),
                      "frames_per_second": round(len(run) / seconds, 1), "odometry_source": run.odometry_source,
                      "ignored_files": run.metadata.get("ignored_files", 0),
                      "positions": run.gps is not None, "aligned_with": run.metadata.get("aligned_with")}, indent=1))
    return 0


def run_export_kapture(args) -> int:
    from scenesig.surveys.importers.kapture import export_kapture
    from scenesig.surveys.run import read_run

    _refuse_existing(args.out, args.overwrite)
    out = export_kapture(read_run(args.run), args.out, camera_id=args.camera_id, overwrite=args.overwrite)
    print(json.dumps({"kapture": str(out)}))
    return 0


def _numbers(counts):
    def parse(text: str) -> list[float]:
        try:
            v = [float(x) for x in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: comma-separated numbers") from None
        if len(v) not in counts:
            raise argparse.ArgumentTypeError(f"needs {' or '.join(map(str, counts))} numbers, got {len(v)}")
        return v
    return parse


def _extrinsic(text: str):
    """--extrinsic x,y,z,qx,qy,qz,qw -> the 4x4 T_vehicle_camera."""
    from scenesig.surveys.geometry import xyzquat_to_pose

    v = _numbers((7,))(text)
    if sum(q * q for q in v[3:]) < 1e-12:
        raise argparse.ArgumentTypeError("zero quaternion")
    return xyzquat_to_pose(v)


def run_rosbag(args) -> int:
    from scenesig.surveys.importers.rosbag import import_rosbag, list_topics, suggest_arguments

    if args.list:
        listing = list_topics(args.bag)
        print(f"{', '.join(listing['bag'])}: {listing['format']}, {listing['duration_s']:.1f} s")
        rows = [(t, str(d["type"]).replace("/msg/", "/"), str(d["count"]),
                 f"{d['rate_hz']:.2f} Hz" if d["rate_hz"] else "-") for t, d in listing["topics"].items()]
        widths = [max(len(r[i]) for r in rows + [("topic", "type", "count", "rate")]) for i in range(4)]
        for r in [("topic", "type", "count", "rate (record times)")] + rows:
            print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        if listing["tf"]:
            print("tf frames (parent -> child): "
                  + ", ".join(f"{v['parent']} -> {c}" for c, v in listing["tf"].items()))
        args_, notes = suggest_arguments(listing)
        print("suggested:\n  scenesig import rosbag " + " ".join(listing["bag"]) + " " + " ".join(args_) + " --out RUN")
        for line in notes:
            print("  " + line)
        return 0
    if args.out is None:
        args._parser.error("--out RUN is required (or --list)")
    if args.image_topic is None:
        args._parser.error("--image-topic is required (--list shows the topics)")
    conf = _conf(args, image_topic=args.image_topic, camera_info_topic=args.camera_info_topic,
                 odom_topic=args.odom_topic, gt_topic=args.gt_topic, truth_topic=args.truth_topic,
                 intrinsics=args.intrinsics, extrinsic=args.extrinsic, base_frame=args.base_frame,
                 odom_frame=args.odom_frame, gt_frame=args.gt_frame, stamps=args.stamps, rectified=args.rectified,
                 skip_corrupt=args.skip_corrupt)
    if args.odom_topic is None and args.gt_topic is None:
        args._parser.error("give --odom-topic, --gt-topic or both (a survey run needs odometry, and build-map "
                           "needs INS poses)")
    if args.camera_info_topic is None and args.intrinsics is None:
        args._parser.error("give --camera-info-topic or --intrinsics (the camera's calibration)")
    return _summary(import_rosbag, args.bag, args, conf)


def run_export_rosbag(args) -> int:
    from pathlib import Path

    import numpy as np

    from scenesig.surveys.errors import DataError
    from scenesig.surveys.importers.rosbag import (
        export_trajectory_bag,
        read_bag_poses,
        read_pose_covariances,
        write_run_bag,
    )
    from scenesig.surveys.run import read_run
    from scenesig.surveys.tum import read_tum

    src, out = Path(args.source), Path(args.out)
    fmt = args.format or ("ros1" if out.suffix == ".bag" else "mcap" if out.suffix == ".mcap" else "ros2")
    _refuse_existing(out, args.overwrite)
    t0 = time.perf_counter()
    if (src / "run.toml").is_file():
        run = read_run(src)
        try:
            write_run_bag(run, out, fmt, images=args.images, odometry_as=args.odometry_as, overwrite=args.overwrite)
        except ValueError as exc:
            raise DataError(out, str(exc)) from None
        times, poses, topic, cov, what = run.odometry_times, run.odometry_poses, \
            ("/odom" if args.odometry_as == "odometry" else "/tf"), None, "survey run"
    elif (src / "trajectory.tum").is_file():
        times, poses = read_tum(src / "trajectory.tum")
        cov = None
        if (src / "covariances.csv").is_file():
            cov, have = read_pose_covariances(src / "covariances.csv", times, poses)
        try:
            export_trajectory_bag(times, poses, out, fmt, covariances=cov, topic=args.topic, frame_id=args.frame_id,
                                  child_frame_id=args.child_frame_id, overwrite=args.overwrite)
        except ValueError as exc:
            raise DataError(out, str(exc)) from None
        topic, what = args.topic, "localisation"
    else:
        raise DataError(src, "neither a localisation folder (trajectory.tum) nor a survey run (run.toml)")
    seconds = time.perf_counter() - t0
    # read back with rosbags: the bag's poses must be the source's
    bt, bp, bc = read_bag_poses(out, topic)
    same_times = len(bt) == len(times) and bool(np.array_equal(bt, np.asarray(times)))
    dpos = float(np.abs(bp[:, :3, 3] - poses[:, :3, 3]).max()) if same_times else None
    drot = float(np.abs(bp[:, :3, :3] - poses[:, :3, :3]).max()) if same_times else None
    print(json.dumps({"bag": str(out), "format": fmt, "source": what, "poses": int(len(times)), "topic": topic,
                      "with_covariance": int(have.sum()) if cov is not None else 0, "seconds": round(seconds, 3),
                      "read_back": {"same_times": same_times, "max_position_difference_m": dpos,
                                    "max_rotation_matrix_difference": drot}}, indent=1))
    if not same_times or dpos > 1e-9 or drot > 1e-9:
        raise DataError(out, "the written bag does not read back with the source's poses")
    return 0
