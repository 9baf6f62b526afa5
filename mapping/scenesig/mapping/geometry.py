"""Mapping geometry: window poses, landmark reprojection, jacobians and the ray-depth parametrisation.

Everything here is built on :mod:`scenesig.surveys.geometry` (the project's one camera and SE(3) implementation);
this module only adds what landmark refinement (McManus et al. 2015, §3.2.1) needs, vectorised over many
landmarks and window frames at once.

Frames (see ``scenesig.surveys.geometry`` for the conventions):

* the *place frame* ``p`` is the vehicle frame at the place (or at the reference frame of a window);
  landmarks ``p_p^i`` live in it;
* window frame ``j`` is the vehicle frame at the j-th image of the window; ``T_window_place[j]`` is the
  vehicle pose ``T_{j,p}`` (maps place-frame points into vehicle frame ``j``), obtained from the known
  odometry increments ``T_{k-1,k}``;
* camera frame ``c_j`` is the camera at window frame ``j``; ``T_cam_place[j] = inv(T_vehicle_camera) @
  T_window_place[j]`` is what the measurement model ``h(T_{j,p}, p_p)`` (eq. 1) projects with.

Refinement works in *ideal pixels*: the pixels of the same camera without lens distortion.  Observed pixels
of a distorted camera are undistorted once (``ideal_pixels``) so the projection and its jacobian
(``Camera.project_jacobian``, undistorted model) are exact and cheap inside the optimiser.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from scenesig.surveys.geometry import Camera, invert

__all__ = [
    "window_poses_from_increments", "window_poses_from_odometry", "camera_poses", "ideal_camera",
    "ideal_pixels", "reproject", "reproject_jacobian", "anchor_rays", "ray_points", "derotate_pixels",
    "camera_depth", "reference_area", "detection_covariance_factor",
]


def window_poses_from_increments(increments: np.ndarray, reference: int) -> np.ndarray:
    """Poses ``T_{j,p}`` of every window frame w.r.t. the reference frame, from odometry increments.

    Parameters
    ----------
    increments : (F-1, 4, 4) array
        ``T_{k-1,k}`` for k = 1..F-1: the pose of frame k in frame k-1 (as delivered by VO or wheel odometry).
    reference : int
        Index (0..F-1) of the frame that defines the place frame ``p``.

    Returns
    -------
    (F, 4, 4) array
        ``T_window_place[j] = T_{j,p}``, mapping reference-frame points into frame ``j``.
    """
    inc = np.asarray(increments, dtype=float)
    if inc.ndim != 3 or inc.shape[1:] != (4, 4):
        raise ValueError(f"increments must be (F-1, 4, 4), got {inc.shape}")
    F = len(inc) + 1
    if not 0 <= reference < F:
        raise ValueError(f"reference index {reference} outside 0..{F - 1}")
    T_0_k = np.empty((F, 4, 4))
    T_0_k[0] = np.eye(4)
    for k in range(1, F):  # a chain: inherently sequential, F is small
        T_0_k[k] = T_0_k[k - 1] @ inc[k - 1]
    return window_poses_from_odometry(T_0_k, reference)


def window_poses_from_odometry(T_odom_vehicle: np.ndarray, reference: int | np.ndarray) -> np.ndarray:
    """``T_{j,p}`` from odometry poses of the window frames (any common, possibly drifting, frame).

    Parameters
    ----------
    T_odom_vehicle : (F, 4, 4) array
        Vehicle poses in the odometry frame at the window's image times.
    reference : int or (4, 4) array
        Index of the reference frame in the window, or directly the odometry pose ``T_odom_place`` of the
        place frame.

    Returns
    -------
    (F, 4, 4) array
        ``inv(T_odom_vehicle[j]) @ T_odom_place``.
    """
    T = np.asarray(T_odom_vehicle, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_odom_vehicle must be (F, 4, 4), got {T.shape}")
    T_odom_place = T[int(reference)] if np.ndim(reference) == 0 else np.asarray(reference, dtype=float)
    return invert(T) @ T_odom_place


def camera_poses(T_window_place: np.ndarray, T_vehicle_camera: np.ndarray) -> np.ndarray:
    """``T_{c_j,p}`` (F,4,4): camera frame ``j`` from the place (vehicle) frame."""
    return invert(np.asarray(T_vehicle_camera, dtype=float)) @ np.asarray(T_window_place, dtype=float)


def ideal_camera(camera: Camera) -> Camera:
    """The same camera without lens distortion (the model refinement optimises in)."""
    return dataclasses.replace(camera, distortion=()) if any(camera.distortion) else camera


def ideal_pixels(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Undistort pixels (..., 2) of ``camera`` into ideal (undistorted) pixels; NaNs pass through."""
    uv = np.asarray(uv, dtype=float)
    if not any(camera.distortion):
        return uv
    flat = uv.reshape(-1, 2)
    out = np.full_like(flat, np.nan)
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        rays = camera.rays(flat[ok])
        out[ok] = rays[:, :2] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return out.reshape(uv.shape)


