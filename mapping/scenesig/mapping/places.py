"""Places every 10 m along the reference run, and each place's training set (McManus et al. 2015, §3.2, §4.1).

A *place* ``π_p`` is a pose on the reference ("map") run's INS trajectory; places are spaced
``spacing`` metres apart in distance travelled.  Its frame is the reference vehicle pose there,
``T_world_place``; landmarks are stored in it.

For each place and each training run the *training image* is the run's frame nearest the place by
INS position and heading (paper: "images at approximately the same location and viewpoint"), and the
*refinement window* is that run's frames within ±``window`` metres of it, with their poses relative to
the training frame from the run's own odometry -- INS would carry its metre-level offset into the
landmark depths; odometry is smooth over 20 m.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scenesig.surveys.geometry import interpolate_poses, invert, yaw_of
from scenesig.surveys.run import SurveyRun
from scenesig.surveys.settings import merge_settings

__all__ = ["Place", "TrainingView", "define_places", "training_views", "neighbour_frames", "odometry_view",
           "default_config",
           "arc_length"]

default_config = {
    "spacing_m": 10.0,          # McManus et al. 2015, §4.1
    "window_m": 10.0,           # refinement window: ±10 m (paper footnote 5)
    "max_position_error_m": 8.0,  # a run further than this from a place (INS) does not see it
    "max_heading_error_deg": 30.0,
    "window_step": 1,           # use every n-th frame of the window
    # Mining frames of a run around its training frame (neighbour_frames): one step apart in distance
    # travelled, alternately ahead and behind, all within the place's own segment (±spacing_m / 2).
    "frame_step_m": 1.0,
}


@dataclass
class Place:
    """One place on the map."""

    index: int
    T_world_place: np.ndarray
    distance_m: float                    # along the reference run
    reference_frame: int                 # index of the reference run's frame nearest the place
    neighbours: list[int] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"index": self.index, "T_world_place": np.asarray(self.T_world_place).tolist(),
                "distance_m": float(self.distance_m), "reference_frame": int(self.reference_frame),
                "neighbours": list(self.neighbours)}

    @classmethod
    def from_dict(cls, d: dict) -> "Place":
        return cls(int(d["index"]), np.asarray(d["T_world_place"], float), float(d["distance_m"]),
                   int(d["reference_frame"]), [int(n) for n in d.get("neighbours", [])])


@dataclass
class TrainingView:
    """One run's view of one place: its training frame and refinement window."""

    run: SurveyRun
    frame: int                           # the training frame (nearest to the place)
    window: np.ndarray                   # frame indices within ±window_m (includes ``frame``)
    T_frame_window: np.ndarray           # (W,4,4) vehicle poses of the window frames in the training
                                         # frame's vehicle frame, from odometry
    position_error_m: float              # INS distance from the place (diagnostic)


def arc_length(positions: np.ndarray) -> np.ndarray:
    """Cumulative distance (m) along a polyline of positions (N,3)."""
    step = np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _frame_poses(run: SurveyRun) -> np.ndarray:
    if run.groundtruth_times is None:
        raise ValueError(f"run {run.name!r} has no INS/GPS poses (groundtruth.tum): it cannot define or train places")
    return interpolate_poses(run.groundtruth_times, run.groundtruth_poses, run.frame_times)


def define_places(reference: SurveyRun, config: dict | None = None) -> list[Place]:
    """Places every ``spacing_m`` along the reference run's INS trajectory (first one after half a spacing)."""
    cfg = merge_settings(default_config, config, "places")
    poses = _frame_poses(reference)
    s = arc_length(poses[:, :3, 3])
    spacing = cfg["spacing_m"]
    targets = np.arange(spacing / 2, s[-1] - spacing / 4, spacing)
    places = []
    for k, d in enumerate(targets):
        i = int(np.argmin(np.abs(s - d)))
        places.append(Place(k, poses[i].copy(), float(s[i]), i))
    for p in places:  # neighbours: places within 1.6 spacings (handles closed loops by position)
        pos = p.T_world_place[:3, 3]
        p.neighbours = [q.index for q in places if q.index != p.index
                        and np.linalg.norm(q.T_world_place[:3, 3] - pos) < 1.6 * spacing]
    return places


