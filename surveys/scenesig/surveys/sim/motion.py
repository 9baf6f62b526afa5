"""Vehicle motion of one run, and the error models of its odometry (VO) and INS/GPS.

Truth
-----
Each run drives the route once (a lap of a loop) in the left lane with its own

* lateral offset ``d(s) = 1.75 m + a slowly varying term`` (sum of sinusoids of 60-240 m wavelength,
  peak amplitude 0.6-1.0 m, so within +-1 m of the lane centre),
* speed profile: a smooth random target in [3.5, 14.5] m/s, capped on bends (lateral acceleration
  <= 2 m/s^2), stopping (dwell 1.5-5 s) at a random subset of the zebra crossings (at least one),
  with acceleration <= 1.5 m/s^2 and braking <= 2.5 m/s^2,
* small pitch/roll from acceleration and road roughness (< 1 deg).

Poses are exact functions of time (:meth:`Drive.pose`); they go to ``truth.tum``.

Odometry error model (VO-like, ~20 Hz, its own clock)
------------------------------------------------------
Each increment ``T_{k-1,k}`` between odometry samples (true length ``l_k`` metres) is corrupted as

* scale: translation times ``1 + e_s``, with ``e_s = b_s + u(s)``: a per-run bias
  ``b_s ~ N(0, (0.5 % f)^2)`` plus an Ornstein-Uhlenbeck process in distance, std ``0.5 % f``,
  correlation length 100 m;
* translation noise ``N(0, (0.01 f)^2 l_k)`` m per axis (z: half) -- a random walk in distance;
* heading: ``b_psi l_k + N(0, (0.025 deg f)^2 l_k)``, per-run drift rate ``b_psi ~ N(0, (0.4 deg f / 100
  m)^2)`` plus a random walk of 0.25 deg f per sqrt(100 m); roll/pitch random walk a third of that;
* a floor of 2 mm / 0.005 deg f per step, so VO jitters even while the vehicle stands still;

where ``f`` is the condition's ``odometry_factor`` (1 sunny/overcast, 1.1 autumn, 1.2 morning, 1.4
snow, 1.6 rain, 1.8 dusk, 2.2 fog, 3.0 night: VO is worse with little texture, noise and blur).
Resulting drift over 100 m of travel (relative pose error, start-aligned; checked in
``tests/test_sim_motion.py`` over many simulated runs):

==================================  ==================  ========================
statistic (per 100 m)               f = 1 (day)         scales with
==================================  ==================  ========================
heading drift, RMS                  0.47 deg            f  (sqrt(0.4^2 + 0.25^2))
translation drift, RMS              0.5 - 1.0 %         ~ f
==================================  ==================  ========================

INS/GPS error model (10 Hz -> ``groundtruth.tum``; 1 Hz GPS fixes -> ``gps.csv``)
---------------------------------------------------------------------------------
* position: a per-run offset ``N(0, 2.0^2)`` m per horizontal axis (``N(0, 0.3^2)`` vertical) -- runs on
  different days disagree by a few metres -- plus a random walk in distance of 0.25 m per sqrt(100 m)
  per horizontal axis (0.05 m vertical) and white noise of 2 cm;
* heading: offset ``N(0, 0.3^2)`` deg, random walk 0.1 deg per sqrt(100 m), white 0.02 deg;
  roll/pitch white 0.02 deg;
* GPS fixes: the INS position error plus white noise of 0.5 m.

So: INS offset RMS 2.0 m per axis (2.8 m horizontal); INS drift over 100 m RMS 0.25 m per axis
(0.35 m horizontal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import exp_so3, invert, rot_z
from .noise import smooth_process
from .route import Route

__all__ = ["Drive", "plan_drive", "odometry", "perturb_odometry", "drift_per_100m", "ins", "gps_fixes", "OdometryModel", "InsModel", "LANE_CENTRE"]

LANE_CENTRE = 1.75  # m left of the centreline (UK: keep left)


@dataclass
class OdometryModel:
    """VO error parameters for ``f = 1`` (see the module docstring); scaled by the condition's factor."""

    scale_bias: float = 0.005
    scale_ou: float = 0.005
    scale_corr_m: float = 100.0
    trans_rw: float = 0.01                   # m per sqrt(m)
    heading_bias_deg_100m: float = 0.4
    heading_rw_deg_sqrt100m: float = 0.25
    floor_m: float = 0.002
    floor_deg: float = 0.005


