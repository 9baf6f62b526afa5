"""Profile of ``scenesig localise``: ``scenesig bench profile_localise MAP RUN [--every 2] [--json OUT]``.

Replays one run against a map exactly as ``scenesig localise`` does (deterministic mode, the
detector on every ``--every``-th frame; the demo's 10 Hz camera with ``--every 2`` is the paper's
5 Hz detector) and reports where the replay loop's wall time goes, per stage:

* ``image_decode`` -- reading and decoding the detector frames (:meth:`scenesig.surveys.run.SurveyRun.image`;
  with prefetching, the default, on a worker thread, overlapping the other stages);
* ``hog`` -- the HOG pyramid regions the bank needs (:func:`scenesig.signatures.hog.build_level`, one level);
* ``bank_filters`` -- the filter responses (``scenesig.signatures.detection._score_job``, one level and filter width);
* ``peak_search`` -- best firing per classifier, sub-cell refinement (``scenesig.signatures.detection._pick``);
* ``search_windows`` -- the prior's search windows and predicted scales (:mod:`scenesig.localiser.detector`);
* ``solve`` -- the eq. 10 pose solve (:func:`scenesig.localiser.solver.solve`);
* ``graph_update`` -- odometry, localisations and resets into the pose graph
  (:class:`scenesig.localiser.posegraph.PoseGraph`); ``graph_query`` -- its estimates and marginals;
* ``snap`` -- SE(2) snapping; ``place_choice`` -- nearest place and the place ahead;
* ``bookkeeping`` -- the rest of the loop (wall time of the loop minus what the main thread spent
  in the stages; with ``--threads 2`` it includes the main thread waiting for a level another
  thread describes).

The detector describes and scores the pyramid levels on its own threads by default (as
``scenesig localise``: two for a whole-image search, one for a windowed one); ``--threads N``
uses N for both, and ``--threads 1`` gives the serial profile, where the stages add up.

``machine_reference_seconds`` is a fixed workload's time before and after the replay
(:func:`scenesig.benchmarks._timing.reference_seconds`, ~0.4 s on the development machine at its usual speed):
the machine's speed while the profile was taken.

Each stage has ``ms`` (wall, exclusive: a stage called inside another is charged to itself),
``cpu_ms`` (CPU time of the thread that ran it), ``calls``, both per detector frame, and
``threads``.  ``realtime_factor`` and ``wall_seconds`` are the replay's own (data duration / wall
time of the loop); ``cpu_seconds`` is the process CPU time of the loop.  On a loaded machine wall
times include waiting for a core and CPU times do not: compare CPU times there.  On Linux,
``main_thread_queued_seconds`` is the time the replay's thread spent runnable but waiting for a
core (``/proc/thread-self/schedstat``) over the whole call (``call_wall_seconds``, set-up included),
and ``realtime_factor_unqueued`` the realtime factor with the loop's share of it (in proportion to
the loop's share of the call) taken out -- an estimate of the idle-machine figure that also works under load (conservative
with ``--threads 2``: a worker thread's own waits for a core, which the replay's thread waits
out, stay in).
"""
from __future__ import annotations

import argparse
import time

__all__ = ["profile_localise", "main"]


def _targets():
    from scenesig.localiser import detector, posegraph, se2, signature_method
    from scenesig.localiser.pipeline import Localiser
    from scenesig.mapping.store import MapStore
    from scenesig.signatures import detection, hog
    from scenesig.surveys.run import SurveyRun
    return [(SurveyRun, "image", "image_decode"),
            (detection, "build_level", "hog"), (hog, "build_level", "hog"), (detection, "_score_job", "bank_filters"),
            (detection, "_pick", "peak_search"),
            (detector, "search_windows", "search_windows"),
            (detector.Detector, "_predicted_levels", "search_windows"),
            (signature_method, "solve", "solve"),
            (posegraph.PoseGraph, "add_odometry", "graph_update"),
            (posegraph.PoseGraph, "add_localisation", "graph_update"),
            (posegraph.PoseGraph, "reset", "graph_update"),
            (posegraph.PoseGraph, "estimate", "graph_query"),
            (posegraph.PoseGraph, "covariance", "graph_query"),
            (se2.PlaneSnapper, "snap", "snap"),
            (MapStore, "nearest_place", "place_choice"), (Localiser, "place_ahead", "place_choice")]


