"""Is a run's camera one the map can localise?  ``scenesig check RUN MAP`` and ``scenesig localise``.

Two questions, answered separately:

1. **What differs from the map's camera** (:func:`compare_cameras`) -- image size, focal lengths,
   principal point, distortion, the extrinsic ``T_vehicle_camera``.  Another size is incompatible (the
   banks' HOG templates and their windows are laid out on the map's image grid); anything else is
   listed, but is no reason to refuse: another vehicle's camera has other intrinsics and another
   mounting, and the localiser projects the map's landmarks through the *run's* camera (McManus et al.
   2015, eq. 1), so a different camera that is correctly described localises.

2. **Is the run's calibration right** (:func:`rotation_consistency`) -- checked against the run's own
   images and odometry, so it needs neither the map nor any truth.  How far the camera turns between two
   frames is known twice: from the odometry, and from the images through the intrinsics (the essential
   matrix of matched ORB features in normalised coordinates).  The rotation *angle* does not depend on
   the extrinsic (it is the same rotation seen from another frame), and a focal length ``k`` times the
   true one makes the images' rotation about ``1/k`` times the odometry's.  The median ratio of the two
   over the run's turns is 1 for a correct calibration, whatever the camera; a ratio far from 1 means the
   run's ``run.toml`` describes another camera than the one that took the images, and every pose solved
   through it would be wrong (with fx, fy halved, a localiser fed this run reported 41 of 54 fixes
   more than 5 m off, with no warning).

:func:`assess` combines them into :class:`Finding` lines (``error`` -> ``localise`` refuses, exit 2;
``warning`` -> it warns and goes on).  Thresholds and how they were chosen: ``docs/integrity.md``,
"Camera compatibility".
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from scenesig.surveys.geometry import Camera, interpolate_poses, invert, log_so3
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "Finding", "CameraAssessment", "compare_cameras", "rotation_consistency", "turns",
           "median_interval", "calibration_finding", "assess"]

default_config = {
    # Listed as a difference (a warning): focal length or principal point more than this share apart,
    # the extrinsic more than these apart.  A different camera is legitimate; the listing says what changed.
    "intrinsics_rel_tol": 0.02,       # of the focal length (fx, fy)
    "principal_point_tol": 0.01,      # of the image's larger side (cx, cy)
    "extrinsic_tol_m": 0.05,
    "extrinsic_tol_deg": 2.0,
    # Rotation consistency: frame pairs ``pair_dt_s`` apart (twice, four times that where too few turn
    # enough) whose odometry turns between ``min_turn_deg`` and ``max_turn_deg``; at most ``max_pairs`` of
    # them, evenly spread; at least ``min_pairs`` with an estimate to judge at all.
    "pair_dt_s": 0.4,
    "min_turn_deg": 3.0,
    "max_turn_deg": 25.0,
    "max_pairs": 16,
    "min_pairs": 5,
    "orb_features": 800,
    "min_matches": 30,
    # A pair's rotation counts only when its essential matrix rests on this many RANSAC inliers: with
    # fewer (fog, night) the estimate is as often a spurious model as the scene's rotation.  The smallest
    # value, in steps of 5 from 15, with which no correctly calibrated run of the 24 integrity calibration
    # worlds (docs/integrity.md, "Camera compatibility") is refused; 15 refused a fog run's right calibration.
    "min_inliers": 30,
    # The images' rotation over the odometry's, median over the pairs: outside [1/refuse, refuse] the
    # calibration is wrong (error); outside [1/warn, warn] it is suspicious (warning).  Chosen on the
    # demo world's training runs (docs/integrity.md), never on the runs reported.
    "warn_ratio": 1.10,
    "refuse_ratio": 1.25,
    # A refusal stops the user's job, so it needs agreeing evidence: at least this many turns, and the
    # distribution-free ``refuse_confidence`` interval of their median ratio (order statistics; no model of
    # how a turn's estimate errs) wholly beyond ``refuse_ratio`` on one side.  Scattered estimates (fog, few
    # features, small turns) give a warning only: correctly calibrated fog runs gave medians of 1.34 over 5
    # turns (ratios 1.02-2.04 between the quartiles; the tiny test world, imported from a bag) and 2.82 over
    # 7 (0.43-11.4; docs/integrity.md, "Camera compatibility").  A design level, not fitted: 90 %.
    "refuse_min_pairs": 5,
    "refuse_confidence": 0.9,
}


@dataclass
class Finding:
    """One line of the comparison: what, how it differs, and whether it is an ``error`` or a ``warning``."""

    what: str
    reason: str
    severity: str = "warning"

    def __str__(self) -> str:
        return f"{self.severity}: {self.what}: {self.reason}"


@dataclass
class CameraAssessment:
    """The findings and the rotation-consistency measurement behind them."""

    findings: list = field(default_factory=list)
    rotation_ratio: float | None = None     # median images' / odometry's rotation (None: not measured)
    pairs: int = 0                          # frame pairs it was measured on

    @property
    def errors(self) -> list:
        return [f for f in self.findings if f.severity == "error"]

    @property
    def warnings(self) -> list:
        return [f for f in self.findings if f.severity == "warning"]

    def as_dict(self) -> dict:
        return {"findings": [asdict(f) for f in self.findings], "rotation_ratio": self.rotation_ratio,
                "pairs": self.pairs}


def _rot_deg(R: np.ndarray) -> float:
    """The rotation angle of ``R`` (its upper-left 3x3 block), in degrees."""
    return float(np.degrees(np.linalg.norm(log_so3(R[:3, :3]))))


def compare_cameras(camera: Camera, T_vehicle_camera, map_camera: Camera, map_T_vehicle_camera,
                    config: dict | None = None) -> list[Finding]:
    """The differences between a run's camera and a map's: size (error), intrinsics and extrinsic (warnings)."""
    cfg = merge_settings(default_config, config, "camera check")
    out: list[Finding] = []
    if (camera.width, camera.height) != (map_camera.width, map_camera.height):
        out.append(Finding("image size", f"{camera.width}x{camera.height}, the map's is "
                                         f"{map_camera.width}x{map_camera.height}: the map's signatures are laid out "
                                         f"on its image grid", "error"))
    tol = float(cfg["intrinsics_rel_tol"])
    for name in ("fx", "fy", "cx", "cy"):
        a, b = float(getattr(camera, name)), float(getattr(map_camera, name))
        focal = name in ("fx", "fy")
        limit = tol * max(abs(b), 1e-9) if focal else \
            cfg["principal_point_tol"] * max(map_camera.width, map_camera.height)
        if abs(a - b) > limit:
            out.append(Finding(name, f"{a:g}, the map's is {b:g} ({a / b:.3g}x)" if name in ("fx", "fy") and b
                               else f"{a:g}, the map's is {b:g}"))
    da, db = tuple(float(v) for v in camera.distortion), tuple(float(v) for v in map_camera.distortion)
    if any(da) or any(db):
        n = max(len(da), len(db))
        if not np.allclose(np.pad(da, (0, n - len(da))), np.pad(db, (0, n - len(db))), atol=1e-6):
            out.append(Finding("distortion", f"{list(da)}, the map's is {list(db)}"))
    D = invert(np.asarray(map_T_vehicle_camera, float)) @ np.asarray(T_vehicle_camera, float)
    dt, dr = float(np.linalg.norm(D[:3, 3])), _rot_deg(D)
    if dt > cfg["extrinsic_tol_m"] or dr > cfg["extrinsic_tol_deg"]:
        out.append(Finding("extrinsic", f"T_vehicle_camera is {dt:.3f} m and {dr:.2f} deg from the map's"))
    return out


def _pairs(run, cfg) -> list[tuple[int, int, float]]:
    """Frame pairs ``(i, j, odometry rotation deg)`` about ``pair_dt_s`` apart that turn enough."""
    ft = np.asarray(run.frame_times, float)
    ot = np.asarray(run.odometry_times, float)
    if len(ft) < 2 or len(ot) < 2:
        return []
    inside = np.flatnonzero((ft >= ot[0]) & (ft <= ot[-1]))
    if len(inside) < 2:
        return []
    P = interpolate_poses(ot, run.odometry_poses, ft[inside]).reshape(-1, 4, 4)
    cands = []
    for a in range(len(inside)):
        b = int(np.searchsorted(ft[inside], ft[inside[a]] + cfg["pair_dt_s"]))
        if b >= len(inside):
            break
        ang = _rot_deg(invert(P[a]) @ P[b])
        if cfg["min_turn_deg"] <= ang <= cfg["max_turn_deg"]:
            cands.append((int(inside[a]), int(inside[b]), ang))
    # non-overlapping pairs, evenly spread over the run
    picked, last = [], -1
    for c in cands:
        if c[0] > last:
            picked.append(c)
            last = c[1]
    k = int(cfg["max_pairs"])
    if len(picked) > k:
        picked = [picked[int(round(x))] for x in np.linspace(0, len(picked) - 1, k)]
    return picked


def _visual_rotation(img_a, img_b, camera: Camera, cfg) -> tuple[float, int] | None:
    """The rotation angle between two images through ``camera``'s intrinsics (essential matrix of ORB
    matches in normalised coordinates) and the RANSAC inliers it rests on, or None when too few features
    match."""
    import cv2

    orb = cv2.ORB_create(int(cfg["orb_features"]))
    ka, da = orb.detectAndCompute(img_a, None)
    kb, db = orb.detectAndCompute(img_b, None)
    if da is None or db is None or len(ka) < cfg["min_matches"] or len(kb) < cfg["min_matches"]:
        return None
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    if len(matches) < cfg["min_matches"]:
        return None
    pa = np.float64([ka[m.queryIdx].pt for m in matches]).reshape(-1, 1, 2)
    pb = np.float64([kb[m.trainIdx].pt for m in matches]).reshape(-1, 1, 2)
    K = camera.K
    dist = np.asarray(list(camera.distortion), float) if any(camera.distortion) else None
    na = cv2.undistortPoints(pa, K, dist).reshape(-1, 2)
    nb = cv2.undistortPoints(pb, K, dist).reshape(-1, 2)
    thr = 1.0 / max(camera.fx, camera.fy)          # one pixel, in normalised units
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None or E.shape != (3, 3) or mask is None:
        return None
    _, R, _, _ = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask)
    return _rot_deg(R), int(mask.sum())


def turns(run, config: dict | None = None) -> list[tuple[float, int]]:
    """``(images' rotation / odometry's, RANSAC inliers)`` for each of the run's turns measured through
    its camera (the measurement; :func:`calibration_finding` judges it)."""
    cfg = merge_settings(default_config, config, "camera check")
    # a straight road turns little between frames ``pair_dt_s`` apart: look further apart then
    for k in range(3):
        pairs = _pairs(run, {**cfg, "pair_dt_s": cfg["pair_dt_s"] * 2 ** k})
        if len(pairs) >= int(cfg["min_pairs"]):
            break
    out = []
    for i, j, ang in pairs:
        try:
            vis = _visual_rotation(run.image(i, gray=True), run.image(j, gray=True), run.camera, cfg)
        except Exception:       # an unreadable frame: the replay names it; here it is one pair less
            vis = None
        if vis is not None:
            out.append((vis[0] / ang, vis[1]))
    return out


def rotation_consistency(run, config: dict | None = None) -> tuple[float | None, int]:
    """Median ratio of the images' rotation (through the run's intrinsics) to the odometry's, over the
    run's turns, and the number of frame pairs it rests on (None with fewer than ``min_pairs``)."""
    cfg = merge_settings(default_config, config, "camera check")
    ratio, ratios = _median_ratio(turns(run, cfg), cfg)
    return ratio, len(ratios)


