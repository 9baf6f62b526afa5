"""``scenesig import kitti-raw|kapture|tum-rgbd|euroc`` and ``scenesig export kapture``: the formats users hold.

The parsers only; the work is in :mod:`surveys.importers` (one module per format, conf dicts).
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


def _conditions(text: str) -> list[str]:
    return [c.strip() for c in text.split(",") if c.strip()]


def _common(p, noise_help: str) -> None:
    p.add_argument("--out", required=True, metavar="RUN", help="survey-run folder to write (atomically)")
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

    x = exp.add_parser("kapture", help="a survey run as a kapture folder (text format 1.1)",
                       description="Export a survey run as kapture: sensors, rigs, trajectories, records_camera, "
                                   "and scenesig's odometry/GPS records; atomically.")
    x.add_argument("run", metavar="RUN")
    x.add_argument("--out", required=True, metavar="DIR")
    x.add_argument("--camera-id", default="cam", help="sensor id of the camera (default cam)")
    x.add_argument("--overwrite", action="store_true", help="replace DIR if it exists (default: refuse)")
    x.set_defaults(_run=run_export_kapture)


def _conf(args, **extra) -> dict:
    conf = {"name": args.name, "odometry_noise": args.odometry_noise, "odometry_seed": args.odometry_seed, **extra}
    if args.conditions is not None:
        conf["conditions"] = args.conditions
    return conf


def _refuse_existing(out, overwrite: bool) -> None:
    from pathlib import Path

    from surveys.errors import DataError

    if Path(out).exists() and not overwrite:
        raise DataError(out, "already exists; pass --overwrite to replace it")


def _summary(fn, source, args, conf) -> int:
    from surveys.run import read_run

    _refuse_existing(args.out, args.overwrite)
    t0 = time.perf_counter()
    out = fn(source, args.out, conf, overwrite=args.overwrite, photometric=args.photometric)
    seconds = time.perf_counter() - t0
    run = read_run(out, check_images=False)
    print(json.dumps({"run": str(out), "name": run.name, "frames": len(run), "seconds": round(seconds, 3),
                      "frames_per_second": round(len(run) / seconds, 1), "odometry_source": run.odometry_source,
                      "gaps": len(run.metadata.get("gaps", []))}, indent=1))
    return 0


def run_kitti_raw(args) -> int:
    from surveys.importers.kitti_raw import import_kitti_raw

    return _summary(import_kitti_raw, args.drive, args, _conf(args, camera=args.camera))


def run_kapture(args) -> int:
    from surveys.importers.kapture import import_kapture

    return _summary(import_kapture, args.kapture, args,
                    _conf(args, camera=args.camera, timestamp_unit=args.timestamp_unit))


def _intrinsics(text: str):
    """--intrinsics: a TUM preset name, or fx,fy,cx,cy[,k1,k2,p1,p2[,k3]] for a 640x480 camera."""
    from surveys.geometry import Camera

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
    from surveys.importers.tum_rgbd import import_tum_rgbd

    return _summary(import_tum_rgbd, args.folder, args, _conf(args, intrinsics=args.intrinsics))


def run_euroc(args) -> int:
    from surveys.importers.euroc import import_euroc

    return _summary(import_euroc, args.folder, args, _conf(args, camera=args.camera))


def run_export_kapture(args) -> int:
    from surveys.importers.kapture import export_kapture
    from surveys.run import read_run

    _refuse_existing(args.out, args.overwrite)
    out = export_kapture(read_run(args.run), args.out, camera_id=args.camera_id, overwrite=args.overwrite)
    print(json.dumps({"kapture": str(out)}))
    return 0
