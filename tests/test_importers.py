"""Importers: KITTI raw, kapture (both ways), TUM RGB-D, EuRoC -- round trips, geometry, bad input."""
import datetime as dt
import filecmp
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROOT, SHARED_DATA, make_run

from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, invert, make_pose, rot_x, rot_y, rot_z, yaw_of
from scenesig.surveys.importers import euroc, kapture, kitti_raw, tum_rgbd
from scenesig.surveys.importers.common import planar_dead_reckoning
from scenesig.surveys.importers.photometric import darken
from scenesig.surveys.run import read_run, write_run

KITTI = SHARED_DATA / "kitti" / "2011_09_26_snippet"


@pytest.fixture(scope="module")
def kitti_drive():
    if not KITTI.is_dir():
        pytest.skip(f"real data not found at {KITTI} (KITTI tests need ../shared/data beside the project)")
    return KITTI


# --------------------------------------------------------------------------------------- a synthetic KITTI drive
def _kitti_time(t: float) -> str:
    base = dt.datetime(2011, 9, 26, 13, 4, 32, tzinfo=dt.timezone.utc) + dt.timedelta(seconds=t)
    return base.strftime("%Y-%m-%d %H:%M:%S.") + f"{round((t % 1) * 1e9):09d}"


def make_kitti_drive(root: Path, n: int = 6, size=(64, 32), speed=5.0, drop=()) -> Path:
    """A tiny KITTI raw drive driving due east at ``speed`` m/s; frames in ``drop`` are missing."""
    w, h = size
    root.mkdir(parents=True)
    f, cx, cy, base = 50.0, w / 2, h / 2, 0.5
    (root / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\n"
        "R_rect_00: 1 0 0 0 1 0 0 0 1\n"
        f"S_rect_02: {w} {h}\nP_rect_02: {f} 0 {cx} 0 0 {f} {cy} 0 0 0 1 0\n"
        f"S_rect_03: {w} {h}\nP_rect_03: {f} 0 {cx} {-f * base} 0 {f} {cy} 0 0 0 1 0\n")
    # velodyne: x forward, y left, z up, 1 m above and 0.2 m ahead of the IMU; camera 0 at the velodyne
    R_cam_velo = CAMERA_FROM_VEHICLE_AXES.T
    (root / "calib_velo_to_cam.txt").write_text(
        "calib_time: x\nR: " + " ".join(map(str, R_cam_velo.ravel())) + "\nT: 0 0 0\n")
    (root / "calib_imu_to_velo.txt").write_text("calib_time: x\nR: 1 0 0 0 1 0 0 0 1\nT: -0.2 0 -1.0\n")
    lat0, lon0 = 49.0, 8.4
    s = math.cos(math.radians(lat0))
    for cam in ("image_02", "image_03"):
        (root / cam / "data").mkdir(parents=True)
        (root / cam / "timestamps.txt").write_text("".join(_kitti_time(0.1 * i) + "\n" for i in range(n)))
    (root / "oxts" / "data").mkdir(parents=True)
    (root / "oxts" / "timestamps.txt").write_text("".join(_kitti_time(0.1 * i + 0.004) + "\n" for i in range(n)))
    img = np.zeros((h, w, 3), np.uint8)
    for i in range(n):
        if i in drop:
            continue
        for cam in ("image_02", "image_03"):
            img[:] = 10 * i
            cv2.imwrite(str(root / cam / "data" / f"{i:010d}.png"), img)
        lon = lon0 + math.degrees(speed * 0.1 * i / (s * kitti_raw.EARTH_RADIUS))
        vals = [lat0, lon, 100.0, 0, 0, 0, 0, speed, speed, 0, 0] + [0] * 11 + [0.0] + [0.1, 0.1, 4, 10, 4, 4, 0]
        assert len(vals) == 30
        (root / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(map(str, vals)) + "\n")
    return root