def training_views(place: Place, runs: list[SurveyRun], config: dict | None = None) -> list[TrainingView]:
    """For each run that passes the place, its nearest frame (position and heading) and ±window frames."""
    cfg = merge_settings(default_config, config, "places")
    views = []
    p_xy = place.T_world_place[:2, 3]
    p_yaw = yaw_of(place.T_world_place)
    for run in runs:
        poses = _frame_poses(run)
        dist = np.linalg.norm(poses[:, :2, 3] - p_xy, axis=1)
        dyaw = np.abs((yaw_of(poses) - p_yaw + np.pi) % (2 * np.pi) - np.pi)
        ok = dyaw < np.deg2rad(cfg["max_heading_error_deg"])
        if not ok.any():
            continue
        cost = np.where(ok, dist, np.inf)
        i = int(np.argmin(cost))
        if dist[i] > cfg["max_position_error_m"]:
            continue
        views.append(_view(run, i, arc_length(poses[:, :3, 3]), cfg, float(dist[i])))
    return views


def neighbour_frames(view: TrainingView, n: int, step_m: float, half_span_m: float) -> np.ndarray:
    """Up to ``n`` frames of one run for mining a place: the training frame and its neighbours.

    Targets lie ``step_m`` apart in distance travelled -- 0, +step, -step, +2 step, ... -- within
    ``half_span_m`` of the training frame (the place's own segment, so the frames show this place and
    not the next one); each takes the window frame nearest to it in the run's odometry.  Neighbouring
    frames give the clustering small viewpoint changes of one appearance, which is what it needs to
    find a patch again when a map has few runs (the paper's many runs give it many appearances instead,
    McManus et al. 2015, §3.2).  A target whose nearest frame is already taken (the vehicle stopped)
    adds nothing, so a run may give fewer than ``n`` frames.

    Returns
    -------
    ndarray of int
        Frame indices, the training frame first.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"frames per run must be >= 1, got {n}")
    pos = view.T_frame_window[:, :3, 3]
    s = arc_length(pos)
    s = s - s[int(np.searchsorted(view.window, view.frame))]
    frames = [int(view.frame)]
    k = 1
    while len(frames) < n and k * step_m <= half_span_m + 1e-9:
        for target in (k * step_m, -k * step_m):
            r = int(np.argmin(np.abs(s - target)))
            if len(frames) < n and abs(s[r] - target) <= 0.5 * step_m and int(view.window[r]) not in frames:
                frames.append(int(view.window[r]))
        k += 1
    return np.asarray(frames, dtype=int)


def _view(run: SurveyRun, i: int, s: np.ndarray, cfg: dict, position_error_m: float) -> TrainingView:
    """Frame ``i``'s view: the frames within ±``window_m`` of it by arc length ``s`` (one per frame) and
    their poses relative to frame ``i`` from the run's odometry."""
    win = np.nonzero(np.abs(s - s[i]) <= cfg["window_m"])[0][:: cfg["window_step"]]
    if i not in win:
        win = np.sort(np.append(win, i))
    odo = interpolate_poses(run.odometry_times, run.odometry_poses, run.frame_times[win])
    T_ref = interpolate_poses(run.odometry_times, run.odometry_poses, run.frame_times[i])
    return TrainingView(run, i, win, invert(T_ref) @ odo, position_error_m)


def odometry_view(run: SurveyRun, frame: int, config: dict | None = None,
                  position_error_m: float = float("nan")) -> TrainingView:
    """The view of a chosen frame of a run using nothing but its odometry (window by odometry arc length):
    a live run's frame added to a place by a lifelong update, whose INS must not be used."""
    cfg = merge_settings(default_config, config, "places")
    odo = interpolate_poses(run.odometry_times, run.odometry_poses, run.frame_times)
    return _view(run, int(frame), arc_length(odo[:, :3, 3]), cfg, position_error_m)
