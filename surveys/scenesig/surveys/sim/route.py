"""The route: a smooth planar centreline parameterised by arc length ``s``.

A closed loop (presets ``demo``, ``begbroke``) is a perturbed super-ellipse -- straight-ish streets
joined by rounded corners, like a science-park ring road; an open route (``tiny``) is a gentle
S-bend with ``extension`` metres of world before its start and after its end so that the view at
either end is not empty.  Everything (world layout, vehicle motion) is expressed in route
coordinates ``(s, d)``: arc length along the centreline and signed lateral offset, positive to the
left (vehicle y axis).
"""
from __future__ import annotations

import numpy as np

__all__ = ["Route"]

_DS = 0.1  # spacing of the dense centreline samples (m)


class Route:
    """Planar centreline sampled densely by arc length.

    Parameters
    ----------
    xy : (N, 2) dense centreline points, spaced ~``_DS`` apart.
    closed : whether the last point connects back to the first.
    s0 : arc length of the first point (negative for an open route's lead-in).
    drive_length : length the vehicle drives (a lap for loops; the route proper for open routes).
    """

    def __init__(self, xy: np.ndarray, closed: bool, s0: float = 0.0, drive_length: float | None = None):
        xy = np.asarray(xy, float)
        seg = np.linalg.norm(np.diff(xy, axis=0, append=xy[:1] if closed else xy[-1:]), axis=1)
        self.closed = bool(closed)
        self.xy = xy
        self.s = s0 + np.concatenate([[0.0], np.cumsum(seg[:-1])])
        self.total = float(seg.sum()) if closed else float(self.s[-1] - s0)
        self.s0 = float(s0)
        # heading from central differences, unwrapped so that it can be interpolated
        if closed:
            d = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
        else:
            d = np.gradient(xy, axis=0)
        self.psi = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        self.drive_length = float(drive_length if drive_length is not None else self.total)

    # ------------------------------------------------------------------ construction
    @classmethod
    def loop(cls, length: float, rng: np.random.Generator, min_radius: float = 25.0) -> "Route":
        """A closed loop of the given length with corner radius at least ``min_radius``."""
        aspect = rng.uniform(1.3, 1.8)
        phases = rng.uniform(0, 2 * np.pi, 3)
        rot = rng.uniform(0, 2 * np.pi)
        best = None
        for p in np.linspace(5.0, 2.0, 13):  # squarest shape whose corners are still wide enough
            xy = cls._superellipse(length, aspect, p, phases, rot)
            r = cls(xy, closed=True)
            if r.min_radius() >= min_radius:
                best = r
                break
        if best is None:
            best = cls(cls._superellipse(length, aspect, 2.0, phases, rot), closed=True)
        return best

    @staticmethod
    def _superellipse(length, aspect, p, phases, rot, n=20000):
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        c, s = np.cos(th), np.sin(th)
        x = aspect * np.sign(c) * np.abs(c) ** (2 / p)
        y = np.sign(s) * np.abs(s) ** (2 / p)
        wob = 1 + 0.035 * np.sin(2 * th + phases[0]) + 0.025 * np.sin(3 * th + phases[1])
        xy = np.stack([x * wob, y * wob], axis=1)
        R = np.array([[np.cos(rot), -np.sin(rot)], [np.sin(rot), np.cos(rot)]])
        xy = xy @ R.T
        per = np.linalg.norm(np.diff(xy, axis=0, append=xy[:1]), axis=1).sum()
        xy *= length / per
        return Route._resample(xy, closed=True)

    @classmethod
    def open(cls, length: float, rng: np.random.Generator, extension: float = 80.0) -> "Route":
        """An open S-bend of ``length`` metres plus ``extension`` metres of world at each end."""
        s = np.arange(-extension, length + extension + _DS, _DS)
        amp = rng.uniform(0.15, 0.3)
        lam = rng.uniform(90, 140)
        ph = rng.uniform(0, 2 * np.pi)
        psi = amp * np.sin(2 * np.pi * s / lam + ph)
        xy = np.cumsum(np.stack([np.cos(psi), np.sin(psi)], axis=1) * _DS, axis=0)
        xy -= xy[np.argmin(np.abs(s))]
        return cls(xy, closed=False, s0=-extension, drive_length=length)

    @staticmethod
    def _resample(xy, closed):
        pts = np.concatenate([xy, xy[:1]]) if closed else xy
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0], np.cumsum(seg)])
        n = int(np.floor(cum[-1] / _DS))
        t = np.linspace(0, cum[-1], n, endpoint=not closed)
        return np.stack([np.interp(t, cum, pts[:, 0]), np.interp(t, cum, pts[:, 1])], axis=1)

    # ------------------------------------------------------------------ queries
    def wrap(self, s):
        """Arc length mapped into the route's range (modulo the lap for loops)."""
        s = np.asarray(s, float)
        if self.closed:
            return np.mod(s - self.s0, self.total) + self.s0
        return np.clip(s, self.s[0], self.s[-1])

    def _interp(self, s, values, periodic_offset=0.0):
        s = self.wrap(s)
        if self.closed:
            ss = np.concatenate([self.s, [self.s[0] + self.total]])
            vv = np.concatenate([values, values[:1] + periodic_offset], axis=0)
        else:
            ss, vv = self.s, values
        if vv.ndim == 1:
            return np.interp(s, ss, vv)
        return np.stack([np.interp(s, ss, vv[:, k]) for k in range(vv.shape[1])], axis=-1)

    def position(self, s) -> np.ndarray:
        """Centreline point(s) (..., 2)."""
        return self._interp(s, self.xy)

    def heading(self, s) -> np.ndarray:
        """Centreline heading(s) (rad), continuous along the route."""
        if not self.closed:
            return self._interp(s, self.psi)
        turn = round((self.psi[-1] - self.psi[0]) / (2 * np.pi)) * 2 * np.pi
        laps = np.floor((np.asarray(s, float) - self.s0) / self.total)
        # beyond one lap the heading keeps turning, so that it stays continuous for a whole drive
        return self._interp(s, self.psi, periodic_offset=turn) + laps * turn

    def normal(self, s) -> np.ndarray:
        """Unit left normal(s) (..., 2)."""
        psi = self.heading(s)
        return np.stack([-np.sin(psi), np.cos(psi)], axis=-1)

    def point(self, s, d) -> np.ndarray:
        """World point(s) at arc length ``s`` and lateral offset ``d`` (left positive), (..., 2)."""
        d = np.asarray(d, float)
        return self.position(s) + self.normal(s) * d[..., None]

    def curvature(self) -> np.ndarray:
        """Signed curvature (1/m) at the dense samples."""
        return np.gradient(self.psi) / _DS

    def min_radius(self) -> float:
        k = np.abs(self.curvature())
        # smooth over 2 m: the dense polyline's local wiggle is not the street's radius
        w = int(2.0 / _DS)
        k = np.convolve(np.concatenate([k[-w:], k, k[:w]]) if self.closed else k, np.ones(w) / w, "same")
        return float(1.0 / max(k.max(), 1e-9))

    def distance_to(self, pts: np.ndarray, stride: int = 5) -> np.ndarray:
        """Distance (m) from 2-D points (N, 2) to the centreline (sampled every ``stride`` points)."""
        from scipy.spatial import cKDTree

        if not hasattr(self, "_tree"):
            self._tree = cKDTree(self.xy[::stride])
        d, _ = self._tree.query(np.asarray(pts, float).reshape(-1, 2))
        return d

    def to_json(self) -> dict:
        step = int(round(1.0 / _DS))
        return {"closed": self.closed, "length_m": round(self.total, 3),
                "drive_length_m": round(self.drive_length, 3), "s0": self.s0,
                "min_radius_m": round(self.min_radius(), 2),
                "centreline_every_1m": np.round(self.xy[::step], 3).tolist()}
