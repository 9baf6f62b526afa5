"""Image selection for map building (McManus et al. 2015, §3.2, §3.2.1): which frames of which runs feed a place.

* *training images* (:func:`place_views`, :func:`mining_images`) -- the frame nearest the place from
  every training run, the reference run's first (the paper's training set); with few runs, each run also
  gives neighbouring frames within the place's segment (:func:`frames_per_run`), and a place that still
  has fewer than ``min_images`` images gets photometrically augmented copies of them
  (:mod:`scenesig.signatures.augment`);
* *negatives* (:func:`place_negatives`) -- the reference images of nearby places, extra negatives of mining;
* *refinement window* (:func:`_subsample`) -- the reference run's frames around the place that landmark
  refinement fires the kept classifiers over, spread evenly in distance travelled.

The options (``frames_per_run``, ``min_images``, ...) are build options (:data:`scenesig.mapping.build.default_config`),
passed in merged by the build (this module does not import it: the build imports this one).
"""
from __future__ import annotations

import math

import numpy as np

from scenesig.mapping import places as places_mod
from scenesig.signatures import experience
from scenesig.signatures.augment import synthesise
from scenesig.surveys.run import SurveyRun
from scenesig.surveys.settings import merge_settings

__all__ = ["MIN_IMAGES", "MAX_FRAMES_PER_RUN", "frames_per_run", "mining_images", "place_views", "place_negatives"]

#: Images a place is mined from at least (see ``frames_per_run``, ``min_images``): two per partition of
#: the clustering (McManus et al. 2015, §3.2; three partitions), as six runs give.
MIN_IMAGES = 6
#: Frames a run gives a place at most when ``frames_per_run`` is automatic.
MAX_FRAMES_PER_RUN = 3


def frames_per_run(cfg: dict, n_runs: int) -> int:
    """Frames each run gives a place seen by ``n_runs`` runs (``cfg``: merged build options)."""
    if cfg["frames_per_run"] is not None:
        n = int(cfg["frames_per_run"])
        if n < 1:
            raise ValueError(f"frames_per_run must be >= 1, got {n}")
        return n
    return int(min(cfg["max_frames_per_run"], max(1, math.ceil(cfg["min_images"] / max(1, n_runs)))))


def mining_images(seed: int, views: list, images: list, cfg: dict):
    """The images a place is mined from, and their alignment offsets.

    ``images[k]`` is the training frame of ``views[k]`` (the reference run's first); these come first
    and in that order, so with one frame per run and enough runs mining sees exactly the paper's
    training set.  Then each run's neighbouring frames (:func:`scenesig.mapping.places.neighbour_frames`, within
    the place's segment), then -- while the place has fewer than ``min_images`` -- photometrically
    augmented copies of the frames in turn (:func:`scenesig.signatures.augment.augment`; seeded by ``seed``, the
    place index at build time, so a build repeats), each offset by its known shift.  ``cfg`` is the merged
    build options (:data:`scenesig.mapping.build.default_config` with the overrides, as the build passes them).

    Returns
    -------
    images : list of ndarray (gray)
    offsets : (n, 2) ndarray
    counts : dict
        ``frames_per_run``, ``frames`` (real frames), ``augmented`` (copies).
    """
    import cv2

    pcfg = merge_settings(places_mod.default_config, cfg["places"], "places")
    per_run = frames_per_run(cfg, len(views))
    out = list(images)
    for v in views:
        for j in places_mod.neighbour_frames(v, per_run, pcfg["frame_step_m"], pcfg["spacing_m"] / 2)[1:]:
            out.append(v.run.image(int(j), gray=True))
    n_frames = len(out)
    rng = np.random.default_rng([int(seed), 19])
    conditions = experience.settings_for(len(views), None, cfg["single_experience"])["conditions"]
    out, offsets = synthesise(out, [[0.0, 0.0]] * n_frames, max(0, int(cfg["min_images"]) - n_frames),
                              rng, float(cfg["augment_shift_px"]), conditions)
    out = out[:n_frames] + [cv2.cvtColor(c, cv2.COLOR_BGR2GRAY) for c in out[n_frames:]]
    counts = {"frames_per_run": per_run, "frames": n_frames, "augmented": len(out) - n_frames}
    return out, np.asarray(offsets, dtype=float), counts


def place_views(place, train: list[SurveyRun], reference: SurveyRun, cfg: dict) -> list:
    """A place's training views (:func:`scenesig.mapping.places.training_views`), the reference run's first."""
    views = places_mod.training_views(place, train, cfg["places"])
    return [v for v in views if v.run.name == reference.name] + [v for v in views if v.run.name != reference.name]


def place_negatives(place, ref_frames: dict, reference: SurveyRun, cfg: dict) -> list[np.ndarray]:
    """Extra negatives of a place: the reference images of the places ``cfg["negative_places"]`` away
    (``ref_frames``: place index -> reference frame)."""
    return [reference.image(ref_frames[place.index + off], gray=True)
            for off in cfg["negative_places"] if place.index + off in ref_frames]


def _subsample(window: np.ndarray, centre: int, n: int, positions: np.ndarray | None = None) -> np.ndarray:
    """At most ``n`` frames of the window, evenly spread, always including the place's own frame.

    With ``positions`` (W, 3) of the window frames, the frames are spread evenly in distance travelled,
    not in frame count: a stop in the window would otherwise fill it with views from one spot, which
    carry no parallax and outvote the moving frames in the depth fit.
    """
    if len(window) <= n:
        return window
    if positions is None:
        pick = np.unique(np.round(np.linspace(0, len(window) - 1, n)).astype(int))
    else:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
        pick = np.unique(np.searchsorted(s, np.linspace(0.0, s[-1], n)).clip(0, len(window) - 1))
    out = np.union1d(window[pick], [centre])
    return out