def test_kitti_synthetic_geometry(tmp_path):
    drive = make_kitti_drive(tmp_path / "drive")
    out = kitti_raw.import_kitti_raw(drive, tmp_path / "run", {"camera": 3}, progress=False)
    run = read_run(out)
    assert len(run) == 6 and run.camera.fx == 50.0 and run.camera.distortion == ()
    # east at 5 m/s: 0.5 m per packet along world x, heading 0 (yaw 0 = east)
    np.testing.assert_allclose(run.groundtruth_poses[:, 0, 3], 0.5 * np.arange(6), atol=1e-6)
    np.testing.assert_allclose(run.groundtruth_poses[:, 1:3, 3], 0, atol=1e-6)
    # camera 3 = camera 0 shifted 0.5 m right; camera 0 sits 0.2 m ahead of and 1 m above the IMU, looking forward
    np.testing.assert_allclose(run.T_vehicle_camera[:3, 3], [0.2, -0.5, 1.0], atol=1e-9)
    np.testing.assert_allclose(run.T_vehicle_camera[:3, :3], CAMERA_FROM_VEHICLE_AXES, atol=1e-9)
    # odometry: the velocities integrated, planar
    np.testing.assert_allclose(run.odometry_poses[:, 0, 3], 0.5 * np.arange(6), atol=1e-5)  # float64 clock at 1.3e9 s
    assert "NOT independent of the INS" in run.metadata["odometry"]
    with pytest.raises(ValueError, match="unknown kitti_raw import option"):
        kitti_raw.load_kitti_raw(drive, {"camra": 3})


def test_kitti_gaps_kept_not_interpolated(tmp_path):
    drive = make_kitti_drive(tmp_path / "drive", n=8, drop=(3,))
    run = read_run(kitti_raw.import_kitti_raw(drive, tmp_path / "run", {"camera": 2}, progress=False))
    assert [Path(f).name for f in run.frame_files] == [f"{i:010d}.png" for i in (0, 1, 2, 4, 5, 6, 7)]
    assert len(run.groundtruth_times) == 7 and run.metadata["dropped_frames"] == 1
    assert len(run.metadata["gaps"]) == 1
    t0, t1 = run.metadata["gaps"][0]
    assert t1 - t0 == pytest.approx(0.2, abs=1e-6)


@pytest.mark.parametrize("breakage, where, what", [
    ("missing_calib", "calib_imu_to_velo.txt", "not found"),
    ("truncated_oxts", "0000000002.txt:1", "expected 30 values"),
    ("mismatched_counts", "oxts/data", "frame counts do not match"),
    ("short_timestamps", "image_02/timestamps.txt:3", "frame counts do not match"),
    ("missing_P", "calib_cam_to_cam.txt", "missing P_rect_02"),
    ("bad_timestamp", "oxts/timestamps.txt:2", "not a timestamp"),
])
def test_kitti_bad_input_names_file_and_line(tmp_path, breakage, where, what):
    drive = make_kitti_drive(tmp_path / "drive")
    if breakage == "missing_calib":
        (drive / "calib_imu_to_velo.txt").unlink()
    elif breakage == "truncated_oxts":
        p = drive / "oxts" / "data" / "0000000002.txt"
        p.write_text(" ".join(p.read_text().split()[:17]))
    elif breakage == "mismatched_counts":
        (drive / "oxts" / "data" / "0000000004.txt").unlink()
    elif breakage == "short_timestamps":
        p = drive / "image_02" / "timestamps.txt"
        p.write_text("".join(p.read_text().splitlines(True)[:3]))
    elif breakage == "missing_P":
        p = drive / "calib_cam_to_cam.txt"
        p.write_text("".join(line for line in p.read_text().splitlines(True) if not line.startswith("P_rect_02")))
    elif breakage == "bad_timestamp":
        p = drive / "oxts" / "timestamps.txt"
        lines = p.read_text().splitlines(True)
        lines[1] = "2011-09-26 13:04:xx.1\n"
        p.write_text("".join(lines))
    with pytest.raises(DataError) as exc:
        kitti_raw.import_kitti_raw(drive, tmp_path / "run", {"camera": 2}, progress=False)
    assert where in str(exc.value) and what in str(exc.value)
    assert not (tmp_path / "run").exists()


