"""Point-feature map of a place (the ORB / SIFT baselines of McManus et al. 2015, §4): keyframe features with 3D points.

The point-feature localiser the paper compares against matches the live image to a *map image* and
solves for the pose from the 2D-3D correspondences.  Its map, per place:

1. the *keyframe* -- the reference run's frame at the place (the frame that defines the place frame);
   its ORB and SIFT features (upright, the strongest ``n_candidates`` by detector response, as in
   :func:`scenesig.signatures.pointfeatures.extract`);
2. *tracks* -- the keyframe is matched to the reference run's frames about 2.5 and 5 m ahead and
   behind (``baselines_m``), whose poses relative to the keyframe come from the run's odometry
   (``TrainingView.T_frame_window``; smooth over a few metres).  Matches are mutual nearest neighbours
   with Lowe's ratio test, then gated by the epipolar constraint the known relative pose gives
   (Sampson distance), so almost no wrong match survives;
3. *triangulation* -- multi-view DLT over every view of a track, Gauss-Newton on the reprojection error,
   dropping the worst view while one disagrees; a point is kept when it is in front of every camera
   within the depth bounds, reprojects within ``reprojection_px`` in every view and is seen under at
   least ``min_parallax_deg`` (points near the focus of expansion of forward motion have no depth);
4. *selection* -- at most ``max_points`` per kind, spread over the image (round robin over a grid of
   cells, best first), so PnP is well conditioned and the place stays small.

Everything is in the place frame (the vehicle frame of the keyframe), like the signatures' landmarks.
:func:`build_point_features` returns plain arrays, stored by :class:`scenesig.mapping.store.PlaceData` under
``points/``:

``{kind}_kp`` (N,2) float32
    keypoint positions in the keyframe (pixels);
``{kind}_desc`` (N,D)
    descriptors: uint8 for ORB; for SIFT uint8 when that is lossless (OpenCV's SIFT descriptors are
    integers in 0..255, so it is), else float16 if lossless, else float32;
``{kind}_xyz`` (N,3) float32
    3D points in the place frame (metres);
``{kind}_sigma`` (N,2) float16
    their uncertainty ``(σ_across, σ_along)`` (m): across and along the keyframe's viewing ray, from the
    triangulation's information matrix with ``pixel_sigma`` per keypoint.  :func:`point_covariances`
    turns it back into (N,3,3) covariances.

The ``all`` point map (:func:`build_point_features_all`) holds the same per keyframe for a keyframe of
every training run at the place, moved into the place frame: ``{kind}_all_kp``, ``_desc``, ``_xyz``,
``_sigma``, ``_keyframe`` (which keyframe each point belongs to) and ``all_T_place_keyframe`` (K,4,4).

:func:`add_to_map` adds the point features to an existing map built without them (every place file is
rewritten atomically with its new checksum; the banks are untouched).

``scenesig bench pointmap RUN --frame I`` builds one keyframe's point map from a survey run and prints
its statistics (and, for simulated runs with ``truth`` depth, the depth error);
``scenesig map add-points MAP --reference RUN`` adds point features to a map.
"""
from __future__ import annotations

import time

import numpy as np

from scenesig.mapping.geometry import camera_poses, ideal_camera, ideal_pixels, reproject_jacobian
from scenesig.signatures.pointfeatures import PointFeatures, default_config as features_default, extract, match
from scenesig.surveys.geometry import Camera, invert
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "resolve_config", "build_point_features", "build_point_features_all", "combine_keyframe_maps",
           "point_keyframes",
           "point_map_covariances", "POINT_MAPS", "triangulate_keyframe", "triangulate_tracks",
           "point_covariances", "point_features", "select_frames", "keypoint_sigma", "add_to_map", "KINDS",
           "TriangulationStats"]

KINDS = ("orb", "sift", "xfeat")

