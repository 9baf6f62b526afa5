"""Synthetic data with known answers, for the tests and the benchmarks (one module for all of them).

* :func:`synthetic_place` -- a procedural place: one scene under many appearance conditions, with known
  alignment (a classifier mined on some conditions must fire at the right spot on a held-out one);
* :func:`synthetic_window` -- a window of frames with landmarks at known depths and classifier
  detections, for landmark refinement (:mod:`scenesig.mapping.refine`);
* :func:`synthetic_problem` -- one localisation problem (detections, landmarks, a perturbed prior and
  the true pose) for the solver (:mod:`scenesig.localiser.solver`).

It sits at the top of the library stack because it builds the inputs of every layer.  The place's
scene is a fixed random layout of "structures" -- filled rectangles (windows,
walls), vertical bars (trunks, poles), discs (canopies) and line segments -- over smooth
low-frequency shading; a *condition* re-renders it with a random global gamma, contrast, colour
cast, a shading ramp (sun direction), blur, sensor noise, and a small known shift of the camera.
"""
from __future__ import annotations

import cv2
import numpy as np

from scenesig.mapping.geometry import camera_poses, reproject
from scenesig.mapping.refine import WindowDetections
from scenesig.surveys.geometry import CAMERA_FROM_VEHICLE_AXES, Camera, invert, make_pose, rot_z

from .solver import pose_exp

__all__ = ["synthetic_scene", "synthetic_place", "synthetic_window", "synthetic_problem"]