def test_failed_import_leaves_nothing_and_keeps_the_old_run(tmp_path):
    drive = make_kitti_drive(tmp_path / "drive")
    out = kitti_raw.import_kitti_raw(drive, tmp_path / "run", {"camera": 2}, progress=False)
    before = (out / "frames.csv").read_bytes()
    (drive / "image_02" / "data" / "0000000004.png").write_bytes(b"GIF89a not what it claims")
    with pytest.raises(DataError, match="0000000004.png: not a decodable"):
        kitti_raw.import_kitti_raw(drive, out, {"camera": 2, "name": "other"}, overwrite=True, progress=False)
    assert (out / "frames.csv").read_bytes() == before and read_run(out).name == "drive_cam2"
    assert not out.with_name("run.tmp").exists() and not out.with_name("run.old").exists()
    with pytest.raises(FileExistsError):
        kitti_raw.import_kitti_raw(drive, out, {"camera": 3}, progress=False)
    # a truncated image (which OpenCV would decode half grey without complaint) is named too
    p = drive / "image_02" / "data" / "0000000004.png"
    good = cv2.imencode(".png", np.full((32, 64, 3), 7, np.uint8))[1].tobytes()
    p.write_bytes(good[: len(good) - 20])
    with pytest.raises(DataError, match="0000000004.png: truncated PNG"):
        kitti_raw.import_kitti_raw(drive, tmp_path / "other", {"camera": 2}, progress=False)
    jpg = drive / "image_02" / "data" / "0000000004.jpg"
    p.unlink()
    data = cv2.imencode(".jpg", np.full((32, 64, 3), 7, np.uint8))[1].tobytes()
    jpg.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="0000000004.jpg: truncated JPEG"):
        kitti_raw.import_kitti_raw(drive, tmp_path / "other", {"camera": 2}, progress=False)
    assert not (tmp_path / "other").exists() and not (tmp_path / "other.tmp").exists()


def test_planar_dead_reckoning_follows_an_arc():
    t = np.linspace(0, 10, 201)
    v, w = 4.0, 0.15  # m/s, rad/s: a 26.7 m radius circle
    P = planar_dead_reckoning(t, np.full_like(t, v), np.zeros_like(t), np.full_like(t, w))
    th = w * t
    np.testing.assert_allclose(P[:, 0, 3], v / w * np.sin(th), atol=2e-3)
    np.testing.assert_allclose(P[:, 1, 3], v / w * (1 - np.cos(th)), atol=2e-3)
    np.testing.assert_allclose(yaw_of(P), th, atol=1e-9)