default_config = {
    "kinds": ["orb", "sift"],
    "n_candidates": 1500,        # keyframe / window features detected per kind (strongest by response)
    # XFeat's keyframe / window keypoints: upstream's top-k (Potje et al. 2024), as the live images get
    "xfeat_candidates": 4096,
    "max_points": 500,           # 3D points kept per kind (keeps a place well under 0.25 MB)
    "baselines_m": [-5.0, -2.5, 2.5, 5.0],  # window frames matched to the keyframe, by signed distance
    "baseline_tolerance_m": 1.25,           # a baseline with no frame this close to it is skipped
    "ratio": 0.8,                # Lowe's ratio for keyframe <-> window matches (mutual as well)
    # XFeat's keyframe <-> window matches: its own matcher (mutual NN, cosine similarity above this;
    # upstream's default) instead of the ratio test
    "xfeat_min_cossim": 0.82,
    "epipolar_px": 2.0,          # Sampson distance gate with the known relative pose (pixels)
    "reprojection_px": 2.0,      # a kept point reprojects within this in every view it keeps
    "min_parallax_deg": 1.0,     # largest angle between its viewing rays
    "min_depth_m": 1.0,          # depth bounds in the keyframe camera
    "max_depth_m": 150.0,
    "pixel_sigma": 1.0,          # keypoint noise (px) for the points' covariance
    "grid": [8, 6],              # cells (columns, rows) over which kept points are spread
    "gauss_newton_iterations": 6,
    "features": {},              # overrides of signatures.pointfeatures.default_config (upright, orb, sift)
}


def _merge(config: dict | None) -> dict:
    cfg = merge_settings(default_config, config, "point-map", open=("features",))
    for kind in cfg["kinds"]:
        if kind not in KINDS:
            raise ValueError(f"unknown point-feature kind {kind!r}; choose from {KINDS}")
    return cfg


def resolve_config(config: dict | None = None) -> dict:
    """Every point-map setting, its features' included: ``config`` (overrides of :data:`default_config`)."""
    cfg = _merge(config)
    cfg["features"] = merge_settings(features_default, cfg["features"], "point-feature", open=("xfeat",))
    return cfg


class TriangulationStats(dict):
    """Counts of one keyframe's triangulation (a dict: ``candidates``, ``tracked``, ``triangulated``,
    ``kept`` and the rejections ``behind``, ``depth``, ``reprojection``, ``parallax``)."""


def keypoint_sigma(features: PointFeatures, pixel_sigma: float = 1.0, config: dict | None = None) -> np.ndarray:
    """Position std. dev. (px) of each keypoint: ``pixel_sigma`` times its octave's scale (at least half).

    ORB's octave field is the pyramid level (scale ``scaleFactor ** level``); SIFT packs the octave in
    the low byte (signed; -1 is the up-sampled first octave, scale 1/2).  ``config``: overrides of
    :data:`scenesig.signatures.pointfeatures.default_config` (for ORB's ``scaleFactor``).
    """
    oct_ = np.asarray(features.octave, dtype=np.int64)
    if features.kind == "orb":
        f = float(merge_settings(features_default, config, "point-feature", open=("xfeat",))["orb"]["scaleFactor"])
        scale = f ** np.clip(oct_, 0, None)
    else:
        o = oct_ & 255
        o = np.where(o >= 128, o - 256, o)
        scale = 2.0 ** o.astype(float)
    return pixel_sigma * np.maximum(scale, 0.5)


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------
def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def _sampson_px(x0: np.ndarray, x1: np.ndarray, T_c1_c0: np.ndarray, f: float) -> np.ndarray:
    """Sampson distance (in pixels of focal length ``f``) of normalised correspondences x0 -> x1 (N,2).

    ``E = [t]x R`` with ``T_c1_c0 = (R, t)``: ``x1^T E x0 = 0`` for a true correspondence.
    """
    E = _skew(T_c1_c0[:3, 3]) @ T_c1_c0[:3, :3]
    h0 = np.column_stack([x0, np.ones(len(x0))])
    h1 = np.column_stack([x1, np.ones(len(x1))])
    Ex0 = h0 @ E.T
    Etx1 = h1 @ E
    num = np.einsum("ij,ij->i", h1, Ex0)
    den = Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return f * np.abs(num) / np.sqrt(den)