def _to_camera(T_cam_place: np.ndarray, P_place: np.ndarray) -> np.ndarray:
    """Points (..., 3) in the place frame -> (..., F, 3) in each window camera."""
    F = T_cam_place.shape[0]
    lead = P_place.shape[:-1]
    # One matmul against the stacked rotations (3F x 3) is much faster than a batched einsum here.
    Pc = P_place.reshape(-1, 3) @ T_cam_place[:, :3, :3].reshape(3 * F, 3).T
    return Pc.reshape(lead + (F, 3)) + T_cam_place[:, :3, 3]


def reproject(T_cam_place: np.ndarray, P_place: np.ndarray, camera: Camera):
    """Project place-frame points into every window camera (eq. 1 without noise).

    Parameters
    ----------
    T_cam_place : (F, 4, 4) array
        Window camera poses ``T_{c_j,p}`` (see :func:`camera_poses`).
    P_place : (..., 3) array
        Landmarks in the place frame (any leading shape, e.g. (N,3) or (N,K,3) for a depth sweep).
    camera : Camera
        Projection model (use :func:`ideal_camera` for refinement).

    Returns
    -------
    uv : (..., F, 2) array
        Pixels; NaN where the point is behind the camera.
    z : (..., F) array
        Depth of the point in each camera.
    """
    Pc = _to_camera(np.asarray(T_cam_place, dtype=float), np.asarray(P_place, dtype=float))
    uv, z = camera.project(Pc.reshape(-1, 3))
    return uv.reshape(Pc.shape[:-1] + (2,)), z.reshape(Pc.shape[:-1])


def reproject_jacobian(T_cam_place: np.ndarray, P_place: np.ndarray, camera: Camera):
    """Reprojection, depths and the jacobian ``H = d h(T_{j,p}, p) / d p`` (eq. 6) for an ideal camera.

    Parameters
    ----------
    T_cam_place : (F, 4, 4) array
    P_place : (..., 3) array
    camera : Camera
        Must be undistorted (:func:`ideal_camera`): the jacobian is the pinhole one.

    Returns
    -------
    uv : (..., F, 2), z : (..., F), H : (..., F, 2, 3)
        ``H = dpi/dP_c @ R_{c_j,p}``; rows for points behind the camera are meaningless (check ``z``).
    """
    if any(camera.distortion):
        raise ValueError("reproject_jacobian needs an undistorted camera; use ideal_camera()/ideal_pixels()")
    T = np.asarray(T_cam_place, dtype=float)
    Pc = _to_camera(T, np.asarray(P_place, dtype=float))
    flat = Pc.reshape(-1, 3)
    uv, z = camera.project(flat)
    with np.errstate(divide="ignore", invalid="ignore"):  # points at z = 0 are flagged by z, not here
        Jp = camera.project_jacobian(flat).reshape(Pc.shape[:-1] + (2, 3))
    H = np.einsum("...fik,fkj->...fij", Jp, T[:, :3, :3])
    return uv.reshape(Pc.shape[:-1] + (2,)), z.reshape(Pc.shape[:-1]), H


def anchor_rays(T_cam_place: np.ndarray, uv: np.ndarray, frame: np.ndarray, camera: Camera):
    """Ray-depth parametrisation: the ray through an anchor detection, expressed in the place frame.

    A landmark on the ray is ``o + d * r`` where ``d`` is its depth (z) in the anchor camera -- the
    quantity the depth sweep samples at 1 m steps.

    Parameters
    ----------
    T_cam_place : (F, 4, 4) array
    uv : (N, 2) array
        Anchor detections in ideal pixels.
    frame : (N,) int array
        Window frame of each anchor detection.
    camera : Camera
        Ideal camera.

    Returns
    -------
    origin : (N, 3) array
        Anchor camera centres in the place frame.
    direction : (N, 3) array
        Ray directions in the place frame, scaled so one unit is one metre of anchor-camera depth.
    """
    T_place_cam = invert(np.asarray(T_cam_place, dtype=float))[np.asarray(frame, dtype=int)]
    rays = camera.rays(np.asarray(uv, dtype=float))  # z = 1 in the anchor camera
    return T_place_cam[:, :3, 3], np.einsum("nij,nj->ni", T_place_cam[:, :3, :3], rays)


