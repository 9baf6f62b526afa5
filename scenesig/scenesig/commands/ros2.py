"""``scenesig ros2 node --map MAP``: the localiser as a ROS 2 node (:mod:`scenesig.ros2_node`; needs ROS 2's rclpy)."""
from __future__ import annotations

import argparse


def _datum(text: str) -> tuple[float, float, float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected lat,lon[,alt]") from None
    if len(v) not in (2, 3) or not (-90 <= v[0] <= 90 and -180 <= v[1] <= 180):
        raise argparse.ArgumentTypeError(f"{text!r}: expected lat,lon[,alt] in degrees (and metres)")
    return (v[0], v[1], v[2] if len(v) == 3 else 0.0)


def register(groups) -> None:
    from scenesig.commands.importers import _extrinsic

    p = groups["ros2"].add_parser(
        "node", help="localise a robot against a map as a ROS 2 node (nav_msgs/Odometry in map, map -> odom TF)",
        description="Subscribe to a camera (raw or compressed), its CameraInfo, odometry and optionally a GNSS "
                    "prior; publish the localised pose (nav_msgs/Odometry in the map frame, with covariance), the "
                    "map -> odom transform (AMCL's convention) and a DiagnosticArray with the integrity state. "
                    "Needs a ROS 2 install (rclpy; see docs/ros2.md).")
    p.add_argument("--map", required=True, metavar="MAP", help="the map folder")
    p.add_argument("--method", default="signatures", help="localisation method (default signatures)")
    p.add_argument("--preset", default=None, help="settings preset of the localise stage")
    p.add_argument("--image-topic", default="/camera/image_raw",
                   help="sensor_msgs/Image, or CompressedImage when the name ends in 'compressed'")
    p.add_argument("--camera-info-topic", default="/camera/camera_info")
    p.add_argument("--odom-topic", default="/odom", help="nav_msgs/Odometry (odom -> base_link)")
    p.add_argument("--navsat-topic", default=None, help="optional sensor_msgs/NavSatFix prior (needs --datum)")
    p.add_argument("--datum", type=_datum, default=None, metavar="LAT,LON[,ALT]",
                   help="WGS-84 position of the map's origin (for --navsat-topic)")
    p.add_argument("--gnss-pose-topic", default=None,
                   help="optional INS/GNSS pose prior in the map frame (nav_msgs/Odometry)")
    p.add_argument("--extrinsic", type=_extrinsic, default=None, metavar="x,y,z,qx,qy,qz,qw",
                   help="the camera's pose on the robot, T_base_camera (default: from /tf_static)")
    p.add_argument("--rectified", action="store_true", help="use CameraInfo P (rectified images)")
    p.add_argument("--map-frame", default="map")
    p.add_argument("--odom-frame", default="odom")
    p.add_argument("--base-frame", default="base_link")
    p.add_argument("--output-topic", default="/scenesig/odometry", help="the published nav_msgs/Odometry")
    p.set_defaults(_run=run, _parser=p)


def run(args) -> int:
    if args.navsat_topic and args.datum is None:
        args._parser.error("--navsat-topic needs --datum LAT,LON[,ALT] (the map origin's WGS-84 position)")
    from scenesig.ros2_node import run as run_node

    return run_node(args)
