"""Speed benchmark of scene signatures: ``scenesig bench speed --json OUT``.

Measures, on simulated 640x480 images of one place (``scenesig.surveys.sim.place_views(preset="demo",
seed=0, n=31)``; the JSON's ``images`` names them):

* ``train_seconds_per_place`` -- :func:`scenesig.signatures.mining.mine_place` on the 31 images with all
  296 candidate shapes, pyramids included, on **one core** (BLAS, OpenCV and joblib limited to one
  thread); the median of ``train_repeats`` (3) trainings, each listed in
  ``train_seconds_per_place_runs`` (a shared virtual machine's speed drifts by a third within
  minutes; one training is one sample of it);
* ``detect_ms_per_frame`` -- one-pass detection of banks of 50 and 200 classifiers on a 640x480
  frame, whole-image search, pyramid included, on **two cores** (the pyramid levels, each described
  then scored, on two threads -- ``threads=2``, as the localiser's detector runs it; OpenCV on two
  threads; the filter multiplies on one BLAS thread, the bank's ``blas_threads`` default); the
  banks are drawn from the classifiers mined above (with repetition when fewer survived, so
  filter sizes and levels are realistic).  ``detect_ms_per_frame_windowed`` repeats it with +-40-px search windows, as the
  localiser runs it;
* ``hog_pyramid_ms`` (the levels the 50-classifier bank needs) and ``hog_ms_per_level``
  (640x480, one core);
* ``blas`` -- the BLAS library numpy uses (threadpoolctl);
* ``machine_reference_seconds`` -- a fixed workload's time before and after
  (:func:`scenesig.benchmarks._timing.reference_seconds`): the machine's speed while the figures were taken.

Timings are medians over repeats.  Wall time on a loaded machine measures the load as much as the
code, so the JSON also holds the CPU time of the process -- ``train_cpu_seconds_per_place`` and
``detect_cpu_ms_per_frame`` (mean per detection, both threads summed) -- and ``load_average``;
compare CPU times between runs made under load.  ``detect_ms_per_frame_unqueued`` (Linux) is the
detection's wall time minus the time the calling thread waited for a core: an estimate of the
idle-machine figure that holds up under load, conservative since the second thread's waits stay in.  Run ``scenesig bench speed --json OUT``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from scenesig.benchmarks._timing import median_ms, median_ms_unqueued, reference_seconds
from scenesig.signatures import hog as hogmod, mining
from scenesig.signatures.bank import Bank
from scenesig.surveys.io import atomic_write_text

__all__ = ["run_speed_bench", "run_from_args", "place_images"]


def place_images(n: int = 31, seed: int = 0):
    """(images, offsets, source) of one simulated place at 640x480."""
    from scenesig.surveys.sim import place_views

    views = place_views(preset="demo", seed=seed, n=n)
    images = [np.asarray(v[0]) for v in views]
    images = [im if im.shape[:2] == (480, 640) else
              cv2.resize(im, (640, 480), interpolation=cv2.INTER_AREA) for im in images]
    return images, np.zeros((len(images), 2)), "surveys.sim.place_views(preset='demo')"


def _blas_info() -> dict:
    """numpy's BLAS (build config) and every BLAS loaded in the process (threadpoolctl)."""
    out = {"library": "unknown"}
    try:
        cfg = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        out = {"library": cfg.get("name"), "version": cfg.get("version")}
    except Exception:   # noqa: BLE001 - informational only
        pass
    try:
        from threadpoolctl import threadpool_info
        out["loaded"] = [{"api": d.get("internal_api"), "version": d.get("version"),
                          "architecture": d.get("architecture"), "threads": d.get("num_threads"),
                          "file": Path(d.get("filepath", "")).name}
                         for d in threadpool_info() if d.get("user_api") == "blas"]
    except Exception:   # noqa: BLE001
        pass
    return out


def _bank_of(bank: Bank, n: int, rng) -> Bank:
    idx = rng.choice(len(bank), size=n, replace=len(bank) < n)
    return Bank([bank.classifiers[i] for i in np.sort(idx)], bank.image_size)


