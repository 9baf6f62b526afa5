"""``scenesig simulate OUT --preset P --seed S``: write simulated survey runs of a procedural world.

Stage of the pipeline: the embedded default data.  For each run (one appearance condition each) it
plans the vehicle's drive (:mod:`scenesig.surveys.sim.motion`), renders the camera frames of the world under
the run's condition with its own distractors (:mod:`scenesig.surveys.sim.scene`), simulates VO odometry and
INS/GPS with their error models, and writes a survey-run folder with :func:`scenesig.surveys.run.write_run`::

    OUT/world.json               preset, seed, route and layout summary (World.load regenerates it), and
                                 ``runs``: each run's name, conditions, camera rate and start (``start_m``)
    OUT/<run_name>/...           one survey run per condition (images, odometry, INS, exact truth)
    OUT/simulate_summary.json    runs, frames, seconds, frames_per_second

Everything follows from the seed: the same seed writes identical files.  The world (layout, textures,
route) depends on the preset and seed only; what differs between calls -- the conditions, the camera
rate, where on the route the runs start (``--start-m``) -- is kept in ``world.json``'s ``runs`` entry,
so runs of one call localise against a map built from runs of another call with the same seed.

Run as ``scenesig simulate OUT --preset tiny --seed 1``.
"""
from __future__ import annotations

import calendar
import json
import time
from pathlib import Path

import numpy as np

from ..io import atomic_write_text
from ..run import SurveyRun, write_run
from .conditions import CONDITIONS
from .motion import gps_fixes, ins, odometry, plan_drive
from .noise import rng_for
from .scene import RunScene, default_extrinsic
from .world import GENERATOR_VERSION, PRESETS, World

__all__ = ["default_config", "simulate", "simulate_run", "run_names"]

default_config = {
    "preset": "demo",
    "seed": 0,
    "runs": None,            # None: the preset's run list; else a list of condition names
    "camera_hz": 20.0,
    "start_m": 0.0,          # distance along the route where every run begins (a kidnapped start)
    "odometry_hz": 20.0,
    "ins_hz": 10.0,
    "gps_hz": 1.0,
    "jobs": 1,
    "jpeg_quality": 95,
}


def _world(preset: str, seed: int) -> World:
    """One World per (preset, seed) per process (workers build their own, identically), the one
    :func:`scenesig.surveys.sim.views.get_world` keeps: a pool worker that rendered runs then renders the
    map builder's truth depths (:mod:`scenesig.surveys.sim.truth`) with the textures it already made."""
    from .views import get_world

    return get_world(preset, seed)


def run_names(conditions: list[str]) -> list[str]:
    return [f"run{i:02d}_{c}" for i, c in enumerate(conditions)]


def _start_epoch(cond, index: int) -> float:
    y, mo, d, h, mi = cond.clock
    # a different day for every run, so repeated conditions do not share timestamps
    return float(calendar.timegm((y, mo, d, h, mi, 0))) + 86400.0 * index


def simulate_run(preset: str, seed: int, index: int, condition: str, out_dir, camera_hz: float = 20.0,
                 odometry_hz: float = 20.0, ins_hz: float = 10.0, gps_hz: float = 1.0, jpeg_quality: int = 95,
                 overwrite: bool = False, progress=None, single_thread: bool = False, start_m: float = 0.0) -> dict:
    """Simulate and write run number ``index`` with ``condition``; returns a small summary dict."""
    import cv2

    if not single_thread:
        return _simulate_run(preset, seed, index, condition, out_dir, camera_hz, odometry_hz, ins_hz, gps_hz,
                             jpeg_quality, overwrite, progress, start_m)
    saved = cv2.getNumThreads()       # OpenCV on one thread for this call only (a pooled worker), then restored
    cv2.setNumThreads(1)
    try:
        return _simulate_run(preset, seed, index, condition, out_dir, camera_hz, odometry_hz, ins_hz, gps_hz,
                             jpeg_quality, overwrite, progress, start_m)
    finally:
        cv2.setNumThreads(saved)


