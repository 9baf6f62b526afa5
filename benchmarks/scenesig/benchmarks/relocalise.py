"""Cost of global localisation per frame as the map grows: ``scenesig bench relocalise MAP RUN --json OUT``.

A localiser without GPS (``scenesig localise --oracle none``, :mod:`scenesig.localiser.relocalise`) spends, on
every detector frame while it is not localised, the time of

* **retrieval** -- the live image's whole-image descriptor and its similarity to every stored
  descriptor of every place (grows linearly with the places), and
* **verification** -- the shortlisted places' banks searched over the whole image and the pose
  solved (``shortlist`` places, however large the map).

The map's places are replicated (their descriptors tiled, a replicated place verified with its
original's bank) to reach ``--places 30,100,300``; frames are spread over the run.  Prints and writes
``{"map", "run", "frames", "shortlist", "places": {N: {"ms_retrieval", "ms_verification", "ms_total"}}}``
(medians over the frames); measured on the machine as it is (say so when it is shared).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["measure", "main"]


class _Tiled:
    """A :class:`scenesig.localiser.relocalise.PlaceRetrieval` whose places are repeated up to ``n_places``."""

    def __init__(self, base, n_places: int):
        self.base = base
        n = len(base.ids)
        k = int(np.ceil(n_places / n))
        owner = np.concatenate([base.owner + r * n for r in range(k)])
        keep = owner < n_places                        # exactly n_places places
        self.D = np.tile(base.D, (k, 1))[keep]
        self.owner = owner[keep]
        self.n = int(n_places)

    def rank(self, image):
        from scenesig.signatures import globaldesc
        from scenesig.signatures.bank import limit_blas_threads

        q = globaldesc.describe(image, self.base.config)
        with limit_blas_threads(1):       # as PlaceRetrieval.scores
            s = globaldesc.similarity(q, self.D, self.owner, self.n)
        return [int(self.base.ids[i % len(self.base.ids)]) for i in np.argsort(-s, kind="stable")]


def measure(map_root, run_root, places=(30, 100, 300), frames: int = 20, shortlist: int | None = None) -> dict:
    from scenesig.localiser.pipeline import Measurement, MotionPrior, make_method
    from scenesig.localiser.relocalise import PlaceRetrieval, default_config as reloc_default
    from scenesig.mapping.store import MapStore
    from scenesig.surveys.run import read_run

    store = MapStore.open(map_root)
    run = read_run(run_root, skip=("groundtruth", "gps", "truth"))
    K = int(shortlist or reloc_default["shortlist"])
    method = make_method("signatures", store, run.camera, run.T_vehicle_camera)
    base = PlaceRetrieval(store)
    prior_cov = np.diag(np.asarray(reloc_default["prior_sigma"], float) ** 2)
    idx = np.linspace(0, len(run) - 1, min(frames, len(run))).round().astype(int)
    images = [run.image(int(i), gray=not method.color) for i in idx]
    out = {}
    try:
        for n in places:
            tiled = _Tiled(base, int(n))
            ret, ver = [], []
            for img in images:
                t0 = time.perf_counter()
                short = tiled.rank(img)[:K]
                t1 = time.perf_counter()
                for p in short:
                    Twp = store.places[p].T_world_place
                    prior = MotionPrior(0.0, Twp, prior_cov, p, Twp, None, True, float("inf"),
                                        reloc_default["verify_classifiers"])
                    Measurement.coerce(method.solve(method.detect(img, p, prior), p, prior))
                t2 = time.perf_counter()
                ret.append(1e3 * (t1 - t0))
                ver.append(1e3 * (t2 - t1))
            out[str(n)] = {"places_used": tiled.n, "ms_retrieval": float(np.median(ret)),
                           "ms_verification": float(np.median(ver)),
                           "ms_total": float(np.median(np.add(ret, ver)))}
    finally:
        method.close()
    return {"map": str(map_root), "run": run.name, "frames": len(images), "shortlist": K,
            "verify_classifiers": reloc_default["verify_classifiers"],
            "map_places": len(store), "cpu_count": os.cpu_count(), "places": out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scenesig bench relocalise", description=__doc__.split("\n")[0])
    p.add_argument("map", help="map folder")
    p.add_argument("run", help="a survey run (its images only)")
    p.add_argument("--places", default="30,100,300", help="map sizes (places are replicated to reach them)")
    p.add_argument("--frames", type=int, default=20, help="frames timed, spread over the run")
    p.add_argument("--shortlist", type=int, default=None, help="places verified per frame (default: the localiser's)")
    p.add_argument("--json", required=True, help="output JSON file")
    args = p.parse_args(argv)
    doc = measure(args.map, args.run, [int(v) for v in args.places.split(",") if v.strip()], args.frames,
                  args.shortlist)
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    from scenesig.cli import main as _cli

    raise SystemExit(_cli(["bench", "relocalise", *sys.argv[1:]]))
