"""Rigid-body geometry and the pinhole camera model -- the one copy in the project.

Conventions (used everywhere, documented in README):

* A pose ``T_a_b`` is a 4x4 homogeneous matrix mapping points in frame *b* into frame *a*:
  ``p_a = T_a_b @ p_b``.  ``T_world_vehicle`` is therefore the vehicle's pose in the world.
* Vehicle frame: x forward, y left, z up (ROS REP-103).
* Camera frame: x right, y down, z forward (OpenCV).  ``T_vehicle_camera`` is the extrinsic.
* Quaternions are ``(qx, qy, qz, qw)`` as in the TUM format.

Everything is plain numpy so the simulator, the trainer and the localiser share it without
pulling GTSAM into the lower layers.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Camera", "quat_to_rot", "rot_to_quat", "make_pose", "invert", "transform",
    "pose_to_xyzquat", "xyzquat_to_pose", "rot_x", "rot_y", "rot_z", "yaw_of",
    "exp_so3", "log_so3", "nearest_rotation", "relative", "interpolate_poses", "point_pose_jacobian", "CAMERA_FROM_VEHICLE_AXES",
]

# Rotation that takes camera axes (x right, y down, z forward) to vehicle axes
# (x forward, y left, z up) for a forward-looking camera: columns are the camera axes in vehicle frame.
CAMERA_FROM_VEHICLE_AXES = np.array([[0.0, 0.0, 1.0],
                                     [-1.0, 0.0, 0.0],
                                     [0.0, -1.0, 0.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def make_pose(R: np.ndarray | None = None, t=None) -> np.ndarray:
    """Build a 4x4 pose from a rotation matrix and a translation."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of one pose (4x4) or a stack of poses (N,4,4), using R^T rather than a general inverse."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def relative(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """``T_a_b`` from two poses in a common frame."""
    return invert(T_w_a) @ T_w_b


def transform(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply pose ``T`` (4x4) to points ``P`` (N,3) or (3,)."""
    P = np.asarray(P, dtype=float)
    return P @ T[:3, :3].T + T[:3, 3]


def quat_to_rot(q) -> np.ndarray:
    """Rotation matrix from quaternion(s) ``(qx, qy, qz, qw)``; accepts (4,) or (N,4). Normalises."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rot_to_quat(R) -> np.ndarray:
    """Quaternion(s) ``(qx, qy, qz, qw)`` with qw >= 0 from rotation matrix/matrices (3,3) or (N,3,3)."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    for i, M in enumerate(R):
        tr = M[0, 0] + M[1, 1] + M[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q[i] = [(M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s, 0.25 * s]
        elif M[0, 0] > M[1, 1] and M[0, 0] > M[2, 2]:
            s = 2.0 * np.sqrt(1.0 + M[0, 0] - M[1, 1] - M[2, 2])
            q[i] = [0.25 * s, (M[0, 1] + M[1, 0]) / s, (M[0, 2] + M[2, 0]) / s, (M[2, 1] - M[1, 2]) / s]
        elif M[1, 1] > M[2, 2]:
            s = 2.0 * np.sqrt(1.0 + M[1, 1] - M[0, 0] - M[2, 2])
            q[i] = [(M[0, 1] + M[1, 0]) / s, 0.25 * s, (M[1, 2] + M[2, 1]) / s, (M[0, 2] - M[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + M[2, 2] - M[0, 0] - M[1, 1])
            q[i] = [(M[0, 2] + M[2, 0]) / s, (M[1, 2] + M[2, 1]) / s, 0.25 * s, (M[1, 0] - M[0, 1]) / s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q[0] if single else q


def xyzquat_to_pose(xyzq) -> np.ndarray:
    """(7,) or (N,7) ``tx ty tz qx qy qz qw`` -> (4,4) or (N,4,4)."""
    xyzq = np.asarray(xyzq, dtype=float)
    single = xyzq.ndim == 1
    xyzq = xyzq.reshape(-1, 7)
    T = np.tile(np.eye(4), (len(xyzq), 1, 1))
    T[:, :3, :3] = quat_to_rot(xyzq[:, 3:])
    T[:, :3, 3] = xyzq[:, :3]
    return T[0] if single else T


def pose_to_xyzquat(T) -> np.ndarray:
    """(4,4) or (N,4,4) -> (7,) or (N,7) ``tx ty tz qx qy qz qw``."""
    T = np.asarray(T, dtype=float)
    single = T.ndim == 2
    T = T.reshape(-1, 4, 4)
    out = np.concatenate([T[:, :3, 3], rot_to_quat(T[:, :3, :3]).reshape(-1, 4)], axis=1)
    return out[0] if single else out


def yaw_of(T) -> np.ndarray | float:
    """Heading (rad) of the x axis of pose(s) ``T`` in the world x-y plane."""
    T = np.asarray(T)
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def exp_so3(w) -> np.ndarray:
    """Rodrigues: rotation matrix from an axis-angle vector."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


def point_pose_jacobian(P: np.ndarray) -> np.ndarray:
    """d P_v / d xi of points seen from a pose perturbed on the right, ``T <- T Exp(xi)``.

    ``P`` (n, 3) are the points in the (vehicle) frame of ``T``; ``xi = (omega, v)`` (GTSAM's order,
    rotation first).  To first order ``P_v <- Exp(-xi) P_v = P_v + [P_v]_x omega - v``, so the
    Jacobian is ``[ [P_v]_x | -I ]``, returned as (n, 3, 6).  The solver (eq. 10) and the detector's
    search windows both linearise projections through it.
    """
    P = np.asarray(P, dtype=float).reshape(-1, 3)
    D = np.zeros((len(P), 3, 6))
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    D[:, 0, 1], D[:, 0, 2] = -z, y
    D[:, 1, 0], D[:, 1, 2] = z, -x
    D[:, 2, 0], D[:, 2, 1] = -y, x
    D[:, 0, 3] = D[:, 1, 4] = D[:, 2, 5] = -1.0
    return D


def nearest_rotation(M) -> np.ndarray:
    """The rotation matrix closest to ``M`` (3,3) in Frobenius norm (SVD projection).

    Calibration files print rotations to a few digits; projecting keeps every pose rigid, so
    conversions to quaternions and back are lossless.
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def log_so3(R) -> np.ndarray:
    """Axis-angle vector of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return 0.5 * v
    if np.pi - th < 1e-6:  # near pi: take the axis from the symmetric part
        A = (R + np.eye(3)) / 2
        axis = A[np.argmax(np.diag(A))]
        return th * axis / np.linalg.norm(axis)
    return th / (2 * np.sin(th)) * v


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with optional OpenCV (k1, k2, p1, p2[, k3]) distortion.

    ``project`` works in the camera frame (x right, y down, z forward).  The simulator renders
    without distortion; real cameras may carry it and ``project`` applies it.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple = field(default=())

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    def project(self, P_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N,2) and depths (N,) of camera-frame points (N,3); points behind get NaN pixels."""
        P = np.atleast_2d(np.asarray(P_cam, dtype=float))
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = P[:, 0] / z
            y = P[:, 1] / z
        if any(self.distortion):
            d = list(self.distortion) + [0.0] * (5 - len(self.distortion))
            k1, k2, p1, p2, k3 = d[:5]
            r2 = x * x + y * y
            rad = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
            x, y = (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)
        uv[z <= 0] = np.nan
        return uv, z

    def project_jacobian(self, P_cam: np.ndarray) -> np.ndarray:
        """d(uv)/d(P_cam), (N,2,3), for the undistorted model (used by the refiners)."""
        P = np.atleast_2d(np.asarray(P_cam, dtype=float))
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        J = np.zeros((len(P), 2, 3))
        J[:, 0, 0] = self.fx / z
        J[:, 0, 2] = -self.fx * x / z ** 2
        J[:, 1, 1] = self.fy / z
        J[:, 1, 2] = -self.fy * y / z ** 2
        return J

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit-depth rays (N,3) (z = 1) through pixels (N,2); undistorts where needed."""
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        if any(self.distortion):
            import cv2  # only real, distorted cameras need OpenCV here
            pts = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, np.asarray(self.distortion, float))
            xy = pts.reshape(-1, 2)
        else:
            xy = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)
        return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)

    def backproject(self, uv: np.ndarray, depth) -> np.ndarray:
        """Camera-frame points (N,3) at the given depth(s) (z) through pixels (N,2)."""
        return self.rays(uv) * np.asarray(depth, dtype=float).reshape(-1, 1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        uv = np.atleast_2d(uv)
        return ((uv[:, 0] >= margin) & (uv[:, 0] <= self.width - 1 - margin)
                & (uv[:, 1] >= margin) & (uv[:, 1] <= self.height - 1 - margin))

    def scaled(self, factor: float) -> "Camera":
        """The same camera with images resized by ``factor`` (pixel-centre convention)."""
        return Camera(self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                      (self.cy + 0.5) * factor - 0.5, int(round(self.width * factor)),
                      int(round(self.height * factor)), self.distortion)

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width,
                "height": self.height, "distortion": list(self.distortion)}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]),
                   int(d["height"]), tuple(float(v) for v in d.get("distortion", ())))


def interpolate_poses(times: np.ndarray, poses: np.ndarray, t) -> np.ndarray:
    """Poses at query time(s) ``t``: linear in translation, SLERP in rotation.

    Queries outside ``[times[0], times[-1]]`` are clamped to the end poses (no extrapolation:
    a pose invented beyond the data would look like a measurement).
    """
    from scipy.spatial.transform import Rotation, Slerp

    times = np.asarray(times, dtype=float)
    poses = np.asarray(poses, dtype=float)
    tq = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), times[0], times[-1])
    if len(times) == 1:
        out = np.repeat(poses[:1], len(tq), axis=0)
    else:
        rot = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(tq).as_matrix()
        trans = np.stack([np.interp(tq, times, poses[:, :3, 3][:, k]) for k in range(3)], axis=1)
        out = np.tile(np.eye(4), (len(tq), 1, 1))
        out[:, :3, :3] = rot
        out[:, :3, 3] = trans
    return out[0] if np.ndim(t) == 0 else out