def triangulate_tracks(uv: np.ndarray, T_cam_place: np.ndarray, camera: Camera, config: dict | None = None,
                       sigma: np.ndarray | None = None):
    """Multi-view triangulation of tracks with known camera poses.

    Parameters
    ----------
    uv : (N, F, 2) array
        Observations of N points in F views (pixels of ``camera``); NaN where a view does not see it.
        View 0 is the keyframe; a point needs view 0 and at least one other.
    T_cam_place : (F, 4, 4) array
        Camera poses ``T_{c_j,p}`` (place frame -> camera j).
    camera : Camera
    config : overrides of :data:`default_config` (``reprojection_px``, ``min_parallax_deg``, depth
        bounds, ``pixel_sigma``, ``gauss_newton_iterations``).
    sigma : (N, F) array, optional
        Std. dev. (px) of each observation (e.g. :func:`keypoint_sigma`: coarse-octave keypoints are
        less precise); default ``pixel_sigma`` everywhere.  Observations are weighted by ``1/σ²`` and
        the reprojection gate is ``reprojection_px · σ / pixel_sigma``.

    Returns
    -------
    xyz : (N, 3) points in the place frame (NaN where not triangulated).
    keep : (N,) bool, the point passed every gate.
    cov : (N, 3, 3) covariances: the inverse of the information (observations weighted by ``1/σ²``).
    reason : (N,) str array: ``""`` kept, or ``"views"``, ``"behind"``, ``"depth"``, ``"reprojection"``,
        ``"parallax"``.
    """
    cfg = _merge(config)
    cam = ideal_camera(camera)
    uv = ideal_pixels(camera, np.asarray(uv, dtype=float))
    T = np.asarray(T_cam_place, dtype=float)
    N, F = uv.shape[:2]
    if T.shape != (F, 4, 4):
        raise ValueError(f"T_cam_place must be ({F}, 4, 4) for {F} views, got {T.shape}")
    seen = np.isfinite(uv).all(axis=2)
    ps = float(cfg["pixel_sigma"])
    sig = np.full((N, F), ps) if sigma is None else np.asarray(sigma, dtype=float).reshape(N, F)
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, ps)
    wgt = 1.0 / sig ** 2                                       # information weight of each observation
    gate = cfg["reprojection_px"] * sig / ps                  # reprojection gate per observation
    reason = np.full(N, "", dtype=object)
    xyz = np.full((N, 3), np.nan)
    cov = np.full((N, 3, 3), np.nan)
    reason[~(seen[:, 0] & (seen.sum(axis=1) >= 2))] = "views"
    todo = np.flatnonzero(reason == "")
    if not len(todo):
        return xyz, np.zeros(N, bool), cov, reason.astype(str)

    # Normalised image coordinates.
    xn = np.stack([(uv[..., 0] - cam.cx) / cam.fx, (uv[..., 1] - cam.cy) / cam.fy], axis=-1)
    P = T[:, :3, :]                                            # (F, 3, 4)

    def dlt(idx, mask):
        # Rows x * P3 - P1 and y * P3 - P2 per view; missing views give zero rows (no effect).
        x = np.nan_to_num(xn[idx])                             # (n, F, 2)
        A = np.concatenate([x[..., 0:1] * P[None, :, 2] - P[None, :, 0],
                            x[..., 1:2] * P[None, :, 2] - P[None, :, 1]], axis=1)  # (n, 2F, 4)
        w = np.concatenate([mask[idx], mask[idx]], axis=1).astype(float)
        A = A * w[..., None]
        # Row scaling does not change the DLT solution but keeps it well conditioned.
        A /= np.maximum(np.linalg.norm(A, axis=2, keepdims=True), 1e-12)
        _, _, Vt = np.linalg.svd(A)
        X = Vt[:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            return X[:, :3] / X[:, 3:4]

    def gauss_newton(X, idx, mask):
        info = np.zeros((len(idx), 3, 3))
        for _ in range(int(cfg["gauss_newton_iterations"]) + 1):
            pred, z, H = reproject_jacobian(T, X, cam)          # (n,F,2), (n,F), (n,F,2,3)
            m = mask[idx] & (z > 1e-6)
            r = np.where(m[..., None], uv[idx] - pred, 0.0)
            H = np.where(m[..., None, None], np.nan_to_num(H), 0.0)
            wH = H * wgt[idx][..., None, None]
            info = np.einsum("nfki,nfkj->nij", wH, H)
            g = np.einsum("nfki,nfk->ni", wH, r)
            ok = np.linalg.det(info) > 1e-18
            step = np.zeros_like(X)
            step[ok] = np.linalg.solve(info[ok], g[ok][..., None])[..., 0]
            X = X + step
        return X, info

    mask = seen.copy()
    X = dlt(todo, mask)
    good = np.isfinite(X).all(axis=1)
    X[~good] = 0.0
    X, info = gauss_newton(X, todo, mask)
    # View rejection: while a point has a view beyond the gate and more than two views, drop its
    # worst non-keyframe view and re-solve (one wrong match drags every view's residual up, so
    # dropping all views over the gate at once would throw good ones away).
    for _ in range(F - 2):
        pred, z, _ = reproject_jacobian(T, X, cam)
        err = np.where(mask[todo], np.linalg.norm(uv[todo] - pred, axis=2) / gate[todo], -np.inf)
        err[:, 0] = -np.inf                                    # the keyframe view is the point's anchor
        worst = np.argmax(err, axis=1)
        again = (err[np.arange(len(todo)), worst] > 1.0) & (mask[todo].sum(axis=1) >= 3)
        if not again.any():
            break
        sub = todo[again]
        mask[sub, worst[again]] = False
        X2 = dlt(sub, mask)
        ok2 = np.isfinite(X2).all(axis=1)
        X2[~ok2] = 0.0
        X2, info2 = gauss_newton(X2, sub, mask)
        X[again], info[again] = X2, info2
        good[again] = ok2
    pred, z, _ = reproject_jacobian(T, X, cam)
    m = mask[todo]
    err = np.where(m, np.linalg.norm(uv[todo] - pred, axis=2) / gate[todo], 0.0)   # in units of the gate
    zm = np.where(m, z, np.inf)
    # Parallax: the largest angle between the point's viewing rays (camera centres -> point).
    centres = invert(T)[:, :3, 3]                              # (F, 3)
    rays = X[:, None, :] - centres[None]                      # (n, F, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    cosang = np.einsum("nfi,ngi->nfg", rays, rays)
    both = m[:, :, None] & m[:, None, :]
    parallax = np.degrees(np.arccos(np.clip(np.where(both, cosang, 1.0), -1, 1))).max(axis=(1, 2))
    r = np.full(len(todo), "", dtype=object)
    r[parallax < cfg["min_parallax_deg"]] = "parallax"
    r[err.max(axis=1) > 1.0] = "reprojection"
    r[(z[:, 0] < cfg["min_depth_m"]) | (z[:, 0] > cfg["max_depth_m"])] = "depth"
    r[~(zm > 1e-6).all(axis=1) | ~good | ~np.isfinite(X).all(axis=1)] = "behind"
    reason[todo] = r
    xyz[todo] = X
    with np.errstate(invalid="ignore"):
        det_ok = np.linalg.det(info) > 1e-18
    c = np.full((len(todo), 3, 3), np.nan)
    c[det_ok] = np.linalg.inv(info[det_ok])                   # information already carries 1/σ²
    cov[todo] = c
    reason[todo[~det_ok & (r == "")]] = "parallax"
    keep = reason == ""
    return xyz, keep, cov, reason.astype(str)


def point_covariances(xyz: np.ndarray, sigma: np.ndarray, T_vehicle_camera: np.ndarray) -> np.ndarray:
    """(N,3,3) covariances from stored ``(σ_across, σ_along)`` of points seen from the keyframe camera.

    ``Σ = σ_across² I + (σ_along² - σ_across²) r rᵀ`` with ``r`` the unit ray from the keyframe camera
    centre (the place frame's camera) to the point.
    """
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    s = np.asarray(sigma, dtype=float).reshape(-1, 2)
    r = xyz - np.asarray(T_vehicle_camera, dtype=float)[:3, 3]
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    a2, b2 = s[:, 0] ** 2, s[:, 1] ** 2
    return a2[:, None, None] * np.eye(3)[None] + (b2 - a2)[:, None, None] * np.einsum("ni,nj->nij", r, r)


def _compress_sigma(xyz, cov, T_vehicle_camera) -> np.ndarray:
    """``(σ_across, σ_along)`` of covariances w.r.t. the keyframe ray (float16, clipped to its range)."""
    r = xyz - np.asarray(T_vehicle_camera, dtype=float)[:3, 3]
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    along = np.einsum("ni,nij,nj->n", r, cov, r)
    across = (np.trace(cov, axis1=1, axis2=2) - along) / 2
    s = np.sqrt(np.clip(np.column_stack([across, along]), 1e-8, None))
    # float16 has ~3 significant digits, plenty for an uncertainty; its range ends at 65504
    return np.clip(s, 1e-3, 6e4).astype(np.float16)


# --------------------------------------------------------------------------------------------------
# features
# --------------------------------------------------------------------------------------------------
def point_features(points: dict, kind: str, point_map: str = "reference") -> PointFeatures | None:
    """The stored map features of one kind as :class:`PointFeatures` (None if the place has none).

    ``point_map``: ``"reference"`` (the reference run's keyframe) or ``"all"`` (the keyframes of every
    training run, :func:`build_point_features_all`; :func:`point_keyframes` says which is which).
    """
    key = f"{_prefix(kind, point_map)}_kp"
    if key not in points:
        return None
    xy = np.asarray(points[key], dtype=np.float32).reshape(-1, 2)
    desc = np.asarray(points[f"{_prefix(kind, point_map)}_desc"])
    desc = desc.astype(np.uint8) if kind == "orb" else desc.astype(np.float32)
    n = len(xy)
    z = np.zeros(n, np.float32)
    return PointFeatures(kind, xy, z, z.copy(), z.copy(), np.zeros(n, np.int64), np.ascontiguousarray(desc))


POINT_MAPS = ("reference", "all")


def _prefix(kind: str, point_map: str) -> str:
    if point_map not in POINT_MAPS:
        raise ValueError(f"point map must be one of {POINT_MAPS}, got {point_map!r}")
    return kind if point_map == "reference" else f"{kind}_all"


def point_keyframes(points: dict, kind: str, point_map: str = "reference"):
    """Which keyframe each stored point belongs to, and the keyframes' vehicle poses in the place frame.

    Returns ``(keyframe (N,) int, T_place_keyframe (K,4,4))``; the reference map has one keyframe,
    the identity (it defines the place frame).
    """
    pre = _prefix(kind, point_map)
    n = len(np.asarray(points.get(f"{pre}_kp", np.zeros((0, 2)))).reshape(-1, 2))
    if point_map == "reference":
        return np.zeros(n, int), np.eye(4)[None]
    return (np.asarray(points[f"{pre}_keyframe"], dtype=int).reshape(-1),
            np.asarray(points["all_T_place_keyframe"], dtype=float).reshape(-1, 4, 4))


def point_map_covariances(points: dict, kind: str, point_map: str, T_vehicle_camera) -> np.ndarray | None:
    """(N,3,3) place-frame covariances of a point map's points (None when it stores no uncertainty).

    Each point's stored ``(σ_across, σ_along)`` is relative to the ray from *its* keyframe's camera.
    """
    pre = _prefix(kind, point_map)
    if f"{pre}_sigma" not in points:
        return None
    xyz = np.asarray(points[f"{pre}_xyz"], dtype=float).reshape(-1, 3)
    sig = np.asarray(points[f"{pre}_sigma"], dtype=float).reshape(-1, 2)
    kf, T_pk = point_keyframes(points, kind, point_map)
    cov = np.zeros((len(xyz), 3, 3))
    T_vc = np.asarray(T_vehicle_camera, dtype=float)
    for k in np.unique(kf):
        sel = kf == k
        cov[sel] = point_covariances(xyz[sel], sig[sel], T_pk[k] @ T_vc)
    return cov


def _compact_descriptors(desc: np.ndarray, kind: str) -> np.ndarray:
    """uint8 (ORB always; SIFT when lossless), float16 for XFeat (unit vectors: cosine similarities
    change by < 1e-3), else float16 when lossless, else float32."""
    if kind == "orb" or desc.dtype == np.uint8:
        return np.ascontiguousarray(desc, dtype=np.uint8)
    if kind == "xfeat":
        return np.ascontiguousarray(desc, dtype=np.float16)
    d = np.asarray(desc, dtype=np.float32)
    if d.size == 0 or (np.all(d == np.round(d)) and d.min() >= 0 and d.max() <= 255):
        return d.astype(np.uint8)
    d16 = d.astype(np.float16)
    if np.array_equal(d16.astype(np.float32), d):
        return d16
    return d


def _spread(xy: np.ndarray, order: np.ndarray, n: int, grid, size) -> np.ndarray:
    """Up to ``n`` indices from ``order`` (best first), taken round robin over grid cells."""
    if len(order) <= n:
        return np.sort(order)
    gx, gy = int(grid[0]), int(grid[1])
    w, h = size
    cx = np.clip((xy[order, 0] / w * gx).astype(int), 0, gx - 1)
    cy = np.clip((xy[order, 1] / h * gy).astype(int), 0, gy - 1)
    cell = cy * gx + cx
    # rank of each point within its cell (order is best first, so rank 0 is the cell's best)
    rank = np.zeros(len(order), int)
    counts: dict[int, int] = {}
    for i, c in enumerate(cell):
        rank[i] = counts.get(c, 0)
        counts[c] = rank[i] + 1
    pick = np.lexsort((np.arange(len(order)), rank))[:n]
    return np.sort(order[pick])


def select_frames(T_frame_window: np.ndarray, key_row: int, baselines_m, tolerance_m: float) -> list[int]:
    """Rows of the window nearest each signed baseline (forward positive), excluding the keyframe."""
    t = np.asarray(T_frame_window, dtype=float)[:, :3, 3]
    signed = np.sign(t[:, 0]) * np.linalg.norm(t, axis=1)
    rows = []
    for b in baselines_m:
        cost = np.abs(signed - b)
        cost[key_row] = np.inf
        j = int(np.argmin(cost))
        if cost[j] <= tolerance_m and j not in rows:
            rows.append(j)
    return rows


def triangulate_keyframe(key_image: np.ndarray, images: list, T_key_frames: np.ndarray, camera: Camera,
                         T_vehicle_camera: np.ndarray, config: dict | None = None):
    """Point map of one keyframe from images with known vehicle poses.

    Parameters
    ----------
    key_image : gray or BGR uint8 image of the keyframe.
    images : list of images of the other frames.
    T_key_frames : (F, 4, 4) vehicle poses of those frames in the keyframe's vehicle frame (the place
        frame), e.g. from odometry.
    camera, T_vehicle_camera : the camera and its extrinsic.
    config : overrides of :data:`default_config`.

    Returns
    -------
    points : dict of str -> ndarray (see the module docstring).
    stats : dict of kind -> :class:`TriangulationStats`.
    """
    cfg = _merge(config)
    T_key_frames = np.asarray(T_key_frames, dtype=float).reshape(-1, 4, 4)
    if len(images) != len(T_key_frames):
        raise ValueError(f"{len(images)} images but {len(T_key_frames)} poses")
    T_vc = np.asarray(T_vehicle_camera, dtype=float)
    T_window_place = np.concatenate([np.eye(4)[None], invert(T_key_frames)])   # T_{j,p}
    T_cam_place = camera_poses(T_window_place, T_vc)
    cam0 = ideal_camera(camera)
    points, stats = {}, {}
    for kind in cfg["kinds"]:
        n_cand = cfg["xfeat_candidates"] if kind == "xfeat" else cfg["n_candidates"]
        kf = extract(key_image, kind, n_features=n_cand, config=cfg["features"])
        others = [extract(img, kind, n_features=n_cand, config=cfg["features"]) for img in images]
        N, F = len(kf), len(images) + 1
        uv = np.full((N, F, 2), np.nan)
        sig = np.full((N, F), np.nan)
        uv[:, 0] = kf.xy
        sig[:, 0] = keypoint_sigma(kf, cfg["pixel_sigma"], cfg["features"])
        x0 = ideal_pixels(camera, kf.xy.astype(float))
        x0n = np.column_stack([(x0[:, 0] - cam0.cx) / cam0.fx, (x0[:, 1] - cam0.cy) / cam0.fy])
        for j, of in enumerate(others, start=1):
            m = (match(kf, of, filter="cossim", mutual=True, min_cossim=cfg["xfeat_min_cossim"]) if kind == "xfeat"
                 else match(kf, of, filter="ratio", ratio=cfg["ratio"], mutual=True))
            if not len(m):
                continue
            x1 = ideal_pixels(camera, of.xy[m.train].astype(float))
            x1n = np.column_stack([(x1[:, 0] - cam0.cx) / cam0.fx, (x1[:, 1] - cam0.cy) / cam0.fy])
            T_cj_c0 = T_cam_place[j] @ invert(T_cam_place[0])
            d = _sampson_px(x0n[m.query], x1n, T_cj_c0, 0.5 * (cam0.fx + cam0.fy))
            ok = d <= cfg["epipolar_px"]
            uv[m.query[ok], j] = of.xy[m.train[ok]]
            sig[m.query[ok], j] = keypoint_sigma(of.subset(m.train[ok]), cfg["pixel_sigma"], cfg["features"])
        xyz, keep, cov, reason = triangulate_tracks(uv, T_cam_place, camera, cfg, sigma=sig)
        st = TriangulationStats(candidates=int(N), tracked=int((np.isfinite(uv[:, 1:, 0]).any(axis=1)).sum()),
                                frames=int(F - 1))
        for r in ("behind", "depth", "reprojection", "parallax"):
            st[r] = int((reason == r).sum())
        idx = np.flatnonzero(keep)
        # best first: more views, then the detector's response
        views = np.isfinite(uv[idx, :, 0]).sum(axis=1)
        order = idx[np.lexsort((-kf.response[idx], -views))]
        sel = _spread(kf.xy, order, int(cfg["max_points"]), cfg["grid"], (camera.width, camera.height))
        st["triangulated"] = int(len(idx))
        st["kept"] = int(len(sel))
        stats[kind] = st
        points[f"{kind}_kp"] = kf.xy[sel].astype(np.float32)
        points[f"{kind}_desc"] = _compact_descriptors(kf.descriptors[sel], kind)
        points[f"{kind}_xyz"] = xyz[sel].astype(np.float32)
        points[f"{kind}_sigma"] = _compress_sigma(xyz[sel], cov[sel], T_vc) if len(sel) else np.zeros((0, 2), np.float16)
    return points, stats


def build_point_features(view, camera: Camera, T_vehicle_camera: np.ndarray, config: dict | None = None,
                         return_stats: bool = False):
    """Point-feature map of a place from the reference run's view of it.

    Parameters
    ----------
    view : :class:`scenesig.mapping.places.TrainingView`
        The reference run's view of the place: ``frame`` is the keyframe (it defines the place frame),
        ``window`` its frames within ±10 m and ``T_frame_window`` their odometry poses in the keyframe's
        vehicle frame.
    camera, T_vehicle_camera : the reference run's camera and extrinsic.
    config : overrides of :data:`default_config`.
    return_stats : also return per-kind :class:`TriangulationStats`.

    Returns
    -------
    dict of str -> ndarray
        ``{kind}_kp``, ``{kind}_desc``, ``{kind}_xyz``, ``{kind}_sigma`` for each kind (ORB and SIFT by
        default), ready for ``PlaceData(points=...)``.  With ``return_stats``: ``(points, stats)``.
    """
    cfg = _merge(config)
    window = np.asarray(view.window)
    hits = np.flatnonzero(window == view.frame)
    if not len(hits):
        raise ValueError(f"run {view.run.name!r}: keyframe {view.frame} is not in its own window")
    rows = select_frames(view.T_frame_window, int(hits[0]), cfg["baselines_m"], cfg["baseline_tolerance_m"])
    key = view.run.image(int(view.frame), gray=True)
    images = [view.run.image(int(window[r]), gray=True) for r in rows]
    T = np.asarray(view.T_frame_window, dtype=float)[rows].reshape(-1, 4, 4)
    points, stats = triangulate_keyframe(key, images, T, camera, T_vehicle_camera, cfg)
    return (points, stats) if return_stats else points


def build_point_features_all(views, T_place_views, config: dict | None = None, reference_points=None) -> dict:
    """Point map of a place from every training run: one keyframe per run, all in the place frame.

    What a user with several surveys builds (hloc-style: many database images per place, the live
    image matched to the one it matches best).  Each run's keyframe is triangulated from that run's
    own window (:func:`build_point_features`) and moved into the place frame with the run's pose
    relative to the place, which the map builder has already solved (``T_place_views``: the
    georeferencing's visual solve of each training image, :func:`scenesig.mapping.georef.observe_place`;
    None where it failed -- that run's keyframe is left out, as an image that does not register is
    left out of an SfM model).

    Parameters
    ----------
    views : list of :class:`scenesig.mapping.places.TrainingView`, the reference run's first.
    T_place_views : list of (4,4) or None, the vehicle pose of each view's frame in the place frame.
    config : overrides of :data:`default_config`.
    reference_points : the reference view's :func:`build_point_features` output, if already built.

    Returns
    -------
    dict of str -> ndarray
        ``{kind}_all_kp``, ``_desc``, ``_xyz`` (place frame), ``_sigma`` (w.r.t. each point's own
        keyframe ray), ``_keyframe`` (int16 index into the keyframes) for each kind, and
        ``all_T_place_keyframe`` (K,4,4) float32.
    """
    cfg = _merge(config)
    if len(views) != len(T_place_views):
        raise ValueError(f"{len(views)} views but {len(T_place_views)} poses")
    parts, poses = [], []
    for k, (view, T) in enumerate(zip(views, T_place_views)):
        if T is None:
            continue
        pts = reference_points if (k == 0 and reference_points is not None) else \
            build_point_features(view, view.run.camera, view.run.T_vehicle_camera, cfg)
        parts.append(pts)
        poses.append(np.asarray(T, dtype=float))
    return combine_keyframe_maps(parts, poses, cfg["kinds"])


def combine_keyframe_maps(parts: list, T_place_keyframes: list, kinds=None) -> dict:
    """One ``all`` point map from keyframe point maps (each in its own keyframe's vehicle frame).

    ``parts[j]`` is a :func:`build_point_features` output and ``T_place_keyframes[j]`` (4,4) that
    keyframe's vehicle pose in the place frame; see :func:`build_point_features_all` for the keys.
    ``kinds``: default, those the first part holds.
    """
    poses = [np.asarray(T, dtype=float) for T in T_place_keyframes]
    if kinds is None:                 # the kinds the keyframe maps hold
        kinds = [k for k in KINDS if parts and f"{k}_kp" in parts[0]]
    out = {"all_T_place_keyframe": np.asarray(poses, np.float32).reshape(-1, 4, 4)}
    for kind in kinds:
        for name in ("kp", "desc", "xyz", "sigma", "keyframe"):
            arrays = []
            for j, (pts, T) in enumerate(zip(parts, poses)):
                if name == "keyframe":
                    arrays.append(np.full(len(pts[f"{kind}_kp"]), j, np.int16))
                elif name == "xyz":
                    xyz = pts[f"{kind}_xyz"].astype(float).reshape(-1, 3)
                    arrays.append((xyz @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
                else:
                    arrays.append(pts[f"{kind}_{name}"])
            if name == "desc":
                dt = np.result_type(*[a.dtype for a in arrays]) if arrays else np.uint8
                arrays = [a.astype(dt) for a in arrays]
            empty = {"kp": (0, 2), "xyz": (0, 3), "sigma": (0, 2), "keyframe": (0,),
                     "desc": (0, {"orb": 32, "xfeat": 64}.get(kind, 128))}[name]
            out[f"{kind}_all_{name}"] = np.concatenate(arrays) if arrays else np.zeros(empty, np.float32)
    return out


def add_to_map(map_root, reference, config: dict | None = None, overwrite: bool = False,
               progress: bool = True) -> dict:
    """Add point features to every place of a finished map that has none (the "lazy" map side).

    Parameters
    ----------
    map_root : the map folder.
    reference : :class:`scenesig.surveys.run.SurveyRun`, the map's reference run (its images and odometry).
    config : overrides of :data:`default_config`.
    overwrite : recompute places that already have point features.

    Returns
    -------
    dict
        ``places`` updated, ``seconds``, ``bytes_per_place_mean`` after the update, per-kind ``kept_mean``.
    """
    from tqdm import tqdm

    from scenesig.mapping.places import Place, training_views
    from scenesig.mapping.store import MapStore, MapWriter, PlaceData

    t0 = time.perf_counter()
    store = MapStore.open(map_root, cache_size=0)
    want = store.params.get("reference")
    if want is not None and want != reference.name:
        raise ValueError(f"map {store.root} was built with reference run {want!r}, not {reference.name!r}")
    places_cfg = (store.params.get("config") or {}).get("places") or {}
    writer = MapWriter(store.root, store.camera, store.T_vehicle_camera, store.params)
    kept = {}
    updated = 0
    for idx in tqdm(sorted(store.places), desc="point features", unit="place", disable=not progress):
        meta = store.places[idx]
        data = store.load_place(idx)
        kinds = _merge(config)["kinds"]
        if not overwrite and all(f"{k}_kp" in (data.points or {}) for k in kinds):
            continue
        place = Place(idx, meta.T_world_place, 0.0, int(data.meta.get("reference_frame", -1)), list(meta.neighbours))
        views = training_views(place, [reference], places_cfg)
        if not views:
            raise ValueError(f"reference run {reference.name!r} does not pass place {idx} of {store.root}")
        view = views[0]
        if place.reference_frame >= 0 and view.frame != place.reference_frame:
            # the keyframe must be the frame that defines the place frame
            win = np.asarray(view.window)
            if place.reference_frame not in win:
                raise ValueError(f"place {idx}: reference frame {place.reference_frame} outside its window")
            from scenesig.surveys.geometry import interpolate_poses
            odo = interpolate_poses(reference.odometry_times, reference.odometry_poses, reference.frame_times[win])
            T_ref = interpolate_poses(reference.odometry_times, reference.odometry_poses,
                                      reference.frame_times[place.reference_frame])
            view = type(view)(reference, place.reference_frame, win, invert(T_ref) @ odo, view.position_error_m)
        points, stats = build_point_features(view, reference.camera, reference.T_vehicle_camera, config,
                                             return_stats=True)
        for k, st in stats.items():
            kept.setdefault(k, []).append(st["kept"])
        # the place's other layers stay; the kinds built here are added (or replaced)
        points = {**{k: np.asarray(v) for k, v in (data.points or {}).items()}, **points}
        writer.write_place(idx, PlaceData(dict(data.bank_arrays), np.array(data.landmarks), np.array(data.covariances),
                                          np.array(data.classifier_ids), data.keyframe, dict(data.meta), points))
        updated += 1
    writer.finalise([{"index": m.index, "T_world_place": m.T_world_place, "neighbours": list(m.neighbours),
                      "extra": m.extra} for m in store.places.values()])
    sizes = [(store.root / m.file).stat().st_size for m in store.places.values()]
    return {"places": updated, "seconds": time.perf_counter() - t0, "bytes_per_place_mean": float(np.mean(sizes)),
            **{f"{k}_kept_mean": float(np.mean(v)) for k, v in kept.items()}}
