"""``scenesig aerial ...``: UAV image to geo-referenced satellite-map matching (MRSM-CC).

* ``scenesig aerial bench TILES_DIR --methods mrsmcc,sism,sift,orb,signatures --trials N --seed S
  --json OUT [--figure DIR]`` -- the Monte-Carlo benchmark (:mod:`scenesig.benchmarks.aerial`, its own
  arguments);
* ``scenesig aerial localise TILES_DIR IMAGES_DIR --out DIR [--prior LAT,LON] [--method psd-kdmm]`` -- a sequence of
  sensed images -> ``track.csv``, ``track.png``, ``summary.json``;
* ``scenesig aerial simulate TILES_DIR OUT --images N --seed S`` -- a synthetic sequence cut from
  the tiles (with ``truth.csv``), to try ``localise`` on.
"""
from __future__ import annotations

import argparse
import importlib
import json


def _latlon(s: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON in degrees, got {s!r}") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError(f"LAT,LON out of range: {s!r}")
    return lat, lon


def register(groups):
    help = "Monte-Carlo aerial scene-matching benchmark (JSON)."
    p = groups["aerial"].add_parser("bench", help=help, description=help, add_help=False)
    p.set_defaults(_run=run_bench, _pass_extra=True)

    help = "Localise a sequence of UAV images on geo-referenced tiles (MRSM-CC)."
    p = groups["aerial"].add_parser("localise", help=help, description=help)
    p.add_argument("tiles", help="folder with map.csv and the tiles")
    p.add_argument("images", help="folder of sensed images, in flight order by file name")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--prior", type=_latlon, help="rough position of the first image: LAT,LON")
    p.add_argument("--prior-radius-m", type=float, default=30.0,
                   help="uncertainty of the prior and of each previous estimate (m, default 30)")
    p.add_argument("--method", default="mrsmcc", choices=("mrsmcc", "psd-point", "psd-kdm", "psd-kdmm"),
                   help="matcher: MRSM-CC (default) or a point-set-domain stage, which tries every tile and "
                        "keeps the best match score (psd-kdmm: the lowest region dissimilarity)")
    p.add_argument("--xfeat-model", default=None, help="psd-*: the XFeat ONNX model file")
    p.add_argument("--feature-cache", default=None, help="psd-*: folder keeping XFeat features between runs")
    p.set_defaults(_run=run_localise)

    help = "Write a synthetic UAV image sequence cut from the tiles (with truth.csv)."
    p = groups["aerial"].add_parser("simulate", help=help, description=help)
    p.add_argument("tiles", help="folder with map.csv and the tiles")
    p.add_argument("out", help="output folder for the images and truth.csv")
    p.add_argument("--images", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--step-m", type=float, default=8.0, help="distance between images (m)")
    p.set_defaults(_run=run_simulate)


def run_bench(args) -> int:
    module = importlib.import_module("scenesig.benchmarks.aerial")
    return int(module.main(list(args._extra)) or 0)


def run_localise(args) -> int:
    from scenesig.aerial.localise import localise_sequence

    psd = None
    if args.method != "mrsmcc":
        psd = {"xfeat": {"model": args.xfeat_model} if args.xfeat_model else {}, "cache": args.feature_cache}
    summary = localise_sequence(args.tiles, args.images, args.out, prior=args.prior,
                                prior_radius_m=args.prior_radius_m, method=args.method, psd_config=psd)
    print(json.dumps(summary, indent=1))
    return 0


def run_simulate(args) -> int:
    from scenesig.aerial.geo import load_tiles
    from scenesig.aerial.trials import write_sequence

    rows = write_sequence(load_tiles(args.tiles), args.out, args.images, args.seed, args.step_m)
    print(json.dumps({"images": len(rows), "out": str(args.out)}))
    return 0
