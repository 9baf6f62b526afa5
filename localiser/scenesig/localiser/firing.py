"""How often each place's signatures fire on their own place and elsewhere: the rates the integrity
monitor's sequential test (:mod:`scenesig.localiser.integrity`) is built on.

At build time the map holds, for every place, the frame of each training run nearest the place and
its pose relative to the place (the georeferencing's visual solve, :mod:`scenesig.mapping.georef`).
From those this module measures, with the localiser's own detector and solver (McManus et al. 2015,
§3.3: windows around the predicted projections, eq. 10), the share of the place's signatures searched
that the solver keeps as inliers:

* **own** -- on frames of every training run a few metres before and after the place (not the frames
  the bank was mined on), the motion prior at their true pose relative to the place: what a right map
  gives, in every training condition;
* **other** -- with the same priors, on frames of the same runs half a run away (another place of the
  world): what a map that does not explain the image gives -- the predicted windows are searched on a
  view of something else, as when a vehicle is given another world's map.

The rates are written beside the map (``firing.json``, :data:`FILE`; the map's own files and their
checksums are untouched) and read by the replay (:func:`load`).  A map without the file -- built
before the statistics existed -- is localised with the monitor's threshold tests instead
(:mod:`scenesig.localiser.integrity`, which says so).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from scenesig.surveys.geometry import interpolate_poses, invert
from scenesig.surveys.io import atomic_write_text
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "FILE", "estimate", "write", "load", "for_map"]

log = logging.getLogger(__name__)

FILE = "firing.json"
VERSION = 1

default_config = {
    "offsets_m": [3.0, 6.0],       # own frames this far before and after each run's training frame
    "prior_sigma": [0.01, 0.01, 0.02, 0.5, 0.5, 0.1],   # the priors' σ (rad, rad, rad, m, m, m): tracking-like
}


def _ins(run, frame: int) -> np.ndarray:
    return interpolate_poses(run.groundtruth_times, run.groundtruth_poses, run.frame_times[int(frame)]).reshape(4, 4)


def _travelled(run) -> np.ndarray:
    """Distance along the run's INS track at every frame (m)."""
    xy = np.array([_ins(run, f)[:2, 3] for f in range(len(run))])
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def estimate(store, runs, config: dict | None = None) -> dict:
    """Per place ``{"own": rate, "other": rate, "own_searched": n, "other_searched": n, ...}`` (module
    docstring); ``runs`` are the map's training runs (:class:`scenesig.surveys.run.SurveyRun`), matched to
    the places' georeferencing records by name.  Places without usable frames are left out."""
    from .methods import MotionPrior
    from .signature_method import SignatureLocaliser

    cfg = merge_settings(default_config, config, "firing")
    runs = {r.name: r for r in runs}
    if not runs:
        raise ValueError("firing rates need the map's training runs")
    first = next(iter(runs.values()))
    method = SignatureLocaliser(store, first.camera, first.T_vehicle_camera)
    P = np.diag(np.asarray(cfg["prior_sigma"], float) ** 2)
    along = {name: _travelled(r) for name, r in runs.items()}
    out = {}
    try:
        for idx in store.places:
            data = store.load_place(idx)
            T_wp = store.places[idx].T_world_place
            counts = {"own": [0, 0, 0], "other": [0, 0, 0]}       # inliers, searched, frames
            for rec in data.meta.get("georef") or []:
                run = runs.get(rec.get("run"))
                if run is None:
                    continue
                k = int(rec["frame"])
                if rec.get("run") == data.meta.get("reference_run") and int(data.meta.get("reference_frame", -1)) == k:
                    T_pk = np.eye(4)                    # the place frame is this frame's vehicle pose
                elif rec.get("ok") and rec.get("T_place_vehicle") is not None:
                    T_pk = np.asarray(rec["T_place_vehicle"], float)
                else:
                    continue
                d = along[run.name]
                T_kw = invert(_ins(run, k))
                for off in cfg["offsets_m"]:
                    for sign in (-1.0, 1.0):
                        f = int(np.argmin(np.abs(d - (d[k] + sign * off))))
                        if abs(abs(d[f] - d[k]) - off) > 1.5:       # the run does not reach that far
                            continue
                        T_pv = T_pk @ T_kw @ _ins(run, f)
                        prior = MotionPrior(float(run.frame_times[f]), T_wp @ T_pv, P, idx, T_wp, None, False, 0.0)
                        # another place of the same run: half its length away
                        g = int(np.argmin(np.abs(d - ((d[f] + d[-1] / 2) % max(d[-1], 1e-9)))))
                        for kind, frame in (("own", f), ("other", g)):
                            img = method.prepare(run.image(frame, gray=not method.color))
                            obs = method.detect(img, idx, prior)
                            m = method.solve(obs, idx, prior)
                            c = counts[kind]
                            c[0] += int(m.inliers)
                            c[1] += int(obs.searched)
                            c[2] += 1
            if counts["own"][1] and counts["other"][1]:
                out[int(idx)] = {"own": counts["own"][0] / counts["own"][1],
                                 "other": counts["other"][0] / counts["other"][1],
                                 "own_searched": counts["own"][1], "other_searched": counts["other"][1],
                                 "own_frames": counts["own"][2], "other_frames": counts["other"][2]}
    finally:
        method.close()
    return out


def write(map_dir, rates: dict, config: dict | None = None) -> Path:
    """Write the rates beside the map (``map_dir/firing.json``), naming the map they belong to."""
    from scenesig.mapping.store import MapStore

    store = MapStore.open(map_dir)
    doc = {"version": VERSION, "map_id": store.map_id, "generation": store.generation,
           "settings": merge_settings(default_config, config, "firing"),
           "places": {str(k): v for k, v in sorted(rates.items())}}
    path = Path(map_dir) / FILE
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    return path


def load(store) -> dict | None:
    """``{place: (own, other)}`` from the map's ``firing.json``, or None where the map has none (or it
    belongs to another map or another generation of this one: an update re-mined places since)."""
    path = Path(store.root) / FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        if doc.get("version") != VERSION:
            return None
        if doc.get("map_id") != store.map_id or doc.get("generation") != store.generation:
            log.warning("%s: firing rates of another map state (%s generation %s; the map is %s generation %s): "
                        "not used", path, doc.get("map_id"), doc.get("generation"), store.map_id, store.generation)
            return None
        return {int(k): (float(v["own"]), float(v["other"])) for k, v in doc["places"].items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        from scenesig.surveys.errors import DataError

        raise DataError(path, f"cannot read the firing rates: {exc}") from None


def for_map(map_dir, runs, config: dict | None = None) -> Path:
    """Estimate the rates of the map at ``map_dir`` from its training ``runs`` and write them beside it
    (what building a map does last: :func:`scenesig.api.build_map`, the demo)."""
    from scenesig.mapping.store import MapStore

    return write(map_dir, estimate(MapStore.open(map_dir), runs, config), config)
