"""Snapping an SE(3) vehicle pose to SE(2) on the local road plane (McManus et al. 2015, §3.3.3, Fig. 7).

The map, the odometry, the solver and the pose graph all work in SE(3); left alone, a
monocular far-field localiser lets the height drift slowly.  Because a car drives on a road, the
local vicinity of the two map keyframes nearest to the estimate is well approximated by a plane:
we put the estimate on that plane (translation projected along the normal), lay its roll and
pitch in the plane (the z axis becomes the plane normal) and keep its heading within the plane.

Plane definition (our choice; the paper only says "a local plane defined by the two closest
keyframes"): the plane **through both keyframe positions** that contains their **average lateral
(y) axis**.  Its normal is ``n = normalise(b - a) x y_avg`` oriented along the keyframes' average
z axis.  Using the two positions pins the slope along the road to the surveyed positions (which
are what stops z-drift), while the lateral axes add the one missing degree of freedom, the
road's bank, which two points cannot give.  When the keyframes (nearly) coincide or their
baseline is (nearly) parallel to the lateral axis, the plane falls back to the one through their
midpoint normal to their average z axis.

Keyframe poses are vehicle poses ``T_world_vehicle`` (x forward, y left, z up), e.g. the places'
reference poses in the map.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["local_plane", "snap_to_plane", "snap_to_keyframes", "PlaneSnapper"]

# Below this sine of the angle between baseline and lateral axis (or this baseline length, m),
# the two-keyframe plane is ill-defined and we fall back to the average-normal plane.
_DEGENERATE_SIN = 1e-3
_DEGENERATE_BASELINE_M = 1e-6


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"cannot normalise vector {v}")
    return v / n


def local_plane(T_world_kf_a: np.ndarray, T_world_kf_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local road plane of two keyframes.

    Parameters
    ----------
    T_world_kf_a, T_world_kf_b : (4, 4) keyframe vehicle poses in the world.

    Returns
    -------
    point : (3,) a point on the plane (the keyframes' midpoint).
    normal : (3,) unit normal, on the side of the keyframes' average z (up) axis.
    """
    Ta = np.asarray(T_world_kf_a, dtype=float)
    Tb = np.asarray(T_world_kf_b, dtype=float)
    if Ta.shape != (4, 4) or Tb.shape != (4, 4):
        raise ValueError(f"keyframe poses must be 4x4, got {Ta.shape} and {Tb.shape}")
    pa, pb = Ta[:3, 3], Tb[:3, 3]
    z_avg = _unit(Ta[:3, 2] + Tb[:3, 2])
    y_avg = Ta[:3, 1] + Tb[:3, 1]
    point = 0.5 * (pa + pb)
    base = pb - pa
    blen = np.linalg.norm(base)
    if blen > _DEGENERATE_BASELINE_M and np.linalg.norm(y_avg) > 0:
        n = np.cross(base / blen, _unit(y_avg))
        sin = np.linalg.norm(n)
        if sin > _DEGENERATE_SIN:
            n = n / sin
            return point, (n if n @ z_avg >= 0 else -n)
    return point, z_avg


def snap_to_plane(T_world_vehicle: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Project a vehicle pose onto a plane: position onto the plane, z axis to the normal, heading kept.

    The new x (forward) axis is the old one projected into the plane, so the heading *within the
    plane* is unchanged; roll and pitch relative to the plane become zero.  The operation is a
    projection: applying it twice gives the same pose.

    Parameters
    ----------
    T_world_vehicle : (4, 4) pose to snap.
    point, normal : the plane (any point on it and its normal; the normal is normalised here).

    Returns
    -------
    (4, 4) snapped pose.
    """
    T = np.asarray(T_world_vehicle, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"pose must be 4x4, got {T.shape}")
    n = _unit(np.asarray(normal, dtype=float).reshape(3))
    p0 = np.asarray(point, dtype=float).reshape(3)
    p = T[:3, 3]
    x = T[:3, 0]
    x_in = x - (x @ n) * n
    if np.linalg.norm(x_in) < 1e-9:
        # Forward axis along the normal (vehicle standing on its nose): no heading to keep; fall
        # back to the lateral axis, which then defines the heading by y = n x x.
        y_in = T[:3, 1] - (T[:3, 1] @ n) * n
        x_in = np.cross(y_in, n)
    x_new = _unit(x_in)
    y_new = np.cross(n, x_new)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = x_new, y_new, n
    out[:3, 3] = p - ((p - p0) @ n) * n
    return out


def snap_to_keyframes(T_world_vehicle: np.ndarray, keyframe_poses: np.ndarray) -> np.ndarray:
    """Snap a pose to the local plane of its two nearest keyframes (by position).

    For repeated calls against the same map use :class:`PlaneSnapper` (builds a k-d tree once).
    """
    return PlaneSnapper(keyframe_poses).snap(T_world_vehicle)


class PlaneSnapper:
    """Snaps poses to the plane of the two nearest of a fixed set of keyframes.

    Parameters
    ----------
    keyframe_poses : (K, 4, 4) keyframe vehicle poses ``T_world_keyframe``, K >= 2.
    """

    def __init__(self, keyframe_poses: np.ndarray):
        kf = np.asarray(keyframe_poses, dtype=float)
        if kf.ndim != 3 or kf.shape[1:] != (4, 4):
            raise ValueError(f"keyframe_poses must be (K,4,4), got {kf.shape}")
        if len(kf) < 2:
            raise ValueError(f"need at least 2 keyframes to define a plane, got {len(kf)}")
        if not np.all(np.isfinite(kf)):
            raise ValueError("keyframe_poses contain non-finite values")
        self.keyframe_poses = kf
        self._tree = cKDTree(kf[:, :3, 3])
        self._planes: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}   # a pair's plane, once

    def nearest_two(self, position: np.ndarray) -> tuple[int, int]:
        """Indices of the two keyframes nearest to a position (nearest first)."""
        _, idx = self._tree.query(np.asarray(position, dtype=float).reshape(3), k=2)
        return int(idx[0]), int(idx[1])

    def plane(self, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(point, normal)`` of the local plane at a position."""
        i, j = self.nearest_two(position)
        plane = self._planes.get((i, j))
        if plane is None:
            plane = self._planes[(i, j)] = local_plane(self.keyframe_poses[i], self.keyframe_poses[j])
        return plane

    def snap(self, T_world_vehicle: np.ndarray) -> np.ndarray:
        """The pose snapped to the local plane of its two nearest keyframes."""
        T = np.asarray(T_world_vehicle, dtype=float)
        point, normal = self.plane(T[:3, 3])
        return snap_to_plane(T, point, normal)