def _median_ratio(measured, cfg) -> tuple[float | None, list[float]]:
    """The turns that rest on ``min_inliers``: their median ratio (None with fewer than ``min_pairs``)
    and their ratios."""
    ratios = [r for r, inliers in measured if inliers >= cfg["min_inliers"]]
    if len(ratios) < int(cfg["min_pairs"]):
        return None, ratios
    return float(np.median(ratios)), ratios


def median_interval(values, confidence: float) -> tuple[float, float] | None:
    """The distribution-free interval ``[x_(j), x_(n+1-j)]`` of the median of ``values`` (order statistics,
    1-based), ``j`` the largest with which it covers the median with at least ``confidence``:
    ``1 - 2 P(B <= j - 1) >= confidence`` for ``B ~ Binomial(n, 1/2)``.  None when even the full range does
    not reach that confidence (too few values)."""
    from scipy.stats import binom

    x = np.sort(np.asarray(values, float))
    n = len(x)
    ok = [j for j in range(1, n // 2 + 1) if 1.0 - 2.0 * binom.cdf(j - 1, n, 0.5) >= confidence]
    return (float(x[ok[-1] - 1]), float(x[n - ok[-1]])) if ok else None


def calibration_finding(measured, config: dict | None = None) -> tuple[Finding | None, float | None, int]:
    """The verdict on :func:`turns`' measurement: a :class:`Finding` (``error``: refuse; ``warning``) or
    None, with the median ratio and the number of turns it rests on."""
    cfg = merge_settings(default_config, config, "camera check")
    ratio, ratios = _median_ratio(measured, cfg)
    n = len(ratios)
    if ratio is None:
        return None, None, n
    dev = max(ratio, 1.0 / ratio) if ratio > 0 else np.inf
    w, refuse = float(cfg["warn_ratio"]), float(cfg["refuse_ratio"])
    interval = median_interval(ratios, float(cfg["refuse_confidence"]))
    lo, hi = interval if interval is not None else (0.0, np.inf)
    agreeing = n >= int(cfg["refuse_min_pairs"]) and (lo > refuse or hi < 1.0 / refuse)
    msg = (f"turns seen in the images through the intrinsics are {ratio:.2f}x those the odometry measured "
           f"(median of {n} turns; 1 for a correct calibration): fx, fy are likely about "
           f"{1.0 / ratio:.2f}x the true ones")
    if dev > refuse and agreeing:
        return Finding("calibration", msg + " -- every pose solved through them would be wrong", "error"), ratio, n
    if dev > refuse:
        return Finding("calibration", msg + f" -- not refused: {n} turns whose ratios disagree (the median's "
                       f"{cfg['refuse_confidence']:.0%} interval {lo:.2f}-{hi:.2f} reaches within "
                       f"{refuse:g}x of 1) are too little evidence; check the calibration", "warning"), ratio, n
    if dev > w:
        return Finding("calibration", msg, "warning"), ratio, n
    return None, ratio, n


def assess(run, store=None, config: dict | None = None, consistency: bool = True) -> CameraAssessment:
    """Compare a run's camera with a map's (``store``, if given) and check its calibration against its
    own images and odometry (``consistency``).  See the module docstring for what is an error."""
    cfg = merge_settings(default_config, config, "camera check")
    out = CameraAssessment()
    if store is not None:
        out.findings += compare_cameras(run.camera, run.T_vehicle_camera, store.camera, store.T_vehicle_camera, cfg)
    if consistency:
        finding, out.rotation_ratio, out.pairs = calibration_finding(turns(run, cfg), cfg)
        if finding is not None:
            out.findings.append(finding)
    return out


def run_toml(run) -> Path | str:
    """Where a run's camera is described (for messages)."""
    return (Path(run.root) / "run.toml") if getattr(run, "root", None) is not None else str(run.name)