# --------------------------------------------------------------------------------------- the real drive
@pytest.fixture(scope="module")
def kitti_runs(kitti_drive, tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti")
    return {c: read_run(kitti_raw.import_kitti_raw(kitti_drive, root / f"cam{c}", {"camera": c}, progress=False))
            for c in (2, 3)}


def _devkit_poses(oxts_dir: Path) -> np.ndarray:
    """The KITTI devkit's convertOxtsToPose, written out again independently (positions relative to frame 0)."""
    rows = [np.array(p.read_text().split()[:6], float) for p in sorted(oxts_dir.glob("*.txt"))]
    er, scale = 6378137.0, np.cos(rows[0][0] * np.pi / 180.0)
    out = []
    for lat, lon, alt, roll, pitch, yaw in rows:
        t = [scale * lon * np.pi * er / 180, scale * er * np.log(np.tan((90 + lat) * np.pi / 360)), alt]
        out.append(make_pose(rot_z(yaw) @ rot_y(pitch) @ rot_x(roll), t))
    out = np.array(out)
    out[:, :3, 3] -= out[0, :3, 3]
    return out


def test_kitti_groundtruth_matches_oxts_within_1cm(kitti_drive, kitti_runs):
    run = kitti_runs[2]
    ref = _devkit_poses(kitti_drive / "oxts" / "data")
    assert len(run.groundtruth_poses) == len(ref) == 91
    assert np.abs(run.groundtruth_poses[:, :3, 3] - ref[:, :3, 3]).max() < 0.01
    assert np.abs(run.groundtruth_poses[:, :3, :3] - ref[:, :3, :3]).max() < 1e-9
    # through the TUM file on disk (what evo reads) as well
    from scenesig.surveys.tum import read_tum
    _, P = read_tum(run.root / "groundtruth.tum")
    assert np.abs(P[:, :3, 3] - ref[:, :3, 3]).max() < 0.01
    # the data README: about 33.5 m with a 21 deg turn
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum()
    assert 33.0 < steps < 34.0
    assert abs(np.degrees(yaw_of(P[-1]) - yaw_of(P[0]))) == pytest.approx(21.1, abs=0.5)
    # gps.csv in the same frame, frames on the camera clock, 63 trailing timestamps without images counted
    np.testing.assert_allclose(run.gps[:, 1:], P[:, :3, 3], atol=1e-9)
    assert len(run) == 91 and run.metadata["trailing_timestamps_without_images"] == 63
    assert run.rates["camera_hz"] == pytest.approx(9.68, abs=0.05)
    assert run.metadata["oxts_pos_accuracy_m"]["median"] == pytest.approx(0.45, abs=0.01)


def test_kitti_stereo_extrinsics(kitti_runs):
    T2, T3 = kitti_runs[2].T_vehicle_camera, kitti_runs[3].T_vehicle_camera
    # both look forward (camera z along vehicle x); camera 3 is 0.54 m to the right (vehicle -y) of camera 2
    assert T2[:3, 2] @ [1, 0, 0] > 0.999 and T3[:3, 2] @ [1, 0, 0] > 0.999
    d = T3[:3, 3] - T2[:3, 3]
    assert np.linalg.norm(d) == pytest.approx(0.532, abs=0.01) and d[1] < -0.5
    # and the cameras sit ~1.08 m ahead of and ~0.73 m above the IMU (KITTI's setup figure)
    assert T2[0, 3] == pytest.approx(1.08, abs=0.05) and T2[2, 3] == pytest.approx(0.73, abs=0.05)
    # a point 20 m ahead projects near the principal point's row in both (rectified pair: same row)
    P_v = np.array([21.0, -0.5, 0.73])
    uv2, _ = kitti_runs[2].camera.project((invert(T2) @ np.append(P_v, 1))[:3][None])
    uv3, _ = kitti_runs[3].camera.project((invert(T3) @ np.append(P_v, 1))[:3][None])
    assert abs(uv2[0, 1] - uv3[0, 1]) < 1.0 and uv2[0, 0] - uv3[0, 0] == pytest.approx(721.5 * 0.532 / 20, rel=0.05)


def _sampson_median(ra, ia, rb, ib, T_vc_b=None) -> float:
    """Median Sampson distance (px) of SIFT matches between two frames under the epipolar geometry that
    the OXTS poses and the imported calibration predict (no fitting: a wrong extrinsic shows)."""
    sift = cv2.SIFT_create(1500)
    (ka, da), (kb, db) = (sift.detectAndCompute(r.image(i, gray=True), None) for r, i in ((ra, ia), (rb, ib)))
    good = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
    xa = np.array([ka[m.queryIdx].pt + (1.0,) for m in good])
    xb = np.array([kb[m.trainIdx].pt + (1.0,) for m in good])
    T_wa = ra.pose_at(ra.frame_times[ia]) @ ra.T_vehicle_camera
    T_wb = rb.pose_at(rb.frame_times[ib]) @ (rb.T_vehicle_camera if T_vc_b is None else T_vc_b)
    T = invert(T_wa) @ T_wb
    t = T[:3, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T[:3, :3]
    F = np.linalg.inv(ra.camera.K).T @ E @ np.linalg.inv(rb.camera.K)
    Fb, Fa = xb @ F.T, xa @ F
    d2 = np.sum(xa * Fb, axis=1) ** 2 / (Fb[:, 0] ** 2 + Fb[:, 1] ** 2 + Fa[:, 0] ** 2 + Fa[:, 1] ** 2)
    assert len(good) > 100
    return float(np.median(np.sqrt(d2)))


def test_kitti_calibration_chain_on_real_images(kitti_runs):
    """Camera 2 and camera 3 through the imported intrinsics, extrinsics and OXTS poses agree with SIFT
    matches: at the same instant (the calibration chain alone) and 5 frames (1.8 m) apart (with OXTS).
    Measured 0.15 px and 0.9 px; a 1 deg yaw error in camera 3's extrinsic makes the second 3.2 px."""
    r2, r3 = kitti_runs[2], kitti_runs[3]
    assert _sampson_median(r2, 40, r3, 40) < 0.5
    assert _sampson_median(r2, 40, r3, 45) < 1.5
    assert _sampson_median(r2, 40, r3, 45, make_pose(rot_z(np.radians(1.0))) @ r3.T_vehicle_camera) > 2.0


def test_kitti_odometry_noise_drifts_and_repeats(kitti_drive, tmp_path):
    run, _ = kitti_raw.load_kitti_raw(kitti_drive, {"camera": 2})
    noisy1, _ = kitti_raw.load_kitti_raw(kitti_drive, {"camera": 2, "odometry_noise": 3.0, "odometry_seed": 1})
    noisy2, _ = kitti_raw.load_kitti_raw(kitti_drive, {"camera": 2, "odometry_noise": 3.0, "odometry_seed": 1})
    np.testing.assert_array_equal(noisy1.odometry_poses, noisy2.odometry_poses)
    a, b = run.odometry_increments(), noisy1.odometry_increments()
    assert not np.allclose(a[:, :3, 3], b[:, :3, 3], atol=1e-4)
    assert noisy1.odometry_source == "oxts_velocities+noise" and "perturbed" in noisy1.metadata["odometry"]
    # the clean signal: planar, within 10 % in length and 3 deg in heading of the OXTS poses over the drive
    G = invert(run.groundtruth_poses[0]) @ run.groundtruth_poses[-1]
    O = invert(run.odometry_poses[0]) @ run.odometry_poses[-1]
    assert np.linalg.norm(O[:2, 3]) == pytest.approx(np.linalg.norm(G[:2, 3]), rel=0.1)
    assert abs(np.degrees(yaw_of(O) - yaw_of(G))) < 3.0
    assert np.all(run.odometry_poses[:, 2, 3] == 0)


def test_night_transform_darkens_deterministically(kitti_drive, tmp_path):
    img = cv2.imread(str(kitti_drive / "image_03" / "data" / "0000000040.jpg"))
    d1, d2 = darken(img, 40), darken(img, 40)
    np.testing.assert_array_equal(d1, d2)
    assert d1.mean() < 0.3 * img.mean() and not np.array_equal(darken(img, 41), d1)
    drive = make_kitti_drive(tmp_path / "drive")
    run = read_run(kitti_raw.import_kitti_raw(drive, tmp_path / "night", {"camera": 3, "conditions": ["night"]},
                                              photometric="night", progress=False))
    assert run.conditions == ["night"] and "not real night" in run.metadata["photometric_transform"]


# --------------------------------------------------------------------------------------- kapture
def _same_run(a, b, tol=1e-12):
    assert (a.name, a.conditions, a.camera, a.odometry_source, a.rates, a.metadata) == \
           (b.name, b.conditions, b.camera, b.odometry_source, b.rates, b.metadata)
    np.testing.assert_allclose(a.T_vehicle_camera, b.T_vehicle_camera, atol=tol)
    for k in ("frame_times", "odometry_times", "groundtruth_times", "truth_times"):
        assert (getattr(a, k) is None) == (getattr(b, k) is None)
        if getattr(a, k) is not None:
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    for k in ("odometry_poses", "groundtruth_poses", "truth_poses", "gps"):
        assert (getattr(a, k) is None) == (getattr(b, k) is None)
        if getattr(a, k) is not None:
            np.testing.assert_allclose(getattr(a, k), getattr(b, k), atol=tol)
    assert a.frame_files == b.frame_files
    for f in a.frame_files:
        assert filecmp.cmp(a.root / f, b.root / f, shallow=False)


def test_kapture_round_trip_is_identical(tmp_path):
    run, images = make_run(n_frames=6)
    run.camera = type(run.camera)(50.0, 51.0, 31.5, 23.5, 64, 48, (0.1, -0.02, 0.001, 0.002))
    run.frame_times = run.frame_times + 1317042272.345808896  # large epoch times survive exactly
    for k in ("odometry_times", "groundtruth_times", "truth_times"):
        setattr(run, k, getattr(run, k) + 1317042272.345808896)
    run.gps[:, 0] += 1317042272.345808896
    src = read_run(write_run(run, tmp_path / "run", images=images))
    kapture.export_kapture(src, tmp_path / "kapture", progress=False)
    assert (tmp_path / "kapture" / "sensors" / "sensors.txt").read_text().startswith("# kapture format: 1.1\n")
    back = read_run(kapture.import_kapture(tmp_path / "kapture", tmp_path / "back", progress=False))
    _same_run(src, back)
    for f in ("frames.csv", "gps.csv"):
        assert (src.root / f).read_bytes() == (back.root / f).read_bytes()
    # --odometry-noise on a scenesig export drifts the recorded odometry (not silently ignored)
    noisy = read_run(kapture.import_kapture(tmp_path / "kapture", tmp_path / "noisy", {"odometry_noise": 2.0},
                                            progress=False))
    assert noisy.odometry_source == src.odometry_source + "+noise" and "perturbed" in noisy.metadata["odometry"]
    assert not np.allclose(noisy.odometry_increments(), src.odometry_increments(), atol=1e-6)
    # and export refuses to overwrite
    with pytest.raises(FileExistsError):
        kapture.export_kapture(src, tmp_path / "kapture", progress=False)


def test_kapture_round_trip_of_the_kitti_run(kitti_runs, tmp_path):
    src = kitti_runs[3]
    kapture.export_kapture(src, tmp_path / "k", progress=False)
    back = read_run(kapture.import_kapture(tmp_path / "k", tmp_path / "back", {"camera": "cam"}, progress=False))
    _same_run(src, back, tol=1e-9)


def _foreign_kapture(root: Path, n=4) -> np.ndarray:
    """A kapture as other tools write it: camera poses only (no rig), sequence-number timestamps."""
    s = root / "sensors"
    (s / "records_data" / "seq").mkdir(parents=True)
    (s / "sensors.txt").write_text("# kapture format: 1.1\n# sensor_device_id, name, sensor_type, [sensor_params]+\n"
                                   "c0, phone, camera, SIMPLE_RADIAL, 64, 48, 55.0, 32, 24, -0.05\n"
                                   "gps1, , gnss, EPSG:4326\n")
    T_wc = np.stack([make_pose(rot_z(0.1 * i) @ CAMERA_FROM_VEHICLE_AXES, [i, 0.5 * i, 1.2]) for i in range(n)])
    lines, recs = [], []
    for i in range(n):
        tx, ty, tz = invert(T_wc[i])[:3, 3]
        from scenesig.surveys.geometry import rot_to_quat
        qx, qy, qz, qw = rot_to_quat(invert(T_wc[i])[:3, :3])
        lines.append(f"{i}, c0, {qw}, {qx}, {qy}, {qz}, {tx}, {ty}, {tz}\n")
        recs.append(f"{i}, c0, seq/{i:03d}.jpg\n")
        cv2.imwrite(str(s / "records_data" / "seq" / f"{i:03d}.jpg"), np.full((48, 64, 3), 40 * i, np.uint8))
    (s / "trajectories.txt").write_text("# kapture format: 1.1\n" + "".join(lines))
    (s / "records_camera.txt").write_text("# kapture format: 1.1\n" + "".join(recs))
    return T_wc


def test_kapture_import_of_camera_poses_without_rig(tmp_path):
    T_wc = _foreign_kapture(tmp_path / "k")
    run = read_run(kapture.import_kapture(tmp_path / "k", tmp_path / "run", {"camera": "c0", "timestamp_unit": "s",
                                                                             "odometry_noise": 1.0}, progress=False))
    np.testing.assert_allclose(run.groundtruth_poses @ run.T_vehicle_camera, T_wc, atol=1e-9)
    np.testing.assert_array_equal(run.frame_times, [0.0, 1.0, 2.0, 3.0])
    assert run.camera.fx == run.camera.fy == 55.0 and run.camera.distortion == (-0.05, 0.0, 0.0, 0.0)
    assert run.odometry_source == "groundtruth+noise" and "NOT an independent sensor" in run.metadata["odometry"]
    assert run.frame_files[0] == "images/seq/000.jpg"


@pytest.mark.parametrize("breakage, where, what", [
    ("camera", "sensors.txt", "no camera 'nope'"),
    ("image", "records_camera.txt:3", "image not found"),
    ("pose", "trajectories.txt:3", "non-numeric"),
    ("version", "sensors.txt:1", "kapture format 2.0 not supported"),
])
def test_kapture_bad_input(tmp_path, breakage, where, what):
    _foreign_kapture(tmp_path / "k")
    s = tmp_path / "k" / "sensors"
    conf = {"camera": "c0", "timestamp_unit": "s"}
    if breakage == "camera":
        conf["camera"] = "nope"
    elif breakage == "image":
        (s / "records_data" / "seq" / "001.jpg").unlink()
    elif breakage == "pose":
        lines = (s / "trajectories.txt").read_text().splitlines(True)
        lines[2] = "1, c0, nan?, 0, 0, 0, 0, 0, 0\n"
        (s / "trajectories.txt").write_text("".join(lines))
    elif breakage == "version":
        (s / "sensors.txt").write_text((s / "sensors.txt").read_text().replace("1.1", "2.0", 1))
    with pytest.raises(DataError) as exc:
        kapture.import_kapture(tmp_path / "k", tmp_path / "run", conf, progress=False)
    assert where in str(exc.value) and what in str(exc.value)
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------------------- TUM RGB-D and EuRoC
def test_tum_rgbd_import(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg3_pioneer_test"
    (seq / "rgb").mkdir(parents=True)
    times = 1305031100.0 + 0.033 * np.arange(6)
    rgb = ["# color images", "# timestamp filename"]
    for t in times:
        cv2.imwrite(str(seq / "rgb" / f"{t:.6f}.png"), np.zeros((480, 640, 3), np.uint8))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
    (seq / "rgb.txt").write_text("\n".join(rgb) + "\n")
    gt_t = np.arange(times[1] - 0.001, times[-1] + 0.05, 0.01)  # the first image is before the ground truth
    T_wc = np.stack([make_pose(rot_z(0.2 * k) @ CAMERA_FROM_VEHICLE_AXES, [k, 0, 0.3]) for k in range(len(gt_t))])
    from scenesig.surveys.tum import format_tum
    (seq / "groundtruth.txt").write_text("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n"
                                         + format_tum(gt_t, T_wc))
    run = read_run(tum_rgbd.import_tum_rgbd(seq, tmp_path / "run", {"odometry_noise": 0.0}, progress=False))
    assert len(run) == 5 and run.metadata["frames_outside_groundtruth"] == 1
    assert run.camera == tum_rgbd.INTRINSICS["fr3"]
    np.testing.assert_allclose(run.groundtruth_poses @ run.T_vehicle_camera, T_wc, atol=1e-9)
    np.testing.assert_allclose(run.odometry_poses, run.groundtruth_poses, atol=1e-12)
    with pytest.raises(DataError, match="freiburg"):
        tum_rgbd.load_tum_rgbd(seq.rename(tmp_path / "unnamed"))


def test_euroc_import(tmp_path):
    mav = tmp_path / "MH_test" / "mav0"
    (mav / "cam0" / "data").mkdir(parents=True)
    (mav / "state_groundtruth_estimate0").mkdir(parents=True)
    T_bs = make_pose(rot_y(0.05) @ CAMERA_FROM_VEHICLE_AXES, [0.02, -0.06, 0.01])
    (mav / "cam0" / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: ["
        + ", ".join(repr(float(v)) for v in T_bs.ravel()) + "]\nrate_hz: 20\nresolution: [80, 48]\n"
        "camera_model: pinhole\nintrinsics: [45.6, 45.7, 36.7, 24.8] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 1.8e-05]\n")
    ticks = 1403636579763555584 + 50_000_000 * np.arange(5, dtype=np.int64)
    rows = ["#timestamp [ns],filename"]
    for t in ticks:
        cv2.imwrite(str(mav / "cam0" / "data" / f"{t}.png"), np.zeros((48, 80), np.uint8))
        rows.append(f"{t},{t}.png")
    (mav / "cam0" / "data.csv").write_text("\n".join(rows) + "\n")
    gt = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for k, t in enumerate(range(int(ticks[0]) - 5_000_000, int(ticks[-1]) + 10_000_000, 5_000_000)):
        gt.append(f"{t}, {0.01 * k}, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0, 0, 0, 0")
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(gt) + "\n")
    run = read_run(euroc.import_euroc(tmp_path / "MH_test", tmp_path / "run", progress=False))
    assert len(run) == 5 and run.camera.size == (80, 48) and len(run.camera.distortion) == 4
    np.testing.assert_allclose(run.T_vehicle_camera, T_bs, atol=1e-12)
    assert run.frame_times[1] - run.frame_times[0] == pytest.approx(0.05, abs=1e-6)
    assert run.frame_times[0] == float("1403636579.763555584")  # the nearest double, not ns * 1e-9
    # a truncated ground-truth line is named
    p = mav / "state_groundtruth_estimate0" / "data.csv"
    lines = p.read_text().splitlines(True)
    lines[3] = lines[3][:20] + "\n"
    p.write_text("".join(lines))
    with pytest.raises(DataError, match=r"state_groundtruth_estimate0/data.csv:4: expected at least 8"):
        euroc.load_euroc(tmp_path / "MH_test")


# --------------------------------------------------------------------------------------- command line
def _cli(argv):
    from scenesig import cli

    return cli.main(argv)


def test_cli_import_export(tmp_path, capsys):
    drive = make_kitti_drive(tmp_path / "drive")
    assert _cli(["import", "kitti-raw", str(drive), "--camera", "3", "--out", str(tmp_path / "run"),
                 "--odometry-noise", "1", "--conditions", "day,sunny"]) == 0
    assert '"frames": 6' in capsys.readouterr().out
    run = read_run(tmp_path / "run")
    assert run.conditions == ["day", "sunny"] and run.metadata["odometry_noise"] == 1.0
    assert _cli(["import", "kitti-raw", str(drive), "--out", str(tmp_path / "run")]) == 2
    assert "already exists; pass --overwrite" in capsys.readouterr().err
    assert _cli(["import", "kitti-raw", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 2
    assert "nowhere: KITTI raw drive folder not found" in capsys.readouterr().err
    assert _cli(["export", "kapture", str(tmp_path / "run"), "--out", str(tmp_path / "k")]) == 0
    assert _cli(["import", "kapture", str(tmp_path / "k"), "--out", str(tmp_path / "back")]) == 0
    _same_run(run, read_run(tmp_path / "back"))


# --------------------------------------------------------------------------------------- end to end (heavy)
@pytest.mark.heavy
@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="known miss: signatures' lateral median is 0.50 m against the 0.3 m target (a one-run "
                          "map's landmark depths); strict, so a fix shows up")
def test_kitti_end_to_end(kitti_drive, tmp_path):
    """Map from camera 2 (one run); camera 3 and a darkened camera 3 replayed. Targets (camera 3, signatures):
    lateral median <= 0.3 m, heading median <= 1 deg, no failure over the 33 m."""
    out = tmp_path / "kitti_drive.json"
    proc = subprocess.run([sys.executable, "-m", "scenesig.cli", "bench", "kitti-drive", str(kitti_drive), "--work",
                           str(tmp_path / "work"), "--json", str(out)], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    import json
    res = json.loads(out.read_text())
    s = res["replays"]["cam3"]["signatures"]
    assert s["lateral_median_m"] <= 0.3 and s["heading_median_deg"] <= 1.0 and s["failures"] == 0
    for method in ("orb", "sift"):
        assert method in res["replays"]["cam3_night"]
