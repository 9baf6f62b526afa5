"""A synthetic world for the localiser tests: a road on a hill, a map of places on it, one live run.

No images are needed by the synthetic weak localisers below (they read the run's exact truth), so the
run's frames are tiny; everything else -- odometry that drifts (including in height), INS/GPS with a
slowly wandering offset, places every 10 m with neighbours -- is what the pipeline sees on real data.
"""
from __future__ import annotations

import numpy as np

from scenesig.localiser.pipeline import Measurement, WeakLocaliser
from scenesig.localiser.solver import LocalisationConstraint, pose_exp
from scenesig.mapping.store import MapWriter, PlaceData
from scenesig.surveys.geometry import (
    CAMERA_FROM_VEHICLE_AXES,
    Camera,
    interpolate_poses,
    invert,
    make_pose,
    rot_y,
    rot_z,
)
from scenesig.surveys.run import SurveyRun, write_run

HZ = 20.0
SPEED = 9.0             # m/s: 0.45 m per frame, so 20 m is not a whole number of steps


def road(s):
    """Position (N,3) and rotation (N,3,3) of the road at arc lengths s: an S-bend over a hill."""
    s = np.asarray(s, float)
    psi = 0.35 * np.sin(s / 45.0)
    ds = 0.05
    grid = np.arange(0.0, s.max() + 2 * ds, ds)
    gpsi = 0.35 * np.sin(grid / 45.0)
    x = np.concatenate([[0.0], np.cumsum(np.cos(gpsi[:-1]) * ds)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(gpsi[:-1]) * ds)])
    z = 3.0 * np.sin(grid / 70.0)                  # a hill: slopes up to ~2.5 degrees
    px, py, pz = np.interp(s, grid, x), np.interp(s, grid, y), np.interp(s, grid, z)
    slope = np.arctan(3.0 / 70.0 * np.cos(s / 70.0))
    R = np.stack([rot_z(a) @ rot_y(-b) for a, b in zip(psi, slope)])
    return np.column_stack([px, py, pz]), R


