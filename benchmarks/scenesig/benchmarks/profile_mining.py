"""Profile of one place's mining: ``scenesig bench profile_mining [--json OUT]``.

Mines one place (:func:`scenesig.signatures.mining.mine_place`, all candidate shapes, one core: BLAS and
OpenCV limited to one thread, ``n_jobs=1``) and reports the wall time per stage, so a change to
the trainer can be judged against it:

* ``pyramids`` -- HOG pyramids of the place's images (:func:`scenesig.signatures.hog.build_pyramid`);
* ``partitions`` -- appearance descriptors and the partition split;
* ``candidates`` -- unrolling every window a shape may fire on (``_candidates``);
* ``negatives`` -- sampling and unrolling the local and external negatives (``_negatives``);
* ``gram`` -- the negatives' Gram matrix per shape (``scenesig.signatures.classifier.LinearSVMTrainer``);
* ``svm_kernel`` / ``svm_solve`` -- assembling each fit's kernel and the filter / the libsvm solve;
* ``fire`` -- scoring the next partition's windows (``_fire``);
* ``calibration`` -- Platt scaling of the held-out scores;
* ``refine_nominal`` -- the final bank detected in every training image;
* ``shape_bookkeeping`` -- the rest of the per-shape loop; ``other`` -- what no stage covers.

Each stage has ``ms`` (exclusive), ``calls`` and ``ms_per_shape``.  The images are the speed
benchmark's place (``scenesig.surveys.sim.place_views(preset="demo", seed=0, n=31)``, 640x480) unless
``--images`` names image files (aligned, offsets zero).  ``--shapes N`` mines only every
(296 / N)-th candidate shape, for a quick look.
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from scenesig.benchmarks._stages import StageTimer, emit_json

__all__ = ["profile_mining", "main"]


def _targets(timer):
    from scenesig.signatures import classifier, detection, hog, mining
    return [(hog, "build_pyramid", "pyramids"), (detection, "build_pyramid", "pyramids"),
            (mining, "partition_images", "partitions"), (mining, "appearance_descriptor", "partitions"),
            (mining, "_candidates", "candidates"), (mining, "_negatives", "negatives"),
            (classifier.LinearSVMTrainer, "__init__", "gram"), (classifier.LinearSVMTrainer, "fit", "svm_kernel"),
            (classifier, "svm_dual", "svm_solve"), (mining, "_fire", "fire"), (mining, "_platt", "calibration"),
            (mining, "_refine_nominal", "refine_nominal"), (mining, "_mine_shape", "shape_bookkeeping")]


def profile_mining(images, offsets=None, shapes: int | None = None, seed: int = 0) -> dict:
    """Mine one place on one core and return the per-stage profile (module docstring)."""
    from threadpoolctl import threadpool_limits

    from scenesig.signatures import mining
    from scenesig.signatures.shapes import ShapeSet, candidate_shapes

    h, w = images[0].shape[:2]
    shape_set = candidate_shapes(w, h)
    if shapes is not None and shapes < len(shape_set):
        keep = np.arange(0, len(shape_set), max(1, len(shape_set) // shapes))[:shapes]
        shape_set = ShapeSet(shape_set.boxes[keep], shape_set.kind[keep], shape_set.kind_names,
                             shape_set.image_size)
    timer = StageTimer()
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1), timer.patch(*_targets(timer)):
            t0 = time.perf_counter()
            bank, stats = mining.mine_place(images, offsets, n_jobs=1, rng=seed, shapes=shape_set)
            wall = time.perf_counter() - t0
    finally:
        cv2.setNumThreads(cv_threads)
    n_shapes = len(shape_set)
    stages = timer.as_dict()
    for d in stages.values():
        d["ms_per_shape"] = round(d["ms"] / max(n_shapes, 1), 3)
    covered = sum(timer.seconds.values())
    stages["other"] = {"ms": round(1e3 * (wall - covered), 3), "calls": 0}
    st = stats.as_dict()
    return {"seconds": round(wall, 3), "n_images": len(images), "image_size": [w, h], "shapes": n_shapes,
            "kept": st["kept"], "converged": st["converged"], "mean_steps": st["mean_steps"],
            "threads": 1, "stages": stages}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scenesig bench profile_mining", description=__doc__.splitlines()[0])
    ap.add_argument("--images", nargs="+", help="image files of one place (default: the speed benchmark's place)")
    ap.add_argument("--shapes", type=int, help="mine only this many evenly spaced candidate shapes")
    ap.add_argument("--json", help="write the result JSON here")
    args = ap.parse_args(argv)
    if args.images:
        from scenesig.benchmarks.mining import read_images
        images = read_images(args.images)
        offsets, source = None, f"{len(images)} files"
    else:
        from scenesig.benchmarks.speed import place_images
        images, offsets, source = place_images()
    res = {"images": source, **profile_mining(images, offsets, args.shapes)}
    emit_json(res, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