def _simulate_run(preset, seed, index, condition, out_dir, camera_hz, odometry_hz, ins_hz, gps_hz, jpeg_quality,
                  overwrite, progress, start_m) -> dict:
    t_start = time.perf_counter()
    world = _world(preset, seed)
    name = run_names([condition] * (index + 1))[index]
    rng = rng_for(seed, "motion", index)
    drive = plan_drive(world.route, rng, world.crossings, start_m=start_m)
    scene = RunScene(world, condition, run_key=(index,))
    cond = scene.cond
    cam = scene.camera
    T_vc = default_extrinsic()
    t_epoch = _start_epoch(cond, index)
    # sensor clocks: the camera starts after the 1 s lead-in; odometry and INS run on their own
    # phases and cover the whole drive, so every frame lies inside their time range
    ft = np.arange(1.0, drive.duration - 1.0, 1.0 / camera_hz)
    ot = np.arange(0.013, drive.duration, 1.0 / odometry_hz)
    it = np.arange(0.037, drive.duration, 1.0 / ins_hz)
    gt = np.arange(0.5, drive.duration, 1.0 / gps_hz)
    odo = odometry(drive, ot, rng_for(seed, "odometry", index), cond.odometry_factor)
    ins_poses, ins_err = ins(drive, it, rng_for(seed, "ins", index))
    gps = gps_fixes(drive, gt, it, ins_err, rng_for(seed, "gps", index))
    truth = drive.pose(ft)
    speed = drive.speed(ft)
    yaw_rate = np.gradient(np.unwrap(np.arctan2(truth[:, 1, 0], truth[:, 0, 0])), ft) if len(ft) > 1 else np.zeros(1)
    gps[:, 0] += t_epoch

    def frames():
        for k in range(len(ft)):
            img, _ = scene.render(truth[k] @ T_vc, frame=k, velocity=(float(speed[k]), float(yaw_rate[k])))
            if progress is not None:
                progress(1)
            yield img

    metadata = {
        "simulator": "surveys.sim", "generator_version": GENERATOR_VERSION, "preset": preset, "seed": int(seed),
        "run_index": int(index), "start_m": float(start_m),
        "condition": condition, "odometry_factor": float(cond.odometry_factor),
        "sun_elevation_deg": float(cond.sun_elev) if cond.sun_elev is not None else -1.0,
        "fog_visibility_m": float(cond.fog_visibility or 0.0),
        "stops_s": [float(s) for s, _ in drive.stops], "stops_dwell_s": [float(d) for _, d in drive.stops],
        "ins_offset_m": [float(v) for v in ins_err[0]],
        "lateral_offset_range_m": [float(v) for v in (drive.lateral_offset(ft).min(), drive.lateral_offset(ft).max())],
        "world_json": "../world.json",
    }
    run = SurveyRun(
        name=name, conditions=[condition], camera=cam, T_vehicle_camera=T_vc,
        rates={"camera_hz": float(camera_hz), "odometry_hz": float(odometry_hz), "ins_hz": float(ins_hz),
               "gps_hz": float(gps_hz)},
        frame_times=ft + t_epoch, frame_files=[f"images/{i:06d}.jpg" for i in range(len(ft))],
        odometry_times=ot + t_epoch, odometry_poses=odo, odometry_source="vo",
        groundtruth_times=it + t_epoch, groundtruth_poses=ins_poses,
        truth_times=ft + t_epoch, truth_poses=truth, gps=gps, metadata=metadata,
    )
    write_run(run, Path(out_dir) / name, images=frames(), overwrite=overwrite, jpeg_quality=jpeg_quality)
    return {"name": name, "conditions": [condition], "frames": int(len(ft)),
            "seconds": time.perf_counter() - t_start, "drive_seconds": float(drive.duration),
            "distance_m": float(world.route.drive_length)}


def simulate(out, preset: str = "demo", seed: int = 0, runs: list[str] | None = None, camera_hz: float = 20.0,
             jobs: int = 1, overwrite: bool = False, show_progress: bool = True, start_m: float = 0.0, **rates) -> dict:
    """Simulate a preset's runs (or the given condition list) into ``out``; returns the summary."""
    from tqdm import tqdm

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    conditions = list(runs) if runs else list(PRESETS[preset]["runs"])
    bad = [c for c in conditions if c not in CONDITIONS]
    if bad:
        raise ValueError(f"unknown condition(s) {', '.join(bad)}; choose from {', '.join(CONDITIONS)}")
    if not camera_hz or camera_hz <= 0:
        raise ValueError(f"camera rate must be positive, got {camera_hz}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = run_names(conditions)
    if not overwrite:
        clash = [n for n in names if (out / n).exists()]
        if clash:
            raise FileExistsError(f"{out / clash[0]}: survey run already exists (use another OUT folder, or "
                                  f"overwrite)")
    t0 = time.perf_counter()
    world = _world(preset, seed)
    desc = world.to_json()
    # frame counts up front (drives are cheap) for an honest progress bar; a bad start_m fails here
    total = 0
    for i in range(len(conditions)):
        d = plan_drive(world.route, rng_for(seed, "motion", i), world.crossings, start_m=start_m)
        total += len(np.arange(1.0, d.duration - 1.0, 1.0 / camera_hz))
    # everything that depends on this call rather than on the world goes in "runs"
    desc["runs"] = [{"name": n, "conditions": [c], "camera_hz": float(camera_hz), "start_m": float(start_m)}
                    for n, c in zip(names, conditions)]
    atomic_write_text(out / "world.json", json.dumps(desc, indent=1))
    kw = dict(camera_hz=camera_hz, start_m=float(start_m), **{k: v for k, v in rates.items() if v is not None})
    bar = tqdm(total=total, unit="frame", desc=f"simulate {preset}", disable=not show_progress)
    results = []
    if jobs == 1 or len(conditions) == 1:
        for i, c in enumerate(conditions):
            bar.set_postfix_str(names[i])
            results.append(simulate_run(preset, seed, i, c, out, overwrite=overwrite, progress=bar.update, **kw))
    else:
        from joblib import Parallel, delayed

        par = Parallel(n_jobs=jobs, return_as="generator_unordered")
        for res in par(delayed(simulate_run)(preset, seed, i, c, out, overwrite=overwrite, single_thread=True, **kw)
                       for i, c in enumerate(conditions)):
            bar.update(res["frames"])
            bar.set_postfix_str(res["name"])
            results.append(res)
    bar.close()
    seconds = time.perf_counter() - t0
    order = {n: i for i, n in enumerate(names)}
    results.sort(key=lambda r: order[r["name"]])
    frames = sum(r["frames"] for r in results)
    summary = {"runs": [{"name": r["name"], "conditions": r["conditions"]} for r in results],
               "frames": int(frames), "seconds": round(seconds, 3),
               "frames_per_second": round(frames / seconds, 2) if seconds > 0 else None,
               "preset": preset, "seed": int(seed), "camera_hz": float(camera_hz), "start_m": float(start_m), "jobs": int(jobs),
               "image_size": list(world.image_size)}
    atomic_write_text(out / "simulate_summary.json", json.dumps(summary, indent=1))
    return summary