def truth_poses(s):
    p, R = road(s)
    T = np.tile(np.eye(4), (len(s), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    return T


def make_live_run(folder, length_m=90.0, seed=0, odometry_bias=(0.0, 0.0, 4e-4, 0.01, 0.0, 0.0),
                  size=(32, 24), name="live", start_m=2.0, stamp_frames=False):
    """Write a live run driving ``length_m`` along the road; returns the SurveyRun read back.

    ``stamp_frames``: frame k's image holds ``k % 256`` and ``k // 256`` in its first two pixels (lossless
    PNG), so a stub that only sees images can tell which frame it is (:func:`frame_index`).

    Odometry: true increments perturbed by a per-step bias (rotation rad, translation m, GTSAM order)
    and white noise, so dead reckoning drifts; INS/GPS: truth with a slowly wandering offset
    (~0.3 m, ~0.3 deg).
    """
    from scenesig.surveys.run import read_run

    rng = np.random.default_rng(seed)
    n = int(round(length_m / SPEED * HZ)) + 1
    t = 100.0 + np.arange(n) / HZ
    s = start_m + SPEED * (t - t[0])
    truth = truth_poses(s)
    incs = invert(truth[:-1]) @ truth[1:]
    sig = np.array([2e-4, 2e-4, 2e-4, 2e-3, 2e-3, 2e-3])
    odo = [make_pose(rot_z(0.4), [50.0, -20.0, 7.0])]      # the odometry's own arbitrary frame
    for inc in incs:
        odo.append(odo[-1] @ inc @ pose_exp(np.asarray(odometry_bias) + rng.normal(0, 1, 6) * sig))
    odo = np.array(odo)
    ins = truth.copy()
    off = np.column_stack([0.3 * np.sin(t / 7.0 + seed), 0.3 * np.cos(t / 5.0 + seed), 0.1 * np.sin(t / 3.0)])
    ins[:, :3, 3] += off
    ins = np.array([T @ make_pose(rot_z(np.radians(0.3) * np.sin(ti / 6.0))) for T, ti in zip(ins, t)])
    w, h = size
    cam = Camera(w * 0.8, w * 0.8, w / 2 - 0.5, h / 2 - 0.5, w, h)
    run = SurveyRun(
        name=name, conditions=["synthetic"], camera=cam,
        T_vehicle_camera=make_pose(CAMERA_FROM_VEHICLE_AXES, [1.5, 0.0, 1.4]),
        rates={"camera_hz": HZ, "odometry_hz": HZ, "ins_hz": HZ},
        frame_times=t, frame_files=[f"images/{i:06d}.png" for i in range(n)],
        odometry_times=t, odometry_poses=odo, groundtruth_times=t, groundtruth_poses=ins,
        truth_times=t, truth_poses=truth, gps=np.column_stack([t, ins[:, :3, 3]]), metadata={"seed": seed},
    )
    img = np.full((h, w), 128, np.uint8)
    images = [img] * n
    if stamp_frames:
        images = [img.copy() for _ in range(n)]
        for k, im in enumerate(images):
            im[0, 0], im[0, 1] = k % 256, k // 256
    write_run(run, folder, images=images)
    return read_run(folder)


def frame_index(image) -> int:
    """The frame number a ``stamp_frames`` run wrote into its image."""
    im = np.asarray(image)
    im = im if im.ndim == 2 else im[:, :, 0]
    return int(im[0, 0]) + 256 * int(im[0, 1])


def make_map(folder, length_m=120.0, spacing=10.0, camera=None, T_vehicle_camera=None, T_map_world=None):
    """A map whose places sit every ``spacing`` m on the road (no signatures in them).

    ``T_map_world``: a georeferencing error -- the places are at ``T_map_world @ truth`` and record their
    truth (``extra["T_truth_place"]``) as a simulated map does.
    """
    from scenesig.mapping.store import MapStore

    s = np.arange(spacing / 2, length_m, spacing)
    poses = truth_poses(s)
    cam = camera or Camera(25.6, 25.6, 15.5, 11.5, 32, 24)
    T_vc = T_vehicle_camera if T_vehicle_camera is not None else make_pose(CAMERA_FROM_VEHICLE_AXES, [1.5, 0, 1.4])
    w = MapWriter(folder, cam, T_vc, {"synthetic": True})
    metas = []
    for i, T in enumerate(poses):
        w.write_place(i, PlaceData({}, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)))
        nb = [j for j in (i - 1, i + 1) if 0 <= j < len(poses)]
        if T_map_world is None:
            metas.append({"index": i, "T_world_place": T, "neighbours": nb})
        else:
            metas.append({"index": i, "T_world_place": T_map_world @ T, "neighbours": nb,
                          "extra": {"T_truth_place": T.tolist()}})
    w.finalise(metas)
    return MapStore.open(folder)


class TruthMethod(WeakLocaliser):
    """A weak localiser that measures the exact truth plus Gaussian noise (for pipeline tests).

    ``blind`` lists (start_m, end_m) stretches of the route (arc length) where it returns nothing.
    Noise is drawn from a generator seeded by the frame time, so any replay mode sees the same values.
    """

    name = "truth+noise"

    def __init__(self, run: SurveyRun, sigma=(0.003, 0.003, 0.005, 0.3, 0.3, 0.1), seed=0, blind=(), start_m=2.0,
                 T_map_world=None):
        self.run = run
        self.sigma = np.asarray(sigma, float)
        self.seed = seed
        self.blind = list(blind)
        self.start_m = start_m
        self.calls = 0
        self.T_map_world = np.eye(4) if T_map_world is None else np.asarray(T_map_world, float)

    def measure(self, image, place, prior):
        self.calls += 1
        t = prior.t
        s = self.start_m + SPEED * (t - self.run.truth_times[0])
        if any(a <= s < b for a, b in self.blind):
            return None
        rng = np.random.default_rng([self.seed, int(round(t * 1000))])
        T = self.T_map_world @ interpolate_poses(self.run.truth_times, self.run.truth_poses, t) @ pose_exp(
            rng.normal(0, 1, 6) * self.sigma)
        cov = np.diag(self.sigma ** 2)
        return Measurement(LocalisationConstraint(T, cov, T, np.linalg.inv(cov)), detections=10, inliers=8,
                           solved=True)


class NothingMethod(WeakLocaliser):
    """Detections withheld: never localises."""

    name = "nothing"

    def measure(self, image, place, prior):
        return None
