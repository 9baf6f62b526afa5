"""Lifelong maps: add a live run's appearance to the places where its localisation was weak.

McManus et al. 2015 (§5) train the map once and name experience-based maps as the way forward; this
module lets the map learn conditions it has not seen from the runs it localised, without re-surveying
and without ground truth:

1. *weak places* -- per place, the frames the localiser assigned to it (``frames.csv``): a place is
   weak when it got no detection, no accepted localisation ("lost"), or fewer than
   ``min_inliers_per_detection`` solver inliers per detection (pooled over its frames);
2. *the live frame* -- the run's frame nearest the place (position, and heading within
   ``max_heading_error_deg``) by the localiser's **own estimated trajectory** (``trajectory.tum``;
   never ``truth.tum`` or the INS).  Its pose relative to the place, ``T_place_vehicle``, is the
   estimate at the run's nearest accepted localisation carried to the frame by the run's odometry, so
   a frame is used only within ``max_blind_m`` of odometry of one (an oracle reset does not count);
3. *re-mining* -- :func:`scenesig.mapping.build.mine_and_refine` on the live frame first, then the place's
   build-time training images and its earlier experiences, with the build's negatives and seed; the
   survivors go through the temporal check and the depth refinement over the live run's ±10 m window
   from its odometry (§3.2.1) and are carried into the place frame by ``T_place_vehicle``, corrected
   first by aligning them to their firings in the reference run's frames around the place
   (:func:`align_to_reference`), with that pose's uncertainty added to their covariances.  The
   place's existing classifiers are kept with their landmarks (refined depths) untouched; the new
   ones are appended.  Other places' files are not touched.
4. *experiences* -- per place (manifest ``extra["experiences"]``): run, conditions, frame, the map
   generation that added it, the reason, signatures added; the map's ``generation`` and ``history``.

Safety on disk.  A rewritten place goes to a new file per generation
(:func:`scenesig.mapping.store.place_file_name`), written atomically and journalled (``update.jsonl``); the
manifest, replaced atomically last, is the commit point: a reader or a crash sees the old generation or
the complete new one.  Files of the previous generation stay (a reader that opened the old manifest
still finds them; :meth:`scenesig.mapping.store.MapStore.load_place` also follows a newer manifest), older
ones are removed.  Re-running an interrupted update with the same inputs resumes from the journal and
gives the same bytes (everything is seeded; nothing depends on the wall clock); re-running a completed
one changes nothing.

The command line is ``scenesig map update MAP LOCALISATION_DIR... [--out NEWMAP] [--runs-dir DIR]``.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from scenesig.mapping import places as places_mod
from scenesig.mapping.build import _merge as build_settings, mine_and_refine, place_negatives, place_views
from scenesig.mapping.codec import PlaceData, encode_place
from scenesig.mapping.identity import map_id_of
from scenesig.mapping.store import (
    JOURNAL as BUILD_JOURNAL,
    MANIFEST,
    PLACES_DIR,
    MapStore,
    place_file_name,
    write_manifest,
)
from scenesig.signatures.bank import Bank
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import invert, yaw_of
from scenesig.surveys.io import atomic_write_bytes, atomic_write_text, fsync_dir
from scenesig.surveys.localisation import Localisation
from scenesig.surveys.run import SurveyRun, read_run
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "read_localisation", "find_run", "weakly_localised_places", "check_localisations", "update_map"]

JOURNAL = "update.jsonl"
SUMMARY = "update_summary.json"

default_config = {
    # a place is weak below this many solver inliers per detection (pooled over its frames); chosen on
    # training runs localised against their own map (tiny test world, overcast and night): places
    # with accepted localisations had 0.53 and 0.74, places where the localiser was lost 0
    "min_inliers_per_detection": 0.5,
    # the live frame's pose is carried from an accepted localisation by at most this much odometry (m):
    # the localiser's own failure distance (McManus et al. 2015, §4.3): it trusts its odometry that far
    "max_blind_m": 20.0,
    "max_position_error_m": 8.0,      # the nearest estimated frame must be this close to the place
    "max_heading_error_deg": 30.0,    # ... and face the same way
    # The live frame's estimated pose is then corrected by aligning the new landmarks to where their
    # classifiers fire in the reference run's frames around the place: the place frame *is* the
    # reference frame's vehicle frame (McManus et al. 2015, §3.1), so those frames' poses are exact
    # (odometry over a few metres). A planar correction (x, y, yaw) is fitted with a robust loss; it
    # is used when enough firings agree with it, else the estimate is kept as it was.
    "align_to_reference": True,
    "align_probability": 0.5,          # a firing: lambda at least the localiser's min_probability
    "align_frames_m": [0.0, -2.0, 2.0, -4.0, 4.0],   # reference frames used, by odometry distance
    "align_window_px": 80.0,           # search around each landmark's predicted pixel
    "align_inlier_px": 8.0,            # residual of an agreeing firing after the fit
    "align_min_inliers": 8,            # firings (of at least align_min_classifiers classifiers)
    "align_min_classifiers": 4,
    # Uncertainty of the live frame's pose, added to the new landmarks' covariances so the solver weighs
    # them below the survey's landmarks (McManus et al. 2015, eq. 5 carries a landmark's covariance into
    # its detection's): horizontal position sigma0 + drift * odometry distance to the anchoring
    # localisation, and yaw. Chosen on the update's input run A of the demo world (its accepted
    # localisations against the day base map: median 0.28 m lateral and 0.44 deg yaw from the truth),
    # never on the runs the update is evaluated with.
    "live_pose_sigma_m": 0.25,
    "live_pose_drift": 0.01,
    "live_pose_sigma_deg": 0.5,
}


def read_localisation(folder, search=()) -> Localisation:
    """A ``scenesig localise`` output folder read back for an update (:meth:`Localisation.from_folder`) with its
    live run (``run``): found by ``metrics.json``'s ``run_path``, else by its name beside it or in the
    folders ``search``.  DataError naming the file if something is missing or inconsistent, or if the
    localisation is not a scene-signature one (only that tells where the map's signatures were weak)."""
    folder = Path(folder)
    mpath = folder / "metrics.json"
    loc = Localisation.from_folder(folder)
    metrics = loc.metrics or {}
    if loc.method != "signatures":
        raise DataError(mpath, f"method is {loc.method!r}: only a scene-signature localisation tells "
                               f"where the map's signatures were weak")
    tpath = folder / "trajectory.tum"
    # the run: where the localisation read it, else by name beside it or in ``search``
    hint = Path(metrics["run_path"]) if metrics.get("run_path") else None
    search = ([hint.parent] if hint is not None else []) + [Path(d) for d in search]
    run = read_run(find_run(metrics["run"], [hint], search))
    if run.name != metrics["run"]:
        raise DataError(mpath, f"names run {metrics['run']!r} but {run.root} holds run {run.name!r}")
    n = len(run.frame_times)
    if len(loc.times) != n:
        raise DataError(tpath, f"{len(loc.times)} poses for run {run.name!r} of {n} frames: not this run's "
                               f"localisation")
    if not np.allclose(loc.times, run.frame_times, atol=1e-5):
        raise DataError(tpath, f"timestamps are not those of run {run.name!r}'s frames")
    loc.run = run
    return loc


def find_run(name: str, hints: list[Path | None], search: list[Path]) -> Path:
    """The folder of the run called ``name``: a hint if it is that run, else a sub-folder of ``search``."""
    for h in hints:
        if h is not None and (h / "run.toml").is_file() and read_run(h, check_images=False).name == name:
            return h
    for d in search:
        for sub in sorted(Path(d).iterdir()) if Path(d).is_dir() else []:
            if (sub / "run.toml").is_file() and not sub.name.endswith(".tmp"):
                if sub.name == name or read_run(sub, check_images=False).name == name:
                    return sub
    raise DataError(search[0] if search else Path(name),
                    f"run {name!r} not found (searched {[str(d) for d in search]}); pass its parent folder with "
                    f"--runs-dir")


def _anchors(loc: Localisation) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: the nearest accepted localisation by odometry distance (before or after; -1 if the
    run was never localised) and that distance (m; inf if none).  Oracle resets do not count: after one
    the estimate is the INS, not the map."""
    run = loc.run
    odo = run.pose_at(run.frame_times, "odometry").reshape(-1, 4, 4)
    s = places_mod.arc_length(odo[:, :3, 3])
    ok = np.nonzero(loc.frames["localised"] > 0)[0]
    if not len(ok):
        return np.full(len(s), -1), np.full(len(s), np.inf)
    # arc length never decreases: the nearest localisation is one of the two around each frame
    right = np.searchsorted(s[ok], s).clip(0, len(ok) - 1)
    left = (right - 1).clip(0, len(ok) - 1)
    d_left, d_right = np.abs(s - s[ok][left]), np.abs(s[ok][right] - s)
    j = np.where(d_left <= d_right, left, right)
    return ok[j], np.minimum(d_left, d_right)


def _live_pose(loc: Localisation, frame: int, anchor: int) -> np.ndarray:
    """``T_world_vehicle`` of ``frame``: the localiser's estimate at its nearest accepted localisation,
    carried to the frame by the run's odometry (the online estimate at a weak place is odometry from
    the last fix anyway; from the nearest fix, before or after, it drifts least)."""
    run = loc.run
    odo = run.pose_at(run.frame_times[[anchor, frame]], "odometry").reshape(-1, 4, 4)
    return loc.poses[anchor] @ invert(odo[0]) @ odo[1]


def weakly_localised_places(store: MapStore, loc: Localisation, config: dict | None = None) -> dict:
    """Per place of the map: is the localisation weak there, why, and the live frame to add.

    Returns ``{index: record}`` with ``weak`` (bool), ``reason`` (``no_detection``, ``lost``,
    ``few_inliers`` or ``ok``), ``detections``, ``inliers``, ``localised`` (sums over the frames the
    localiser assigned to the place), ``inliers_per_detection``; for weak places ``frame`` (the live
    frame to add, or None) and ``skip`` (why not, or None).
    """
    cfg = merge_settings(default_config, config, "update")
    fr = loc.frames
    anchor, blind = _anchors(loc)
    xy = loc.poses[:, :2, 3]
    yaw = yaw_of(loc.poses)
    out = {}
    for i, meta in sorted(store.places.items()):
        seg = fr["place"] == i
        det, inl, ok = (int(fr[c][seg].sum()) for c in ("detections", "inliers", "localised"))
        ipd = inl / det if det else None
        if det == 0:
            reason = "no_detection"
        elif ok == 0:
            reason = "lost"
        elif ipd < cfg["min_inliers_per_detection"]:
            reason = "few_inliers"
        else:
            reason = "ok"
        rec = {"weak": reason != "ok", "reason": reason, "detections": det, "inliers": inl, "localised": ok,
               "inliers_per_detection": ipd, "frame": None, "skip": None}
        if rec["weak"]:
            d = np.linalg.norm(xy - meta.T_world_place[:2, 3], axis=1)
            dyaw = np.abs(np.angle(np.exp(1j * (yaw - meta.yaw))))
            d = np.where(dyaw <= np.radians(cfg["max_heading_error_deg"]), d, np.inf)
            f = int(np.argmin(d))
            if not d[f] <= cfg["max_position_error_m"]:
                rec["skip"] = f"the estimated trajectory never comes within {cfg['max_position_error_m']} m of it"
            elif not blind[f] <= cfg["max_blind_m"]:
                rec["skip"] = ("the run was never localised against the map, so its estimated trajectory "
                               "places nothing relative to a place" if not np.isfinite(blind[f]) else
                               f"its nearest localisation is {blind[f]:.1f} m of odometry away (> "
                               f"{cfg['max_blind_m']} m)")
            else:
                rec["frame"] = f
                rec["anchor_frame"] = int(anchor[f])
                rec["blind_m"] = float(blind[f])
                rec["position_error_m"] = float(d[f])
        out[i] = rec
    return out


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class _Runs:
    """Survey runs by name, read once (the map's training runs and earlier experiences' runs)."""

    def __init__(self, search: list[Path]):
        self.search = [Path(p) for p in search]
        self._runs: dict[str, SurveyRun] = {}

    def add(self, run: SurveyRun):
        self._runs.setdefault(run.name, run)

    def __getitem__(self, name: str) -> SurveyRun:
        if name not in self._runs:
            self._runs[name] = read_run(find_run(name, [], self.search))
        return self._runs[name]


def _copy_map(src: Path, dst: Path) -> None:
    """Copy a finished map's current generation (manifest last) to ``dst``; files already there with the
    right checksum are kept, so an interrupted copy resumes."""
    store = MapStore.open(src)
    doc = json.loads((src / MANIFEST).read_text(encoding="utf-8"))
    if (dst / MANIFEST).is_file():
        have = json.loads((dst / MANIFEST).read_text(encoding="utf-8"))
        if not isinstance(have, dict) or map_id_of(have) != store.map_id:
            other = map_id_of(have) if isinstance(have, dict) else "?"
            raise DataError(dst / MANIFEST, f"--out names an existing, different map (map_id {other}; the map "
                                            f"being updated is {store.map_id}); choose a new folder")
        if have.get("history", [])[:len(doc.get("history", []))] == doc.get("history", []) and \
                have.get("params") == doc.get("params"):
            return  # a copy (maybe already updated by these runs) is there: the update resumes or stops
        raise DataError(dst / MANIFEST, "--out names an existing, different map; choose a new folder")
    (dst / PLACES_DIR).mkdir(parents=True, exist_ok=True)
    for meta in store.places.values():
        target = dst / meta.file
        if not (target.is_file() and hashlib.sha256(target.read_bytes()).hexdigest() == meta.sha256):
            atomic_write_bytes(target, store.place_bytes(meta.index))
    for name in ("build_summary.json",):
        if (src / name).is_file():
            shutil.copyfile(src / name, dst / name)
    write_manifest(dst, doc)


def _collect_garbage(root: Path, keep: set[str]) -> None:
    for f in (root / PLACES_DIR).glob("place_*.npz"):
        if f"{PLACES_DIR}/{f.name}" not in keep:
            f.unlink(missing_ok=True)
    for f in (root / PLACES_DIR).glob(".*.tmp"):
        f.unlink(missing_ok=True)
    fsync_dir(root / PLACES_DIR)


def _read_journal(path: Path, inputs: str) -> dict:
    """Place records of an interrupted update of the same inputs (else nothing)."""
    if not path.is_file():
        return {}
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    try:
        head = json.loads(lines[0])
    except (IndexError, json.JSONDecodeError):
        return {}
    if head.get("inputs") != inputs:
        return {}
    done = {}
    for line in lines[1:]:
        try:
            r = json.loads(line)
        except json.JSONDecodeError:  # torn last line of a killed update: that place is redone
            break
        done[int(r["index"])] = r
    return done


def _append(path: Path, obj) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(obj, sort_keys=True) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def _live_pose_covariance(points: np.ndarray, T_place_vehicle: np.ndarray, blind_m: float, ucfg: dict) -> np.ndarray:
    """(n,3,3) place-frame covariance of points fixed in the live vehicle frame from the uncertainty of
    ``T_place_vehicle``: an isotropic horizontal position sigma and a yaw sigma (lever arm to the point)."""
    s = float(ucfg["live_pose_sigma_m"]) + float(ucfg["live_pose_drift"]) * float(blind_m)
    arm = points[:, :2] - T_place_vehicle[:2, 3]
    v = np.stack([-arm[:, 1], arm[:, 0], np.zeros(len(points))], axis=1) * np.radians(ucfg["live_pose_sigma_deg"])
    return np.diag([s * s, s * s, 0.25 * s * s])[None] + v[:, :, None] * v[:, None, :]


def _planar(params, centre) -> np.ndarray:
    """SE(3) of a planar correction (dx, dy, dyaw) rotating about ``centre`` (x, y)."""
    dx, dy, a = params
    c, s = np.cos(a), np.sin(a)
    M = np.eye(4)
    M[:2, :2] = [[c, -s], [s, c]]
    M[:2, 3] = np.asarray(centre[:2]) - M[:2, :2] @ np.asarray(centre[:2]) + [dx, dy]
    return M


def align_to_reference(bank: Bank, landmarks_vehicle: np.ndarray, T_place_vehicle: np.ndarray, ref_view,
                       config: dict | None = None) -> tuple[np.ndarray, dict]:
    """Correct the live frame's estimated pose with the reference run's frames around the place.

    ``landmarks_vehicle`` (n,3) are the new landmarks in the live frame's vehicle frame; ``ref_view`` the
    reference run's :class:`scenesig.mapping.places.TrainingView` of the place, whose training frame is the
    place frame.  Each new classifier is searched within ``align_window_px`` of its landmark's predicted
    pixel in the reference frames ``align_frames_m`` away; a planar correction is fitted to the firings
    (robust, soft-L1) and refitted on those that agree within ``align_inlier_px``.

    Returns
    -------
    T_place_vehicle : the corrected pose, or the given one when too few firings agree.
    info : ``firings``, ``inliers``, ``classifiers``, ``used`` and the correction (``dx``, ``dy`` m, ``dyaw_deg``).
    """
    from scipy.optimize import least_squares

    cfg = merge_settings(default_config, config, "update")
    run = ref_view.run
    camera, T_vc = run.camera, run.T_vehicle_camera
    s = places_mod.arc_length(ref_view.T_frame_window[:, :3, 3])
    s = s - s[int(np.searchsorted(ref_view.window, ref_view.frame))]
    rows = sorted({int(np.argmin(np.abs(s - d))) for d in cfg["align_frames_m"]})
    P = landmarks_vehicle @ T_place_vehicle[:3, :3].T + T_place_vehicle[:3, 3]
    r = float(cfg["align_window_px"])
    obs = []   # (row, classifier, u, v)
    for row in rows:
        T_cam_place = invert(ref_view.T_frame_window[row] @ T_vc)
        uv, _ = camera.project(P @ T_cam_place[:3, :3].T + T_cam_place[:3, 3])
        if not np.isfinite(uv).any():
            continue
        d = bank.detect(run.image(int(ref_view.window[row]), gray=True),
                        windows=np.concatenate([uv - r, uv + r], axis=1), top_n=1)
        ok = np.isfinite(uv[:, 0]) & np.isfinite(d.x[:, 0]) & \
            (np.nan_to_num(d.prob[:, 0], nan=0.0) >= float(cfg["align_probability"]))
        obs += [(row, c, float(d.x[c, 0]), float(d.y[c, 0])) for c in np.nonzero(ok)[0]]
    info = {"firings": len(obs), "inliers": 0, "classifiers": 0, "used": False, "dx": 0.0, "dy": 0.0,
            "dyaw_deg": 0.0}
    if len(obs) < int(cfg["align_min_inliers"]):
        return T_place_vehicle, info
    o = np.asarray(obs)
    rr, cc, target = o[:, 0].astype(int), o[:, 1].astype(int), o[:, 2:]
    T_cam = np.stack([invert(ref_view.T_frame_window[k] @ T_vc) for k in rr])
    centre = T_place_vehicle[:2, 3]

    def residuals(x, sel):
        M = _planar(x, centre)
        Q = P[cc[sel]] @ M[:3, :3].T + M[:3, 3]
        Qc = np.einsum("nij,nj->ni", T_cam[sel, :3, :3], Q) + T_cam[sel, :3, 3]
        uv, _ = camera.project(Qc)
        return np.nan_to_num(uv - target[sel], nan=1e3).ravel()

    sel = np.ones(len(o), bool)
    x = np.zeros(3)
    for _ in range(2):   # robust fit, then a refit on the firings that agree with it
        x = least_squares(residuals, x, args=(sel,), loss="soft_l1", f_scale=float(cfg["align_inlier_px"]),
                          method="trf").x
        err = np.linalg.norm(residuals(x, np.ones(len(o), bool)).reshape(-1, 2), axis=1)
        sel = err <= float(cfg["align_inlier_px"])
        if sel.sum() < int(cfg["align_min_inliers"]):
            break
    n_cls = len(np.unique(cc[sel]))
    info.update(inliers=int(sel.sum()), classifiers=int(n_cls), dx=float(x[0]), dy=float(x[1]),
                dyaw_deg=float(np.degrees(x[2])))
    if sel.sum() < int(cfg["align_min_inliers"]) or n_cls < int(cfg["align_min_classifiers"]):
        return T_place_vehicle, info
    info["used"] = True
    return _planar(x, centre) @ T_place_vehicle, info


def _new_place(old: PlaceData, place, views, negatives, cfg, T_place_vehicle, ucfg: dict | None = None,
               blind_m: float = 0.0, ref_view=None) -> tuple[PlaceData, int, np.ndarray, dict | None]:
    """The old place plus the classifiers mined with ``views[0]`` (the live frame) first; also the
    live pose the new landmarks were placed with and the reference alignment's record."""
    from threadpoolctl import threadpool_limits

    ucfg = merge_settings(default_config, ucfg, "update")
    align = None
    with threadpool_limits(limits=1):  # the same bytes in any process (see mapping.build.build_place)
        mp = mine_and_refine(views, negatives, cfg, rng=place.index)
        if ucfg["align_to_reference"] and ref_view is not None and len(mp.bank):
            T_place_vehicle, align = align_to_reference(mp.bank, mp.landmarks, T_place_vehicle, ref_view, ucfg)
    k = len(mp.bank)
    R, t = T_place_vehicle[:3, :3], T_place_vehicle[:3, 3]
    new_points = mp.landmarks @ R.T + t
    old_bank = Bank.from_arrays(old.bank_arrays)
    bank = Bank(old_bank.classifiers + mp.bank.classifiers, old_bank.image_size or mp.bank.image_size,
                old_bank.meta)
    if not old_bank.classifiers:
        bank.hog = dict(mp.bank.hog)
    start = int(old.classifier_ids.max()) + 1 if len(old.classifier_ids) else 0
    meta = dict(old.meta)
    meta["detections_at_reference"] = list(meta.get("detections_at_reference", [])) + [[None, None]] * k
    meta["kept"] = int(len(bank))
    data = PlaceData(
        bank_arrays=bank.to_arrays(),
        landmarks=np.concatenate([old.landmarks.reshape(-1, 3), new_points]),
        covariances=np.concatenate([old.covariances.reshape(-1, 3, 3), R @ mp.covariances @ R.T
                                    + _live_pose_covariance(new_points, T_place_vehicle, blind_m, ucfg)]),
        classifier_ids=np.concatenate([old.classifier_ids, np.arange(start, start + k)]).astype(np.int64),
        keyframe=old.keyframe, points=dict(old.points), meta=meta)
    return data, k, T_place_vehicle, align