@dataclass
class InsModel:
    offset_xy: float = 2.0
    offset_z: float = 0.3
    rw_xy_sqrt100m: float = 0.25
    rw_z_sqrt100m: float = 0.05
    white_m: float = 0.02
    heading_offset_deg: float = 0.3
    heading_rw_deg_sqrt100m: float = 0.1
    white_deg: float = 0.02
    gps_white_m: float = 0.5


class Drive:
    """Exact motion of one run: arc length as a function of time, and poses.

    Attributes: ``duration`` (s), ``t_grid``/``s_grid`` (the s(t) table), ``stops`` [(s, dwell)].
    """

    def __init__(self, route: Route, t_grid, s_grid, offset_fn, stops, rough):
        self.route = route
        self.t_grid = np.asarray(t_grid, float)
        self.s_grid = np.asarray(s_grid, float)
        self.duration = float(self.t_grid[-1])
        self.stops = stops
        # dense path of the vehicle (centreline + offset), heading from its tangent
        ss = np.arange(self.s_grid[0] - 5.0, self.s_grid[-1] + 5.0, 0.05)
        d = offset_fn(ss)
        P = route.point(ss, d)
        dP = np.gradient(P, axis=0)
        self._ss, self._P = ss, P
        self._yaw = np.unwrap(np.arctan2(dP[:, 1], dP[:, 0]))
        self._d = d
        self._rough = rough

    def s(self, t):
        return np.interp(t, self.t_grid, self.s_grid)

    def speed(self, t, dt: float = 0.02):
        t = np.asarray(t, float)
        return (self.s(t + dt) - self.s(t - dt)) / (2 * dt)

    def lateral_offset(self, t):
        return np.interp(self.s(t), self._ss, self._d)

    def pose(self, t) -> np.ndarray:
        """Exact ``T_world_vehicle`` at time(s) ``t``: (4,4) or (N,4,4)."""
        t = np.asarray(t, float)
        single = t.ndim == 0
        t = np.atleast_1d(t)
        s = self.s(t)
        x = np.interp(s, self._ss, self._P[:, 0])
        y = np.interp(s, self._ss, self._P[:, 1])
        yaw = np.interp(s, self._ss, self._yaw)
        v = self.speed(t)
        acc = (self.speed(t + 0.25) - self.speed(t - 0.25)) / 0.5
        kappa = (np.interp(s + 0.5, self._ss, self._yaw) - np.interp(s - 0.5, self._ss, self._yaw)) / 1.0
        a_lat = v * v * kappa
        rp, rr, rz = self._rough
        pitch = -0.004 * acc + rp(s)      # nose dips when braking (positive pitch = nose down)
        roll = -0.006 * a_lat + rr(s)     # body rolls out of the bend
        z = rz(s)
        cy, sy = np.cos(yaw), np.sin(yaw)
        cp, sp = np.cos(pitch), np.sin(pitch)
        cr, sr = np.cos(roll), np.sin(roll)
        out = np.zeros((len(t), 4, 4))
        # R = Rz(yaw) Ry(pitch) Rx(roll), vectorised
        out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
        out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
        out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = -sp, cp * sr, cp * cr
        out[:, 0, 3], out[:, 1, 3], out[:, 2, 3], out[:, 3, 3] = x, y, z, 1.0
        return out[0] if single else out


