"""Ground truth of simulated survey runs beyond poses: the true depth behind every pixel of a frame.

A simulated run records in ``run.toml [metadata]`` the preset, seed, run index and condition it was
made with; that is enough to regenerate its world and scene exactly (the simulator is deterministic)
and to render the depth buffer of any frame from its ``truth.tum`` pose.  Used to measure how far
estimated landmark depths are from the truth.
"""
from __future__ import annotations

import numpy as np

from ..errors import DataError
from ..run import SurveyRun

__all__ = ["is_simulated", "world_for_run", "scene_for_run", "camera_pose", "depth_image"]

_SCENES: dict = {}


def is_simulated(run: SurveyRun) -> bool:
    return run.metadata.get("simulator") == "surveys.sim" and run.truth_poses is not None


def world_for_run(run: SurveyRun):
    """The :class:`~surveys.sim.world.World` a simulated run was rendered from."""
    from .views import get_world
    from .world import GENERATOR_VERSION, PRESETS

    where = run.root / "run.toml" if run.root is not None else None
    md = run.metadata
    for k in ("preset", "seed", "run_index", "condition"):
        if k not in md:
            raise DataError(where, f"simulated run lacks metadata.{k}: cannot regenerate its world")
    if md["preset"] not in PRESETS:
        raise DataError(where, f"unknown simulator preset {md['preset']!r}")
    version = md.get("generator_version", GENERATOR_VERSION)
    if version != GENERATOR_VERSION:
        raise DataError(where, f"made by simulator generator version {version}, this is {GENERATOR_VERSION}")
    return get_world(md["preset"], int(md["seed"]))


def scene_for_run(run: SurveyRun, static: bool = False):
    """The run's :class:`~surveys.sim.scene.RunScene` (its condition and distractors), cached."""
    from .scene import RunScene

    world = world_for_run(run)
    md = run.metadata
    key = (md["preset"], int(md["seed"]), int(md["run_index"]), md["condition"], run.camera, static)
    sc = _SCENES.get(key)
    if sc is None:
        _SCENES.clear()  # one scene at a time: each holds its baked textures
        sc = RunScene(world, md["condition"], run_key=(int(md["run_index"]),), camera=run.camera,
                      distractors=not static)
        _SCENES[key] = sc
    return sc


def camera_pose(run: SurveyRun, frame: int) -> np.ndarray:
    """True ``T_world_camera`` of a frame."""
    T_wv = run.pose_at(run.frame_times[frame], which="truth")
    return T_wv @ run.T_vehicle_camera


def depth_image(run: SurveyRun, frame: int, static: bool = False) -> np.ndarray | None:
    """True z-depth (metres, float32, inf where only sky) behind every pixel of frame ``frame``.

    Returns None for runs that are not simulated.  ``static=True`` leaves out the run's parked cars
    and pedestrians (the permanent structure only); by default the depth is that of what the image
    shows, including them (and, e.g., bare trees in the snow run).
    """
    if not is_simulated(run):
        return None
    if not 0 <= frame < len(run):
        raise IndexError(f"frame {frame} out of range 0..{len(run) - 1}")
    sc = scene_for_run(run, static)
    return sc.render(camera_pose(run, frame), frame=frame)[1]