def run_speed_bench(n_images: int = 31, repeat: int = 10, seed: int = 0, progress: bool = True,
                    train_repeats: int = 3) -> dict:
    """Run the benchmark and return the result dict (see module docstring)."""
    from threadpoolctl import threadpool_limits
    ref0 = reference_seconds()
    images, offsets, source = place_images(n_images, seed)
    frame = images[-1]
    out = {"images": source, "n_images": len(images), "image_size": [640, 480],
           "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
           "blas": _blas_info()}
    cv_threads = cv2.getNumThreads()
    try:
        # ---------------- one core: HOG and training
        cv2.setNumThreads(1)
        with threadpool_limits(limits=1):
            gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            out["hog_ms_per_level"] = round(median_ms(lambda: hogmod.fhog(gray), repeat * 2), 2)
            walls, cpus = [], []
            for _ in range(max(1, int(train_repeats))):   # the same bank every time (seeded)
                t0, c0 = time.perf_counter(), time.process_time()
                bank, stats = mining.mine_place(images, offsets, n_jobs=1, rng=seed, progress=progress)
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            out["train_seconds_per_place"] = round(float(np.median(walls)), 2)
            out["train_seconds_per_place_runs"] = [round(v, 2) for v in walls]
            out["train_cpu_seconds_per_place"] = round(float(np.median(cpus)), 2)
            out["train_stats"] = {k: v for k, v in stats.as_dict().items() if k != "partitions"}
        if len(bank) == 0:
            raise RuntimeError("no classifier converged on the benchmark place; cannot time "
                               "detection")
        rng = np.random.default_rng(seed)
        banks = {n: _bank_of(bank, n, rng) for n in (50, 200)}
        with threadpool_limits(limits=1):
            lv = banks[50].levels()
            out["hog_pyramid_levels"] = lv
            out["hog_pyramid_ms"] = round(median_ms(
                lambda: hogmod.build_pyramid(frame, bank.hog, levels=lv), repeat), 2)
        # ---------------- two cores: detection
        cv2.setNumThreads(2)
        with threadpool_limits(limits=2):
            det, detu, detw, det_cpu = {}, {}, {}, {}
            two = {"threads": 2}          # the pyramid levels on two threads, as the localiser's detector
            for n, b in banks.items():
                c0 = time.process_time()
                wall, unqueued = median_ms_unqueued(lambda: b.detect(frame, config=two), repeat)
                det_cpu[str(n)] = round(1000.0 * (time.process_time() - c0) / (repeat + 1), 2)
                det[str(n)] = round(wall, 2)
                detu[str(n)] = None if unqueued is None else round(unqueued, 2)
                nom = np.array([c.nominal_xy for c in b])
                win = np.concatenate([nom - 40.0, nom + 40.0], axis=1)
                detw[str(n)] = round(median_ms(lambda: b.detect(frame, windows=win, config=two), repeat), 2)
            out["detect_ms_per_frame"] = det
            out["detect_ms_per_frame_unqueued"] = detu
            out["detect_hz"] = {k: round(1000.0 / v, 1) for k, v in det.items()}
            out["detect_ms_per_frame_windowed"] = detw
            out["detect_cpu_ms_per_frame"] = det_cpu
    finally:
        cv2.setNumThreads(cv_threads)
    out["threads"] = {"train": 1, "detect": 2}
    out["machine_reference_seconds"] = [ref0, reference_seconds()]
    out["load_average"] = [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None
    return out


def run_from_args(args) -> int:
    """CLI entry (``scenesig bench speed``): ``args.json`` = output path or None."""
    res = run_speed_bench(progress=True, train_repeats=getattr(args, "train_repeats", 3))
    text = json.dumps(res, indent=1)
    print(text)
    if getattr(args, "json", None):
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.json, text + "\n")
    return 0


def main(argv=None) -> int:
    """``scenesig bench speed [--json OUT]``."""
    ap = argparse.ArgumentParser(prog="scenesig bench speed", description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the result JSON here")
    ap.add_argument("--train-repeats", type=int, default=3,
                    help="trainings timed (train_seconds_per_place is their median; default 3)")
    return run_from_args(ap.parse_args(argv))


if __name__ == "__main__":
    import sys

    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "speed", *sys.argv[1:]]))