def synthetic_scene(width: int, height: int, seed: int = 0, n_structures: int | None = None):
    """Render the condition-free scene (BGR float32 in [0, 1]), larger than the view by a margin
    so that shifted views stay inside it.  Returns (scene, margin)."""
    rng = np.random.default_rng(seed)
    margin = max(16, int(0.1 * width))
    W, H = width + 2 * margin, height + 2 * margin
    base = rng.random((max(2, H // 32), max(2, W // 32), 3)).astype(np.float32)
    img = cv2.resize(base, (W, H), interpolation=cv2.INTER_CUBIC) * 0.4 + 0.3
    n = n_structures or max(12, (W * H) // 3000)
    for _ in range(n):
        col = tuple(float(c) for c in rng.random(3))
        kind = rng.integers(4)
        x, y = int(rng.integers(0, W)), int(rng.integers(0, H))
        if kind == 0:      # rectangle (window / wall patch)
            w, h = int(rng.integers(8, W // 6)), int(rng.integers(8, H // 5))
            cv2.rectangle(img, (x, y), (x + w, y + h), col, -1)
            if rng.random() < 0.5:
                cv2.rectangle(img, (x + 3, y + 3), (x + w - 3, y + h - 3),
                              tuple(1 - c for c in col), 2)
        elif kind == 1:    # vertical bar (trunk / pole)
            w = int(rng.integers(3, 14))
            cv2.rectangle(img, (x, y), (x + w, min(H, y + int(rng.integers(H // 4, H)))), col, -1)
        elif kind == 2:    # disc (canopy / sign)
            cv2.circle(img, (x, y), int(rng.integers(5, H // 6)), col, -1)
        else:              # line segment (edge / cable)
            x2, y2 = x + int(rng.integers(-W // 4, W // 4)), y + int(rng.integers(-H // 4, H // 4))
            cv2.line(img, (x, y), (x2, y2), col, int(rng.integers(1, 4)))
    # Fine texture so that flat regions are not perfectly flat.
    img += rng.normal(0, 0.02, img.shape).astype(np.float32)
    return np.clip(img, 0, 1), margin


def synthetic_place(n: int, width: int = 640, height: int = 480, seed: int = 0,
                    max_shift: float = 12.0, strength: float = 1.0):
    """Views of one synthetic place under ``n`` appearance conditions.

    Parameters
    ----------
    n : int
        Number of conditions (views).
    width, height : int
        View size in pixels.
    seed : int
        Scene and conditions seed (the scene depends on ``seed`` only, conditions on ``seed`` and
        the view index).
    max_shift : float
        Largest camera shift (pixels) of a view relative to view 0 (view 0 is unshifted).
    strength : float
        Scales the photometric changes (0: identical appearance).

    Returns
    -------
    images : list of ndarray
        BGR uint8 views.
    offsets : ndarray, shape (n, 2)
        A scene point at (x, y) in view 0 appears at (x + dx, y + dy) in view i.
    """
    scene, margin = synthetic_scene(width, height, seed)
    images, offsets = [], []
    for i in range(n):
        rng = np.random.default_rng([seed, i + 1])
        dx, dy = (0.0, 0.0) if i == 0 else tuple(rng.uniform(-max_shift, max_shift, 2))
        # View i shows the scene translated by (dx, dy): crop starting at margin - d.
        M = np.float32([[1, 0, dx - margin], [0, 1, dy - margin]])
        v = cv2.warpAffine(scene, M, (width, height), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT)
        s = strength if i > 0 else 0.0
        ramp = np.linspace(-1, 1, width, dtype=np.float32)[None, :] * rng.uniform(-0.25, 0.25) * s
        v = v * (1 + ramp[:, :, None])
        v = v * (1 + s * rng.uniform(-0.2, 0.2, 3)[None, None, :])
        m = v.mean()
        v = m + (1 + s * rng.uniform(-0.4, 0.3)) * (v - m)
        v = np.clip(v, 0, 1) ** float(np.exp(s * rng.uniform(-0.5, 0.5)))
        if s > 0 and rng.random() < 0.5:
            v = cv2.GaussianBlur(v, (0, 0), 0.5 + s * rng.random())
        v = v + rng.normal(0, 0.02 * s, v.shape).astype(np.float32)
        images.append(np.clip(v * 255, 0, 255).astype(np.uint8))
        offsets.append((dx, dy))
    return images, np.asarray(offsets, dtype=float)


def synthetic_window(n_landmarks=300, n_frames=21, spacing=1.0, path="straight", radius=60.0,
                     depth_range=(5.0, 90.0), sigma_px=1.0, outlier_rate=0.05, dropout_rate=0.1,
                     n_random=0, seed=0, camera: Camera | None = None):
    """A window of frames along a straight or curved path, with landmarks at known depths.

    Detection noise is drawn from the covariance the refinement assumes, ``R = a/(lambda s) Q`` with
    ``Q = sigma_px^2 I``, ``a = 1``, ``lambda`` in [0.5, 1] and ``s`` in {1, 0.5}; a fraction
    ``outlier_rate`` of detections are replaced by uniform random pixels.  The last ``n_random``
    classifiers fire at random pixels in every frame (what the temporal check must reject).

    Returns
    -------
    dict
        ``detections``, ``T_window_place``, ``camera``, ``T_vehicle_camera``, ``reference``, ``Q``,
        ``points`` (N, 3) true landmarks in the place frame (NaN for random classifiers), ``depth`` (N,)
        true place-camera depths, ``random`` (N,) bool.
    """
    rng = np.random.default_rng(seed)
    cam = camera or Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.5, 0.0, 1.5])
    ref = n_frames // 2
    arc = (np.arange(n_frames) - ref) * spacing
    if path == "straight":
        T_place_window = np.stack([make_pose(None, [x, 0.0, 0.0]) for x in arc])
    elif path == "curved":
        yaw = arc / radius
        T_place_window = np.stack([make_pose(rot_z(th), [radius * np.sin(th), radius * (1 - np.cos(th)), 0.0])
                                   for th in yaw])
    else:
        raise ValueError(f"path must be 'straight' or 'curved', got {path!r}")
    T_wp = invert(T_place_window)
    n_true = n_landmarks - n_random
    depth = rng.uniform(*depth_range, n_true)
    uv0 = np.column_stack([rng.uniform(40, cam.width - 40, n_true), rng.uniform(40, cam.height - 40, n_true)])
    P_place = (np.concatenate([cam.backproject(uv0, depth), np.ones((n_true, 1))], axis=1) @ T_vc.T)[:, :3]
    T_cp = camera_poses(T_wp, T_vc)
    uv, zc = reproject(T_cp, P_place, cam)
    visible = (zc > 0.5) & cam.in_image(uv.reshape(-1, 2)).reshape(zc.shape)
    N, F = n_landmarks, n_frames
    prob = rng.uniform(0.5, 1.0, (N, F))
    scale = rng.choice([1.0, 0.5], size=(N, F))
    sig = sigma_px / np.sqrt(prob * scale)
    det = np.full((N, F, 2), np.nan)
    det[:n_true] = np.where(visible[..., None], uv + rng.standard_normal((n_true, F, 2)) * sig[:n_true, :, None],
                            np.nan)
    det[n_true:] = np.stack([rng.uniform(0, cam.width, (n_random, F)), rng.uniform(0, cam.height, (n_random, F))],
                            axis=2)
    det[rng.random((N, F)) < dropout_rate] = np.nan
    det[:, ref][:n_true] = np.where(visible[:, ref, None], uv[:, ref] + rng.standard_normal((n_true, 2)) *
                                    sig[:n_true, ref, None], np.nan)  # the classifier was mined here
    out = (rng.random((N, F)) < outlier_rate) & np.isfinite(det).all(axis=2)
    out[:, ref] = False
    det[out] = np.stack([rng.uniform(0, cam.width, out.sum()), rng.uniform(0, cam.height, out.sum())], axis=1)
    points = np.full((N, 3), np.nan)
    points[:n_true] = P_place
    true_depth = np.full(N, np.nan)
    true_depth[:n_true] = depth
    return {"detections": WindowDetections(det, scale, prob, np.ones(N)), "T_window_place": T_wp, "camera": cam,
            "T_vehicle_camera": T_vc, "reference": ref, "Q": (sigma_px ** 2) * np.eye(2), "points": points,
            "depth": true_depth, "random": np.arange(N) >= n_true}


def synthetic_problem(n_detections=50, outlier_fraction=0.2, seed=0, pixel_sigma=1.0, landmark_sigma=0.3,
                      prior_sigmas=(0.02, 0.02, 0.05, 1.0, 1.0, 0.3)):
    """A random but repeatable place with far-field landmarks, detections, outliers and a perturbed prior.

    Returns a dict with the inputs of :func:`solve` (keys ``uv, R, landmarks, landmark_cov,
    T_place_vehicle_prior, P_prior, camera, T_vehicle_camera``) plus ``T_true`` and ``outliers``.
    Used by the tests and the benchmark.
    """
    rng = np.random.default_rng(seed)
    camera = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    T_vc = make_pose(CAMERA_FROM_VEHICLE_AXES, [1.5, 0.0, 1.4])
    T_true = make_pose(rot_z(0.05), [3.0, -0.8, 0.1])
    # Landmarks 8-60 m ahead of the true camera, inside the image.
    depth = rng.uniform(8.0, 60.0, n_detections)
    uv_true = np.column_stack([rng.uniform(20, 620, n_detections), rng.uniform(20, 460, n_detections)])
    P_c = camera.backproject(uv_true, depth)
    T_pc = T_true @ T_vc
    landmarks_true = P_c @ T_pc[:3, :3].T + T_pc[:3, 3]
    landmark_cov = np.tile(np.eye(3) * landmark_sigma ** 2, (n_detections, 1, 1))
    landmarks = landmarks_true + rng.normal(0, landmark_sigma, landmarks_true.shape)
    R = np.tile(np.eye(2) * pixel_sigma ** 2, (n_detections, 1, 1))
    uv = uv_true + rng.normal(0, pixel_sigma, uv_true.shape)
    n_out = int(round(outlier_fraction * n_detections))
    outliers = np.zeros(n_detections, bool)
    out_idx = rng.choice(n_detections, n_out, replace=False)
    outliers[out_idx] = True
    uv[out_idx] = np.column_stack([rng.uniform(0, 640, n_out), rng.uniform(0, 480, n_out)])
    sig = np.asarray(prior_sigmas, float)
    P_prior = np.diag(sig ** 2)
    T_prior = T_true @ pose_exp(rng.normal(0, 1, 6) * sig)
    return {"uv": uv, "R": R, "landmarks": landmarks, "landmark_cov": landmark_cov,
            "T_place_vehicle_prior": T_prior, "P_prior": P_prior, "camera": camera,
            "T_vehicle_camera": T_vc, "T_true": T_true, "outliers": outliers}