def plan_drive(route: Route, rng: np.random.Generator, crossings=(), stop_prob: float = 0.7,
               start_m: float = 0.0) -> Drive:
    """Draw one run's lateral offset, speed profile and stops; return its :class:`Drive`.

    ``start_m``: arc length where the run begins (a kidnapped start).  A loop is still driven for a
    whole lap (from ``start_m`` round to it again), an open route from ``start_m`` to its end.  The
    random draws are the same for every ``start_m``: 0 gives exactly the drive it always gave.
    """
    M = float(start_m)
    L = route.drive_length if route.closed else route.drive_length - M
    if not 0.0 <= M < route.drive_length or L < 20.0:
        raise ValueError(f"start_m must lie in [0, {route.drive_length:.0f}) m and leave at least 20 m to drive "
                         f"(an open route ends at {route.drive_length:.0f} m), got {M:g}")
    ds = 0.1
    sg = np.arange(0.0, L + ds / 2, ds)         # distance driven from the start
    v_t = 9.0 + smooth_process(rng, sg, (50.0, 110.0, 230.0), amplitude=rng.uniform(3.5, 5.5))
    kappa = np.abs(np.interp(route.wrap(sg + M), route.s, route.curvature()))
    kappa = np.convolve(kappa, np.ones(41) / 41, "same")
    v = np.clip(np.minimum(v_t, np.sqrt(2.0 / np.maximum(kappa, 1e-6))), 3.5, 14.5)
    lap = route.drive_length
    crossings = [(c - M) % lap if route.closed else c - M for c in np.atleast_1d(crossings)]
    crossings = sorted(c for c in crossings if 10.0 < c < L - 5.0)
    stops = []
    for c in crossings:
        if rng.random() < stop_prob:
            stops.append((float(c - 3.0), float(rng.uniform(1.5, 5.0))))
    if not stops and crossings:
        c = crossings[int(rng.integers(len(crossings)))]
        stops.append((float(c - 3.0), float(rng.uniform(1.5, 5.0))))
    stops.sort()
    for s_stop, _ in stops:
        v[np.argmin(np.abs(sg - s_stop))] = 0.0
    a_acc, a_dec = 1.5, 2.5
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * a_acc * ds))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * a_dec * ds))
    # time along the grid; creep at 0.3 m/s in the last few cm before a stop line
    vm = np.maximum(v, 0.3)
    dt = ds * 0.5 * (1 / vm[1:] + 1 / vm[:-1])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    # insert the dwell: the stop point appears twice, at arrival and at departure
    for s_stop, dwell in stops:
        k = int(np.argmin(np.abs(sg - s_stop)))
        t = np.concatenate([t[:k + 1], t[k:] + dwell])
        sg = np.concatenate([sg[:k + 1], sg[k:]])
    # lead-in / lead-out of 1 s so that sensors start before the first frame and end after the last
    v0, v1 = max(v[0], 0.3), max(v[-1], 0.3)
    t = np.concatenate([[0.0], t + 1.0, [t[-1] + 2.0]])
    sg = np.concatenate([[-v0], sg, [sg[-1] + v1]])
    # lateral offset: a fixed smooth function of s, peak deviation 0.6-1.0 m from the lane centre
    span = np.arange(-50.0, L + 50.0, 0.5)
    base = smooth_process(rng, span, (60.0, 120.0, 240.0), amplitude=rng.uniform(0.6, 1.0))

    def offset(s):
        return LANE_CENTRE + np.interp(s - M, span, base)

    def rough(scale):
        vals = smooth_process(rng, span, (7.0, 13.0, 31.0), amplitude=scale)
        return lambda s: np.interp(s - M, span, vals)

    return Drive(route, t, sg + M, offset, [(s + M, d) for s, d in stops],
                 (rough(0.003), rough(0.002), rough(0.005)))


def drift_per_100m(P_true: np.ndarray, P_est: np.ndarray, length: float = 100.0, stride: int = 10):
    """Start-aligned relative pose errors over ``length`` metres of true travel.

    Returns (heading errors in degrees, translation errors in % of ``length``), one per window start
    (every ``stride`` samples).  This is the statistic the module docstring documents.
    """
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P_true[:, :3, 3], axis=0), axis=1))])
    he, te = [], []
    for i in range(0, len(dist), stride):
        j = int(np.searchsorted(dist, dist[i] + length))
        if j >= len(dist):
            break
        E = invert(invert(P_true[i]) @ P_true[j]) @ (invert(P_est[i]) @ P_est[j])
        he.append(np.degrees(np.arctan2(E[1, 0], E[0, 0])))
        te.append(100.0 * np.linalg.norm(E[:3, 3]) / length)
    return np.array(he), np.array(te)


def _ou(rng, dist, sigma, corr):
    """Ornstein-Uhlenbeck process sampled at cumulative distances ``dist`` (stationary std ``sigma``)."""
    out = np.empty(len(dist))
    x = rng.normal(0, sigma)
    prev = dist[0]
    for i, d in enumerate(dist):
        a = np.exp(-(d - prev) / corr)
        x = a * x + np.sqrt(max(1 - a * a, 0.0)) * sigma * rng.normal()
        out[i] = x
        prev = d
    return out


def odometry(drive: Drive, times: np.ndarray, rng: np.random.Generator, factor: float = 1.0,
             model: OdometryModel = OdometryModel()) -> np.ndarray:
    """VO poses ``T_odom_vehicle`` (N,4,4) at ``times``; the odometry frame is the first pose."""
    return perturb_odometry(drive.pose(times), rng, factor, model)


