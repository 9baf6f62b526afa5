"""Latency of the online localiser per image: ``scenesig bench session DEMO_DIR``.

For each live run of a finished ``scenesig demo`` folder in the asked conditions (default night and fog) and
each method (default ``signatures`` and ``hybrid``), the run is fed through :class:`scenesig.Session` as a
vehicle would feed it -- GNSS/INS poses (``oracle="gnss"``), odometry samples in time order, and every
``every``-th camera frame (5 Hz: the demo's detector rate) as a decoded ``uint8`` array once the odometry
reaches it -- in two passes:

1. **as fast as it goes**: the wall time and the CPU time (every thread of the process, so work a call hands
   to a worker thread counts) of each :meth:`Session.add_image` call -- p50, p95, max -- and the wall time
   less the calling thread's wait for a core (``add_image_unqueued_ms``, :func:`benchmarks._timing.queued_seconds`:
   what the call takes on a machine that is not shared; conservative where other threads wait too);
2. **paced at the data's own clock** (a real 5 Hz camera): each input is given at its timestamp; reported are
   the longest any call blocked the caller (``add_image`` and ``add_odometry``), how many calls blocked
   longer than one detector period (``1 / detector_hz``), and the feed's largest lag behind the data clock.

Decoding the JPEG is not timed (a camera driver delivers arrays).  The map and runs are read, never written.
The machine's speed (``machine_reference_seconds``, :func:`benchmarks._timing.reference_seconds`) and load
average are reported beside the numbers: on a shared machine they say how much of a time is the load's.
Target (issue 36): p95 <= 60 ms for signatures at 640x480 on 2 cores; no call longer than one detector period
at 5 Hz.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from ._stages import emit_json
from ._timing import queued_seconds, reference_seconds

__all__ = ["benchmark", "feed", "main"]


def _stats(ms) -> dict:
    a = np.asarray(ms, float)
    if not len(a):
        return {"calls": 0}
    return {"calls": int(len(a)), "p50": round(float(np.percentile(a, 50)), 2),
            "p95": round(float(np.percentile(a, 95)), 2), "max": round(float(a.max()), 2),
            "mean": round(float(a.mean()), 2)}


def feed(session, run, every: int, paced: bool = False, frames: int | None = None) -> dict:
    """Feed ``run`` through ``session`` (module docstring); per-call wall and CPU ms, and for ``paced`` the
    blocking times and lag."""
    odo_t = np.asarray(run.odometry_times, float)
    incs = run.odometry_increments()
    ft = np.asarray(run.frame_times, float)
    for t in run.groundtruth_times:
        session.add_gnss(t, run.pose_at(t, "groundtruth"))
    # events in time order; a frame is given right after the odometry sample that reaches its time (as a
    # vehicle buffers an image until the odometry that spans it arrives: the Session's rule), so its call
    # localises it rather than holding it for add_odometry
    det = [i for i in range(len(ft)) if i % every == 0 and ft[i] <= odo_t[-1]][:frames]
    reach = np.searchsorted(odo_t, ft, side="left")
    events = sorted([(float(t), 0, k, float(t)) for k, t in enumerate(odo_t) if k <= reach[det[-1]]] +
                    [(float(odo_t[reach[i]]), 1, i, float(ft[i])) for i in det])
    wall, cpu, unq, odo_wall = [], [], [], []
    waited = 0.0
    fixes = 0
    lag_max = 0.0
    wall0 = time.perf_counter()
    t0 = events[0][0]
    first_odometry = True
    for t, kind, k, t_data in events:
        if kind == 1:
            image = run.image(k)                 # decoded before the call: a camera delivers arrays
        if paced:
            delay = wall0 + (t - t0) - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            lag_max = max(lag_max, time.perf_counter() - wall0 - (t - t0))
        w0, c0, q0 = time.perf_counter(), time.process_time(), queued_seconds()
        if kind == 0:
            session.add_odometry(t, np.eye(4) if first_odometry else incs[k - 1])
            first_odometry = False
            odo_wall.append(1e3 * (time.perf_counter() - w0))
        else:
            fix = session.add_image(max(t_data, float(odo_t[0])), image)
            wall.append(1e3 * (time.perf_counter() - w0))
            cpu.append(1e3 * (time.process_time() - c0))
            q1 = queued_seconds()
            if q0 is not None and q1 is not None:      # the wall time less this thread's wait for a core
                unq.append(wall[-1] - 1e3 * (q1 - q0))
                waited += q1 - q0
            fixes += fix is not None
    out = {"add_image_wall_ms": _stats(wall), "add_image_cpu_ms": _stats(cpu),
           # None where the kernel does not account run-queue waits (schedstats off: every wait reads 0)
           "add_image_unqueued_ms": _stats(unq) if unq and waited > 0 else None,
           "add_odometry_wall_ms": _stats(odo_wall), "fixes": int(fixes), "frames": len(det),
           "state_at_end": session.state, "frames_too_late": session.frames_too_late,
           "frames_dropped": session.frames_dropped, "frames_held": int(session.frames_held)}
    if paced:
        out["lag_max_s"] = round(lag_max, 3)
    return out, np.asarray(wall), np.asarray(odo_wall)


def benchmark(demo_dir, conditions=("night", "fog"), methods=("signatures", "hybrid"), detector_hz: float = 5.0,
              paced: bool = True, frames: int | None = None) -> dict:
    """The benchmark on ``demo_dir`` (module docstring); the JSON's content."""
    from scenesig import Session
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    demo_dir = Path(demo_dir)
    store = MapStore.open(demo_dir / "map")
    live = [r["run"] for r in json.loads((demo_dir / "summary.json").read_text())["runs"]]
    runs = [read_run(demo_dir / "world" / n) for n in live]
    runs = [r for r in runs if r.conditions and r.conditions[0] in conditions]
    if not runs:
        raise ValueError(f"{demo_dir}: no live run in the conditions {', '.join(conditions)} (live runs: "
                         f"{', '.join(live)})")
    period_ms = 1e3 / float(detector_hz)
    res = {"demo": str(demo_dir.resolve()), "cpu_count": os.cpu_count(), "detector_hz": float(detector_hz),
           "period_ms": period_ms, "load_average_before": [round(v, 2) for v in os.getloadavg()],
           "machine_reference_seconds_before": reference_seconds(), "runs": {}}
    for run in runs:
        camera_hz = 1.0 / float(np.median(np.diff(run.frame_times)))
        every = max(1, round(camera_hz / float(detector_hz)))
        res["runs"][run.name] = entry = {"conditions": list(run.conditions), "camera_hz": round(camera_hz, 3),
                                         "every": every, "image_size": [run.camera.width, run.camera.height]}
        for method in methods:
            with Session(store, run.camera, run.T_vehicle_camera, method, oracle="gnss") as s:
                fast, _, _ = feed(s, run, every, frames=frames)
            m = {"unpaced": fast}
            if paced:
                with Session(store, run.camera, run.T_vehicle_camera, method, oracle="gnss") as s:
                    p, w, ow = feed(s, run, every, paced=True, frames=frames)
                p["max_blocking_ms"] = round(float(max(w.max(initial=0.0), ow.max(initial=0.0))), 2)
                p["calls_over_period"] = int((w > period_ms).sum() + (ow > period_ms).sum())
                p["within_period"] = p["calls_over_period"] == 0
                m["paced"] = p
            entry[method] = m
    res["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
    res["machine_reference_seconds_after"] = reference_seconds()
    sig = [res["runs"][n]["signatures"]["unpaced"]["add_image_wall_ms"]["p95"] for n in res["runs"]
           if "signatures" in res["runs"][n]]
    if sig:
        res["signatures_p95_ms_worst"] = max(sig)
        res["target_p95_ms"] = 60.0
        res["target_met"] = max(sig) <= 60.0
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench session",
                                 description="Per-call latency of scenesig.Session.add_image on a finished demo's "
                                             "live runs (p50/p95/max wall and CPU ms), and a paced 5 Hz replay's "
                                             "longest blocking call against the detector period.")
    ap.add_argument("demo", help="a scenesig demo output folder (with world/, map/, summary.json)")
    ap.add_argument("--conditions", default="night,fog", help="live runs in these conditions (default night,fog)")
    ap.add_argument("--methods", default="signatures,hybrid", help="default signatures,hybrid")
    ap.add_argument("--detector-hz", type=float, default=5.0, help="images given per second (default 5)")
    ap.add_argument("--frames", type=int, default=None, help="at most this many images per run (default all)")
    ap.add_argument("--no-paced", action="store_true", help="skip the paced pass")
    ap.add_argument("--json", help="also write the JSON here")
    args = ap.parse_args(argv)
    if not (Path(args.demo) / "summary.json").is_file():
        from scenesig.surveys.errors import DataError

        raise DataError(Path(args.demo) / "summary.json", "missing: not a scenesig demo output folder")
    res = benchmark(args.demo, tuple(c for c in args.conditions.split(",") if c),
                    tuple(m for m in args.methods.split(",") if m), args.detector_hz, not args.no_paced, args.frames)
    emit_json(res, args.json)
    return 0


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    sys.exit(_cli(["bench", "session", *sys.argv[1:]]))