def check_localisations(store: MapStore, localisations, allow_older_generation: bool = False,
                        applied: bool = False) -> None:
    """Every localisation must have been made against this map (``map_id``, :mod:`scenesig.mapping.identity`) and
    its current generation; DataError naming the localisation's ``metrics.json`` and saying why not.

    A localisation of an older generation (the map was updated since) is refused unless
    ``allow_older_generation``: the places it found weak may have been updated already.  ``applied``:
    these localisations made the map's latest generation (re-running a finished update changes nothing).
    """
    for loc in localisations:
        mpath = Path(loc.folder) / "metrics.json"
        m = loc.metrics
        lid, lgen = m.get("map_id"), m.get("map_generation")
        if lid is None:
            # written before maps had identities: only by the folder it named, and only that generation
            named = Path(m["map"]).resolve() if m.get("map") else None
            if named != Path(store.root).resolve():
                raise DataError(mpath, f"records no map identity (written before maps had one) and was made against "
                                       f"{m.get('map')!r}, not {store.root}; localise the run against this map again")
        elif lid != store.map_id:
            raise DataError(mpath, f"was made against another map (map_id {lid}, {m.get('map')}), not {store.root} "
                                   f"(map_id {store.map_id}): an update adds a run's appearance to the map it was "
                                   f"localised against; localise the run against this map first")
        if lgen is None or applied:
            continue
        if int(lgen) > store.generation:
            raise DataError(mpath, f"was made against generation {lgen} of this map, but {store.root} is at "
                                   f"generation {store.generation}: a newer state than the one here")
        if int(lgen) < store.generation and not allow_older_generation:
            raise DataError(mpath, f"was made against generation {lgen} of this map, which is now at generation "
                                   f"{store.generation}: its weak places may have been updated since; localise the "
                                   f"run again, or pass --allow-older-generation to use it anyway")


