"""Time targets of scene signatures on real webcam images: ``scenesig bench webcam-speed DIR --json OUT``.

The figures, all on **one core** but ``detect_hz_1024x627_2_threads`` (OpenCV ``setNumThreads(1)``, BLAS limited to one thread by
threadpoolctl, ``n_jobs=1``), as :mod:`scenesig.benchmarks.speed` measures training:

* ``mine_seconds_per_bank_20_images`` -- :func:`scenesig.signatures.mining.mine_place` on 20 training
  images of one scene (all 296 candidate shapes, HOG pyramids included), the way
  ``scenesig bench webcam --train multi`` mines a scene: the first scene with at least 20 even-position
  images (``chamonix`` in ``../shared/data/webcam``), at the webcam benchmark's processing size (at
  most 640x480 pixels of area), the other scenes' first training images as external negatives;
* ``detect_hz_1024x627`` -- that bank detected in a 1024x627 image (the scene's first test image
  resized), whole-image search over every level the bank uses, HOG pyramid included: frames per
  second from the median of ``--repeat`` runs.  ``detect_hz_1024x627_windowed`` repeats it with
  +-40-px search windows around each classifier's trained position, as the localiser searches under
  its odometry prior; ``detect_hz_1024x627_best_100`` whole-image with the bank's 100 best classifiers
  (held-out quality), since whole-image time grows with the bank (about 9 GFLOP of filter
  responses for ~280 classifiers at 1024x627, close to one core's peak);
  ``detect_hz_1024x627_2_threads`` whole-image on **two cores**: the pyramid levels on two threads
  (``Bank.detect``'s ``threads``, as the localiser's detector runs it; filter multiplies still on
  one BLAS thread each);
* ``mine_seconds_single`` -- the single-experience bank of the same scene (one image and its
  synthesised copies, :func:`scenesig.benchmarks.webcam.mine_scene_bank` with ``--train single``'s input).

The JSON also holds the bank size, the CPU time of each measurement (``*_cpu_*``: on a busy machine
the wall time measures the load as much as the code; one thread's CPU time is what a free core would
take) and the load average.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import cv2
import numpy as np

from scenesig.benchmarks._stages import emit_json, read_config
from scenesig.benchmarks._timing import median_ms

__all__ = ["run", "main"]

N_IMAGES = 20
DETECT_SIZE = (1024, 627)
WINDOW_PX = 40.0
SMALL_BANK = 100


def run(root, repeat: int = 10, seed: int = 0, config: dict | None = None) -> dict:
    """Measure the time targets on the webcam folder ``root`` (module docstring); ``config``:
    overrides of the webcam benchmark's settings (:data:`scenesig.benchmarks.webcam.default_config`)."""
    from threadpoolctl import threadpool_limits

    from scenesig.benchmarks import webcam
    from scenesig.signatures import mining
    from scenesig.surveys.errors import DataError

    cfg = webcam._merged(webcam.default_config, config or {})
    scenes = webcam.load_scenes(root, "multi")
    scene = next((s for s in scenes if len(s.train) >= N_IMAGES), None)
    if scene is None:
        raise DataError(root, f"no scene with {N_IMAGES} even-position (training) images")

    def load(f):
        im = webcam.read_image(f)
        return webcam._resize(im, webcam.processing_scale(im.shape, cfg["max_pixels"]))

    images = [load(f) for f in scene.train[:N_IMAGES]]
    size = images[0].shape[1], images[0].shape[0]
    negatives = [cv2.resize(load(s.train[0]), size, interpolation=cv2.INTER_AREA)
                 for s in scenes if s is not scene]
    frame = cv2.resize(webcam.read_image(scene.test[0]), DETECT_SIZE, interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    out = {"dataset": str(root), "scene": scene.name, "train_images": N_IMAGES,
           "image_size": list(size), "detect_image_size": list(DETECT_SIZE),
           "detect_image": scene.test[0].name, "threads": 1}
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            t0, c0 = time.perf_counter(), time.process_time()
            bank, stats = mining.mine_place(images, config=cfg["signatures"]["mining"],
                                            negatives=negatives, n_jobs=1, rng=seed)
            out["mine_seconds_per_bank_20_images"] = round(time.perf_counter() - t0, 2)
            out["mine_cpu_seconds_per_bank_20_images"] = round(time.process_time() - c0, 2)
            out["bank_size"] = len(bank)
            if len(bank) == 0:
                raise RuntimeError("no classifier converged; cannot time detection")
            c0 = time.process_time()
            ms = median_ms(lambda: bank.detect(gray), repeat)
            out["detect_ms_1024x627"] = round(ms, 1)
            out["detect_hz_1024x627"] = round(1000.0 / ms, 2)
            out["detect_cpu_ms_1024x627"] = round(1000.0 * (time.process_time() - c0) / (repeat + 1), 1)
            # the same on two cores: the pyramid levels on two threads, as the localiser's detector runs
            ms = median_ms(lambda: bank.detect(gray, config={"threads": 2}), repeat)
            out["detect_hz_1024x627_2_threads"] = round(1000.0 / ms, 2)
            # the bank's positions are in mining pixels: scale them to the detection image
            sx, sy = DETECT_SIZE[0] / size[0], DETECT_SIZE[1] / size[1]
            nom = np.array([c.nominal_xy for c in bank]) * [sx, sy]
            win = np.concatenate([nom - WINDOW_PX, nom + WINDOW_PX], axis=1)
            c0 = time.process_time()
            ms = median_ms(lambda: bank.detect(gray, windows=win), repeat)
            out["detect_ms_1024x627_windowed"] = round(ms, 1)
            out["detect_hz_1024x627_windowed"] = round(1000.0 / ms, 2)
            out["detect_cpu_ms_1024x627_windowed"] = round(1000.0 * (time.process_time() - c0) / (repeat + 1), 1)
            # Whole-image cost grows with the bank: the best SMALL_BANK by held-out quality
            small = bank.best(SMALL_BANK)
            c0 = time.process_time()
            ms = median_ms(lambda: small.detect(gray), repeat)
            out[f"detect_hz_1024x627_best_{SMALL_BANK}"] = round(1000.0 / ms, 2)
            out[f"detect_cpu_ms_1024x627_best_{SMALL_BANK}"] = round(
                1000.0 * (time.process_time() - c0) / (repeat + 1), 1)
            single = webcam.load_scenes(root, "single")[scenes.index(scene)].train
            one = [load(single[0])]
            t0, c0 = time.perf_counter(), time.process_time()
            sbank, _, _ = webcam.mine_scene_bank(one, negatives, cfg, n_jobs=1)
            out["mine_seconds_single"] = round(time.perf_counter() - t0, 2)
            out["mine_cpu_seconds_single"] = round(time.process_time() - c0, 2)
            out["single_bank_size"] = len(sbank)
    finally:
        cv2.setNumThreads(cv_threads)
    out["mining_stats"] = {k: v for k, v in stats.as_dict().items() if k != "partitions"}
    out["load_average"] = [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None
    out["targets"] = {"mine_seconds_per_bank_20_images": 30.0, "detect_hz_1024x627": 10.0}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench webcam-speed", description=__doc__.splitlines()[0])
    ap.add_argument("dir", help="webcam folder, one sub-folder per scene (e.g. ../shared/data/webcam)")
    ap.add_argument("--repeat", type=int, default=10, help="detection repeats (median)")
    ap.add_argument("--json", help="write the result JSON here")
    ap.add_argument("--config", default=None, metavar="JSON",
                    help="JSON file of overrides of the webcam benchmark's settings")
    args = ap.parse_args(argv)
    config = read_config(args.config)
    out = run(args.dir, args.repeat, config=config)
    if config:
        out["config"] = config
    emit_json(out, args.json)
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "webcam-speed", *sys.argv[1:]]))