def profile_localise(map_root, run_root, method: str = "signatures", every: int = 2,
                     prefetch: bool = True, threads: int | None = None) -> dict:
    """Replay ``run_root`` against ``map_root`` with stage timers (module docstring)."""
    from scenesig.benchmarks._stages import StageTimer
    from scenesig.benchmarks._timing import queued_seconds, reference_seconds
    from scenesig.localiser.replay import replay
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    store = MapStore.open(map_root)
    run = read_run(run_root)
    timer = StageTimer()
    ref0 = reference_seconds()
    q0, w0 = queued_seconds(), time.perf_counter()
    with timer.patch(*_targets()):
        c0, m0 = time.process_time(), time.thread_time()
        config = {"prefetch": bool(prefetch)}
        if method == "signatures" and threads is not None:
            config["method"] = {"detector": {"threads": int(threads), "window_threads": int(threads)}}
        res = replay(store, run, method, every=every, config=config)
        cpu, main_cpu = time.process_time() - c0, time.thread_time() - m0
    q1, call_wall = queued_seconds(), time.perf_counter() - w0
    tm = res.timings
    # the queue is read around the whole call (map and run set-up included), the replay's own wall time
    # inside it: the loop's share of the queueing is taken in proportion to its share of the call
    queued_loop = None if q0 is None else (q1 - q0) * tm["wall_seconds"] / max(call_wall, 1e-9)
    n_det = int(res.detector_ran.sum())
    stages = timer.as_dict(per=max(n_det, 1))
    for k, d in stages.items():
        d["ms_per_detector_frame"] = d.pop("ms_per")
        d["cpu_ms_per_detector_frame"] = d.pop("cpu_ms_per")
        d["threads"] = sorted(timer.thread_names[k])
    main = [timer.by_thread[k].get("MainThread", (0.0, 0.0)) for k in timer.seconds]
    book = tm["wall_seconds"] - sum(m[0] for m in main)
    book_cpu = main_cpu - sum(m[1] for m in main)
    stages["bookkeeping"] = {"ms": round(1e3 * book, 3), "cpu_ms": round(1e3 * book_cpu, 3), "calls": 0,
                             "ms_per_detector_frame": round(1e3 * book / max(n_det, 1), 3),
                             "cpu_ms_per_detector_frame": round(1e3 * book_cpu / max(n_det, 1), 3),
                             "threads": ["MainThread"]}
    ref1 = reference_seconds()
    return {"map": str(map_root), "run": run.name, "method": res.method, "every": every, "prefetch": bool(prefetch),
            "machine_reference_seconds": [ref0, ref1],
            "threads": (None if threads is None else int(threads)) if method == "signatures" else None,
            "frames": len(res.times), "detector_frames": n_det, "duration_s": round(tm["duration_s"], 3),
            "wall_seconds": round(tm["wall_seconds"], 3), "cpu_seconds": round(cpu, 3),
            "realtime_factor": round(tm["realtime_factor"], 3),
            "call_wall_seconds": round(call_wall, 3),
            "main_thread_queued_seconds": None if q0 is None else round(q1 - q0, 3),
            "realtime_factor_unqueued": None if q0 is None else
            round(tm["duration_s"] / max(tm["wall_seconds"] - queued_loop, 1e-9), 3),
            "ms_per_detection": tm["ms_per_detection"], "ms_per_solve": tm["ms_per_solve"],
            "localised_fraction": float(res.localised.sum()) / max(n_det, 1), "failures": int(res.failures),
            "stages": stages}


def main(argv=None) -> int:
    from scenesig.benchmarks._stages import emit_json

    ap = argparse.ArgumentParser(prog="scenesig bench profile_localise", description=__doc__.splitlines()[0])
    ap.add_argument("map", help="map folder")
    ap.add_argument("run", help="survey run folder")
    ap.add_argument("--method", default="signatures")
    ap.add_argument("--every", type=int, default=2, help="detector on every N-th frame (default 2: 5 Hz at 10 Hz)")
    ap.add_argument("--no-prefetch", action="store_true", help="decode frames inline (serial profile)")
    ap.add_argument("--threads", type=int, default=None,
                    help="detector threads, whole-image and windowed (pyramid levels at once; default: the "
                         "detector's own, 2 and 1; 1: serial profile)")
    ap.add_argument("--json", help="write the result JSON here")
    args = ap.parse_args(argv)
    res = profile_localise(args.map, args.run, args.method, args.every, not args.no_prefetch, args.threads)
    emit_json(res, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