def _check_out(out: Path) -> None:
    """``--out`` must be a folder we can write (new, or a copy of the map): DataError naming it otherwise."""
    if out.exists() and not out.is_dir():
        raise DataError(out, "--out exists and is not a folder: name a new folder for the updated map")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".scenesig-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise DataError(out, f"--out cannot be written: {exc.strerror or exc}") from None


def update_map(map_root, localisations, out=None, runs_dirs=(), config: dict | None = None,
               progress: bool = True, allow_older_generation: bool = False) -> dict:
    """Update a map with the weak places of one or more localisations (see the module docstring).

    Parameters
    ----------
    map_root : the map folder (updated in place unless ``out``).
    localisations : list of :class:`scenesig.surveys.localisation.Localisation` (``scenesig localise`` outputs
        read by :func:`read_localisation`; their runs must still exist).
    out : optional new map folder: the map is copied there first and updated there.
    runs_dirs : folders holding the map's training runs (default: the live runs' parent folders).
    config : overrides of :data:`default_config`.
    allow_older_generation : accept localisations made against an older generation of this map
        (:func:`check_localisations`; localisations of another map are always refused).

    Returns
    -------
    dict
        The update summary (also ``update_summary.json`` in the map when it changed): ``generation``, ``updated``
        places, per localisation and place the rule's verdict, ``seconds_per_updated_place``,
        ``bytes_added``, and ``message`` when nothing was added.
    """
    from tqdm import tqdm

    cfg = merge_settings(default_config, config, "update")
    root = Path(map_root)
    source = MapStore.open(root)  # a finished, valid map (DataError otherwise)
    locs = list(localisations)
    inputs = _digest({"localisations": [loc.digest() for loc in locs], "config": cfg})
    applied = bool(source.history) and source.history[-1].get("inputs") == inputs
    check_localisations(source, locs, allow_older_generation, applied)
    if out is not None:
        root = Path(out)
        _check_out(root)
        _copy_map(Path(map_root), root)
    if (root / BUILD_JOURNAL).exists():
        raise DataError(root / BUILD_JOURNAL, "a build of this map is unfinished; finish it before updating")
    store = MapStore.open(root, cache_size=0)
    doc = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
    hints = [loc.run.root.parent for loc in locs if loc.run.root is not None]
    runs = _Runs(list(runs_dirs) + list(dict.fromkeys(hints)))
    for loc in locs:
        runs.add(loc.run)
    gen = store.generation + 1
    t0 = time.perf_counter()
    verdicts = {str(loc.folder): weakly_localised_places(store, loc, cfg) for loc in locs}
    summary = {"map": str(root), "generation": store.generation, "updated": [], "verdicts": verdicts,
               "seconds_per_updated_place": None, "bytes_added": 0}
    if store.history and store.history[-1].get("inputs") == inputs:
        summary["message"] = f"already applied: generation {store.generation} holds these localisations"
        _collect_garbage(root, _files(doc) | _files_of_previous(root, doc))
        (root / JOURNAL).unlink(missing_ok=True)
        return summary

    # places to update and the live frames they get (in localisation order)
    todo: dict[int, list] = {}
    for loc in locs:
        for i, rec in verdicts[str(loc.folder)].items():
            if rec["weak"] and rec["frame"] is not None:
                todo.setdefault(i, []).append((loc, rec))
    if not todo:
        why = sorted({(r["reason"] if not r["weak"] else r["skip"]) for v in verdicts.values() for r in v.values()})
        summary["message"] = "nothing added: " + "; ".join(
            ("no place was weak" if w == "ok" else w) for w in why)
        (root / JOURNAL).unlink(missing_ok=True)
        return summary  # the map is not touched

    bcfg = build_settings(store.params["config"])
    reference = runs[store.params["reference"]]
    train = [runs[n] for n in store.params["runs"]]
    places = {p.index: p for p in places_mod.define_places(reference, bcfg["places"])}
    ref_frames = {i: p.reference_frame for i, p in places.items()}
    storage = doc.get("storage", {})
    done = _read_journal(root / JOURNAL, inputs)
    if not done:
        atomic_write_text(root / JOURNAL, json.dumps({"inputs": inputs, "generation": gen}, sort_keys=True) + "\n")
    entries = {int(p["index"]): p for p in doc["places"]}
    seconds = []
    bar = tqdm(total=len(todo), desc="map update places", unit="place", disable=not progress)
    for i in sorted(todo):
        rel = place_file_name(i, gen)
        r = done.get(i)
        if r is not None and (root / rel).is_file() and \
                hashlib.sha256((root / rel).read_bytes()).hexdigest() == r["sha256"]:
            bar.update(1)
            continue
        tp = time.perf_counter()
        data = store.load_place(i)
        experiences = list(entries[i].get("extra", {}).get("experiences", []))
        new_exp = []
        base = place_views(places[i], train, reference, bcfg)
        earlier = [places_mod.odometry_view(runs[e["run"]], e["frame"], bcfg["places"]) for e in experiences]
        negs = place_negatives(places[i], ref_frames, reference, bcfg)
        for loc, rec in todo[i]:
            live = places_mod.odometry_view(loc.run, rec["frame"], bcfg["places"], rec["position_error_m"])
            T_pv = invert(store.places[i].T_world_place) @ _live_pose(loc, rec["frame"], rec["anchor_frame"])
            ref_view = base[0] if base and base[0].run.name == reference.name else None
            data, k, T_pv, align = _new_place(data, places[i], [live] + base + earlier, negs, bcfg, T_pv, cfg,
                                              rec["blind_m"], ref_view)
            earlier.append(live)
            new_exp.append({"run": loc.run.name, "conditions": list(loc.run.conditions), "frame": int(rec["frame"]),
                            "run_start_time": float(loc.run.frame_times[0]), "generation": gen,
                            "reason": rec["reason"], "inliers_per_detection": rec["inliers_per_detection"],
                            "signatures_added": int(k), "alignment": align,
                            "T_place_vehicle": [[float(x) for x in row] for row in T_pv]})
        raw = encode_place(i, data, float(storage.get("float16_tol", 4e-3)),
                           float16_min_size=int(storage.get("float16_min_size", 4096)))
        atomic_write_bytes(root / rel, raw)
        _append(root / JOURNAL, {"index": i, "file": rel, "sha256": hashlib.sha256(raw).hexdigest(),
                                 "bytes": len(raw), "signatures": data.n_signatures, "experiences": new_exp})
        seconds.append(time.perf_counter() - tp)
        bar.update(1)
    bar.close()

    # commit: the new manifest, written atomically, is the new generation
    done = _read_journal(root / JOURNAL, inputs)
    old_files = _files(doc)
    new = json.loads(json.dumps(doc))
    for p in new["places"]:
        r = done.get(int(p["index"]))
        if r is None:
            continue
        p.update({"file": r["file"], "sha256": r["sha256"], "bytes": r["bytes"], "signatures": r["signatures"]})
        p.setdefault("extra", {})["experiences"] = list(p["extra"].get("experiences", [])) + r["experiences"]
    new["generation"] = gen
    new["map_id"] = store.map_id          # the identity survives the update (written out for an old map)
    new["history"] = list(doc.get("history", [])) + [{
        "generation": gen, "inputs": inputs, "places": sorted(done),
        "runs": [{"run": loc.run.name, "conditions": list(loc.run.conditions)} for loc in locs]}]
    write_manifest(root, new)
    (root / JOURNAL).unlink(missing_ok=True)
    _collect_garbage(root, _files(new) | old_files)
    summary.update({
        "generation": gen, "updated": sorted(done),
        "seconds_per_updated_place": float(np.mean(seconds)) if seconds else None,
        "seconds": time.perf_counter() - t0,
        "bytes_added": int(sum(p["bytes"] for p in new["places"]) - sum(p["bytes"] for p in doc["places"])),
        "signatures_added": int(sum(e["signatures_added"] for r in done.values() for e in r["experiences"]))})
    atomic_write_text(root / SUMMARY, json.dumps(summary, indent=1, allow_nan=False) + "\n")
    return summary


def _files(doc: dict) -> set[str]:
    return {p["file"] for p in doc["places"]}


def _files_of_previous(root: Path, doc: dict) -> set[str]:
    """Files of the generation before ``doc``'s (kept for readers that opened its manifest): a place
    updated by the last generation had, before it, its latest file of an earlier generation or the build's."""
    keep = set()
    last = doc.get("history", [])[-1:] if doc.get("history") else []
    if not last:
        return keep
    gen = int(last[0]["generation"])
    for p in doc["places"]:
        if int(p["index"]) in last[0]["places"]:
            for g in range(gen - 1, -1, -1):
                if (root / place_file_name(p["index"], g)).is_file():
                    keep.add(place_file_name(p["index"], g))
                    break
    return keep
