"""Robust absolute pose from 2D-3D matches: the point-feature localiser's first step.

Point features give a few hundred putative matches of which, across a change of appearance, most
are wrong.  The field-standard answer (hloc, COLMAP's image registrator) is LO-RANSAC with a
minimal P3P solver, a number of trials driven by the confidence and the inlier ratio found so far
(not a fixed count), local optimisation of the best model and a final non-linear refinement on
the inliers.  Two libraries implement it and are installed; :func:`estimate` runs either:

``poselib`` (default)
    ``poselib.estimate_absolute_pose`` (Larsson, PoseLib, 2020-): LO-RANSAC over P3P (Ding et al.
    2023 / Lambda-twist), MSAC scoring, Cauchy-loss bundle refinement on the inliers.
``pycolmap``
    ``pycolmap.estimate_and_refine_absolute_pose``: COLMAP's LO-RANSAC with P3P and EPnP local
    optimisation, then a Ceres refinement -- what hloc's localiser calls.
``opencv``
    ``cv2.solvePnPRansac`` with EPnP minimal sets (a fixed iteration cap): kept for comparison.

Measured on synthetic matches with 70 % outliers (``python -m scenesig.benchmarks.absolute_pose``, written up
in the README): both libraries recover the pose every time with the same accuracy; poselib takes
about half pycolmap's time, so it is the default.

The input keypoints are in the (possibly distorted) image; they are mapped to ideal pinhole pixels
first so both libraries see a PINHOLE camera.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from scenesig.surveys.geometry import Camera
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "ESTIMATORS", "AbsolutePose", "estimate"]

ESTIMATORS = ("poselib", "pycolmap", "opencv")

default_config = {
    "estimator": "poselib",
    "max_error_px": 4.0,        # inlier threshold on the reprojection error (ideal pixels)
    "confidence": 0.9999,       # RANSAC stops when an all-inlier sample was drawn with this probability
    "min_iterations": 100,
    "max_iterations": 10000,    # cap: reached only below ~8 % inliers
    "seed": 0,                  # fixed so results repeat
}


@dataclass
class AbsolutePose:
    """Outcome of :func:`estimate`.

    Attributes
    ----------
    ok : a pose was found.
    T_cam_place : (4,4) place frame -> camera (None unless ``ok``).
    inliers : (N,) bool.
    iterations : RANSAC iterations run (-1: the library does not say).
    ms : wall time.
    """

    ok: bool
    T_cam_place: np.ndarray | None
    inliers: np.ndarray
    iterations: int
    ms: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _ideal(camera: Camera, uv: np.ndarray) -> np.ndarray:
    if not any(camera.distortion):
        return uv
    rays = camera.rays(uv)
    return np.stack([camera.fx * rays[:, 0] + camera.cx, camera.fy * rays[:, 1] + camera.cy], axis=1)


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def estimate(uv, xyz, camera: Camera, config: dict | None = None) -> AbsolutePose:
    """Robust camera pose from keypoints ``uv`` (N,2) and their 3D points ``xyz`` (N,3, place frame).

    Parameters
    ----------
    config : overrides of :data:`default_config`.

    Returns
    -------
    AbsolutePose
    """
    cfg = merge_settings(default_config, config, "absolute-pose")
    if cfg["estimator"] not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, got {cfg['estimator']!r}")
    t0 = time.perf_counter()
    uv = np.ascontiguousarray(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    xyz = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
    n = len(uv)
    if len(xyz) != n:
        raise ValueError(f"{n} keypoints but {len(xyz)} 3D points")
    none = AbsolutePose(False, None, np.zeros(n, bool), 0, 0.0)
    if n < 4:
        none.ms = (time.perf_counter() - t0) * 1e3
        return none
    ideal = np.ascontiguousarray(_ideal(camera, uv))
    est = cfg["estimator"]
    if est == "poselib":
        import poselib

        cam = {"model": "PINHOLE", "width": int(camera.width), "height": int(camera.height),
               "params": [camera.fx, camera.fy, camera.cx, camera.cy]}
        ransac = {"max_reproj_error": float(cfg["max_error_px"]), "success_prob": float(cfg["confidence"]),
                  "min_iterations": int(cfg["min_iterations"]), "max_iterations": int(cfg["max_iterations"]),
                  "seed": int(cfg["seed"])}
        pose, info = poselib.estimate_absolute_pose(ideal, xyz, cam, ransac, {})
        inl = np.asarray(info.get("inliers", []), bool).reshape(-1)
        ok = len(inl) == n and inl.sum() >= 4
        T = _pose(pose.R, pose.t) if ok else None
        iters = int(info.get("iterations", 0))
    elif est == "pycolmap":
        from scenesig.surveys.extras import require

        pycolmap = require("pycolmap", "colmap", "the pycolmap absolute-pose estimator")

        cam = pycolmap.Camera(model="PINHOLE", width=int(camera.width), height=int(camera.height),
                              params=[camera.fx, camera.fy, camera.cx, camera.cy])
        opts = pycolmap.AbsolutePoseEstimationOptions()
        opts.ransac.max_error = float(cfg["max_error_px"])
        opts.ransac.confidence = float(cfg["confidence"])
        opts.ransac.min_num_trials = int(cfg["min_iterations"])
        opts.ransac.max_num_trials = int(cfg["max_iterations"])
        opts.ransac.min_inlier_ratio = 0.01
        opts.ransac.random_seed = int(cfg["seed"])
        res = pycolmap.estimate_and_refine_absolute_pose(ideal, xyz, cam, opts)
        ok = res is not None
        if ok:
            m = res["cam_from_world"].matrix()
            T = _pose(m[:3, :3], m[:3, 3])
            inl = np.asarray(res["inlier_mask"], bool).reshape(-1)
            iters = -1                      # pycolmap does not report its trials
        else:
            T, inl, iters = None, np.zeros(n, bool), 0
    else:
        import cv2

        cv2.setRNGSeed(int(cfg["seed"]))
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            xyz, ideal, camera.K, None, iterationsCount=int(cfg["max_iterations"]),
            reprojectionError=float(cfg["max_error_px"]), confidence=float(cfg["confidence"]),
            flags=cv2.SOLVEPNP_EPNP)
        inl = np.zeros(n, bool)
        if ok and idx is not None:
            inl[idx.ravel()] = True
        ok = bool(ok) and inl.sum() >= 4
        T = _pose(cv2.Rodrigues(rvec)[0], tvec) if ok else None
        iters = int(cfg["max_iterations"])
    return AbsolutePose(bool(ok), T, inl if ok else np.zeros(n, bool), iters, (time.perf_counter() - t0) * 1e3)