def ray_points(origin: np.ndarray, direction: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """Points (N, K, 3) at anchor depths along rays ``origin + d * direction`` (both (N, 3)).

    ``depths`` is (K,) (the same samples for every ray, as in the sweep) or (N, K) (per ray).
    """
    d = np.asarray(depths, dtype=float)
    if d.ndim == 1:
        return origin[:, None, :] + d[None, :, None] * direction[:, None, :]
    return origin[:, None, :] + d[:, :, None] * direction[:, None, :]


def derotate_pixels(uv: np.ndarray, T_cam_place: np.ndarray, T_place_cam0: np.ndarray,
                    camera: Camera) -> np.ndarray:
    """Remove the camera rotation from detections: where each ray would hit the image of camera ``c0``.

    Rotating every window detection into a common orientation (the place camera's) leaves only the image
    motion due to translation, which for a landmark seen from a straight path is a straight line through
    the epipole whatever its depth -- the shape the temporal check fits.

    Parameters
    ----------
    uv : (N, F, 2) array
        Ideal pixels (NaN where missing).
    T_cam_place : (F, 4, 4) array
    T_place_cam0 : (4, 4) array
        Pose of the common camera in the place frame (usually ``T_vehicle_camera``).
    camera : Camera
        Ideal camera.

    Returns
    -------
    (N, F, 2) array
        Derotated pixels; NaN where missing or where the rotated ray points backwards.
    """
    uv = np.asarray(uv, dtype=float)
    N, F = uv.shape[:2]
    rays = camera.rays(uv.reshape(-1, 2)).reshape(N, F, 3)
    # R_{c0,cj} = R_{c0,p} R_{p,cj}
    R_c0_p = np.asarray(T_place_cam0, dtype=float)[:3, :3].T
    R_c0_cj = np.einsum("ik,fjk->fij", R_c0_p, np.asarray(T_cam_place, dtype=float)[:, :3, :3])
    r0 = np.einsum("fij,nfj->nfi", R_c0_cj, rays)
    out, _ = camera.project(r0.reshape(-1, 3))
    return out.reshape(N, F, 2)


def camera_depth(P_place: np.ndarray, T_vehicle_camera: np.ndarray) -> np.ndarray:
    """Depth (z) of place-frame points (..., 3) in the camera mounted on the vehicle at the place."""
    T_c_v = invert(np.asarray(T_vehicle_camera, dtype=float))
    P = np.asarray(P_place, dtype=float)
    return P @ T_c_v[2, :3] + T_c_v[2, 3]


def reference_area(areas) -> float:
    """The patch area ``a`` is measured in units of: the median of ``areas`` (pixels), 1 when there are
    none or one is not positive.  Dividing by it makes eq. 5's ``a / (λ s)`` dimensionless, so ``Q`` keeps
    its meaning -- the covariance of a typical patch at full scale and certainty."""
    areas = np.asarray(areas, dtype=float)
    return float(np.median(areas)) if areas.size and np.all(areas > 0) else 1.0


def detection_covariance_factor(area, prob, scale, area_ref: float, inverse: bool = False):
    """McManus et al. 2015, eq. 5: a detection's covariance is ``R = a / (λ s) · Q``; this is the factor
    ``a / (λ s)`` (``inverse``: its reciprocal ``λ s / a``, the information factor ``R⁻¹ = (λ s / a) Q⁻¹``),
    with ``a = area / area_ref`` (:func:`reference_area`), λ the detection probability (Platt) and s
    the pyramid scale it fired at.  Element-wise over arrays.

    Who chooses ``area_ref``: the landmark refinement (:func:`scenesig.mapping.refine.refine_landmarks`) uses the
    median area of the firings it weighs against each other in the window; the live detector
    (:mod:`scenesig.localiser.detector`) and the georeferencing (:mod:`scenesig.mapping.georef`) use the median box area
    of the place's classifiers, which does not depend on which of them fired in one image.  Both make
    ``a`` about 1 for a typical patch.  The two sets differ, and aligning them would change every
    landmark and covariance of a built map, so each keeps the set it was built and tuned with.
    """
    a = np.asarray(area, float) / float(area_ref)
    if inverse:
        return np.asarray(prob, float) * np.asarray(scale, float) / a
    return a / (np.asarray(prob, float) * np.asarray(scale, float))
