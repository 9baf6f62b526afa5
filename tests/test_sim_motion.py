"""Vehicle motion, odometry and INS error statistics match what surveys.sim.motion documents."""
import numpy as np
import pytest

from scenesig.surveys.geometry import invert
from scenesig.surveys.sim.motion import LANE_CENTRE, InsModel, drift_per_100m, ins, odometry, plan_drive
from scenesig.surveys.sim.noise import rng_for
from scenesig.surveys.sim.world import World

N_RUNS = 30


@pytest.fixture(scope="module")
def demo_world():
    return World("demo", 0)


@pytest.fixture(scope="module")
def drives(demo_world):
    return [plan_drive(demo_world.route, rng_for(7, "test-drive", k), demo_world.crossings) for k in range(N_RUNS)]


def _odometry_drift(drives, factor):
    H, T = [], []
    for k, dr in enumerate(drives):
        t = np.arange(0.0, dr.duration, 0.05)
        P = dr.pose(t)
        Q = odometry(dr, t, rng_for(7, "test-odo", factor, k), factor)
        h, tr = drift_per_100m(P, Q, stride=20)
        H.extend(h)
        T.extend(tr)
    return np.sqrt(np.mean(np.square(H))), np.sqrt(np.mean(np.square(T)))


def test_day_odometry_drift_per_100m(drives):
    h, t = _odometry_drift(drives, 1.0)
    assert 0.47 * 0.75 <= h <= 0.47 * 1.25, f"heading drift {h:.3f} deg/100 m (documented 0.47)"
    assert 0.5 <= t <= 1.0, f"translation drift {t:.2f} %/100 m (documented 0.5-1.0)"


def test_night_odometry_drift_scales_with_factor(drives):
    h, t = _odometry_drift(drives, 3.0)
    assert 3 * 0.47 * 0.75 <= h <= 3 * 0.47 * 1.25, f"night heading drift {h:.3f} deg/100 m"
    assert 3 * 0.5 <= t <= 3 * 1.0, f"night translation drift {t:.2f} %/100 m"


def test_odometry_increments_are_close_to_truth_over_one_step(drives):
    dr = drives[0]
    t = np.arange(0.0, dr.duration, 0.05)
    P = dr.pose(t)
    Q = odometry(dr, t, rng_for(1), 1.0)
    assert np.allclose(Q[0], np.eye(4))
    dP = invert(P[:-1]) @ P[1:]
    dQ = invert(Q[:-1]) @ Q[1:]
    step = np.linalg.norm(dP[:, :3, 3], axis=1)
    err = np.linalg.norm(dQ[:, :3, 3] - dP[:, :3, 3], axis=1)
    assert np.median(err) < 0.02 and np.all(err < 0.02 + 0.05 * step + 0.05)


def test_ins_offset_and_drift(demo_world, drives):
    m = InsModel()
    offsets, drift = [], []
    for k, dr in enumerate(drives):
        t = np.arange(0.0, dr.duration, 0.1)
        P_ins, err = ins(dr, t, rng_for(7, "test-ins", k))
        P = dr.pose(t)
        # the written pose differs from truth by the error process (+ 2 cm white noise)
        assert np.all(np.linalg.norm(P_ins[:, :3, 3] - P[:, :3, 3] - err, axis=1) < 0.1)
        offsets.extend(err[0, :2])
        s = dr.s(t)
        for i in range(0, len(t), 25):
            j = np.searchsorted(s, s[i] + 100.0)
            if j < len(t):
                drift.extend(err[j, :2] - err[i, :2])
    off_rms = np.sqrt(np.mean(np.square(offsets)))
    drift_rms = np.sqrt(np.mean(np.square(drift)))
    assert m.offset_xy * 0.7 <= off_rms <= m.offset_xy * 1.3, f"INS offset RMS {off_rms:.2f} m per axis"
    assert m.rw_xy_sqrt100m * 0.75 <= drift_rms <= m.rw_xy_sqrt100m * 1.25, f"INS drift {drift_rms:.3f} m/100 m"


def test_drive_lateral_offset_speed_and_stops(drives):
    for dr in drives:
        t = np.arange(0.0, dr.duration, 0.05)
        d = dr.lateral_offset(t)
        assert np.all(np.abs(d - LANE_CENTRE) <= 1.0 + 1e-9)
        assert np.ptp(d) > 0.3  # it does vary
        v = dr.speed(t[(t > 1.2) & (t < dr.duration - 1.2)])
        assert v.max() <= 15.0
        assert len(dr.stops) >= 1
        tt = t[(t > 1.2) & (t < dr.duration - 1.2)]
        slow = v < 3.0
        s_slow = dr.s(tt[slow])
        stop_s = np.array([s for s, _ in dr.stops])
        # below 3 m/s only while braking for / pulling away from a stop
        assert np.all(np.min(np.abs(s_slow[:, None] - stop_s[None, :]), axis=1) < 40.0)
        # the vehicle stands still for the dwell time
        assert (v < 0.05).sum() * 0.05 >= min(dw for _, dw in dr.stops) - 0.2


def test_truth_poses_are_rigid_and_follow_the_path(drives):
    dr = drives[1]
    t = np.arange(1.0, dr.duration - 1.0, 0.05)
    P = dr.pose(t)
    R = P[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    moving = dr.speed(t) > 2.0
    vel = np.gradient(P[:, :3, 3], t, axis=0)
    course = np.arctan2(vel[:, 1], vel[:, 0])
    yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    dev = np.degrees(np.abs(np.angle(np.exp(1j * (course - yaw)))))
    assert np.all(dev[moving] < 1.0)
    assert np.all(np.degrees(np.abs(np.arcsin(np.clip(P[:, 2, 0], -1, 1)))) < 1.5)  # pitch stays small