def perturb_odometry(P: np.ndarray, rng: np.random.Generator, factor: float = 1.0,
                     model: OdometryModel = OdometryModel()) -> np.ndarray:
    """Odometry poses ``T_odom_vehicle`` (N,4,4) drifting from the poses ``P`` (N,4,4) as VO drifts.

    Each increment ``inv(P[k-1]) @ P[k]`` is corrupted by the error model in the module docstring
    (scaled by ``factor``); the result starts at the identity.  Importers of real data use it too,
    to turn a clean motion signal into one that drifts like a real odometer.
    """
    P = np.asarray(P, dtype=float)
    inc = invert(P[:-1]) @ P[1:]
    step = np.linalg.norm(inc[:, :3, 3], axis=1)
    dist = np.concatenate([[0.0], np.cumsum(step)])
    f = factor
    e_s = rng.normal(0, model.scale_bias * f) + _ou(rng, dist[1:], model.scale_ou * f, model.scale_corr_m)
    b_psi = np.radians(rng.normal(0, model.heading_bias_deg_100m * f)) / 100.0
    s_psi = np.radians(model.heading_rw_deg_sqrt100m * f) / 10.0  # per sqrt(m)
    out = np.empty_like(P)
    out[0] = np.eye(4)
    n = len(step)
    noise_t = rng.standard_normal((n, 3))
    noise_r = rng.standard_normal((n, 3))
    floor_r = np.radians(model.floor_deg * f)
    for k in range(n):
        l = step[k]
        d = inc[k].copy()
        sig_t = np.sqrt((model.trans_rw * f) ** 2 * l + (model.floor_m * f) ** 2)
        d[:3, 3] = d[:3, 3] * (1 + e_s[k]) + noise_t[k] * sig_t * np.array([1.0, 1.0, 0.5])
        sig_r = np.sqrt(s_psi ** 2 * l + floor_r ** 2)
        err = np.array([noise_r[k, 0] * sig_r / 3, noise_r[k, 1] * sig_r / 3, b_psi * l + noise_r[k, 2] * sig_r])
        d[:3, :3] = d[:3, :3] @ exp_so3(err)
        out[k + 1] = out[k] @ d
    return out


def ins(drive: Drive, times: np.ndarray, rng: np.random.Generator, model: InsModel = InsModel()):
    """INS poses ``T_world_vehicle`` (N,4,4) at ``times`` and the position error process (N,3)."""
    P = drive.pose(times)
    dist = np.maximum.accumulate(drive.s(times) - drive.s(times[0]))
    ddist = np.diff(dist, prepend=dist[0])
    off = rng.normal(0, [model.offset_xy, model.offset_xy, model.offset_z])
    rw_sig = np.array([model.rw_xy_sqrt100m, model.rw_xy_sqrt100m, model.rw_z_sqrt100m]) / 10.0
    walk = np.cumsum(rng.standard_normal((len(times), 3)) * rw_sig * np.sqrt(ddist)[:, None], axis=0)
    err = off + walk
    pos_err = err + rng.normal(0, model.white_m, (len(times), 3))
    h_off = np.radians(rng.normal(0, model.heading_offset_deg))
    h_walk = np.cumsum(rng.standard_normal(len(times)) * np.radians(model.heading_rw_deg_sqrt100m) / 10.0
                       * np.sqrt(ddist))
    wd = np.radians(model.white_deg)
    out = P.copy()
    for i in range(len(times)):
        R_err = rot_z(h_off + h_walk[i] + rng.normal(0, wd)) @ exp_so3(rng.normal(0, wd, 3) * [1, 1, 0])
        out[i, :3, :3] = R_err @ P[i, :3, :3]
        out[i, :3, 3] = P[i, :3, 3] + pos_err[i]
    return out, err


def gps_fixes(drive: Drive, times: np.ndarray, ins_times: np.ndarray, ins_err: np.ndarray,
              rng: np.random.Generator, model: InsModel = InsModel()) -> np.ndarray:
    """(K,4) GPS fixes ``t, x, y, z``: truth + the INS's slow error + white noise."""
    P = drive.pose(times)
    e = np.stack([np.interp(times, ins_times, ins_err[:, k]) for k in range(3)], 1)
    xyz = P[:, :3, 3] + e + rng.normal(0, model.gps_white_m, (len(times), 3)) * [1, 1, 1.5]
    return np.column_stack([times, xyz])
