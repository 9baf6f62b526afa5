"""``scenesig localise MAP RUN --out DIR``: replay a traverse against a map."""
from __future__ import annotations

import json

from ._types import positive_int

#: the localisation methods of :data:`localiser.pipeline.METHODS`
METHODS = ("signatures", "orb", "sift")


def register(groups):
    help = "Localise a replayed traverse against a map."
    p = groups[""].add_parser("localise", help=help, description=help)
    p.add_argument("map", help="map folder")
    p.add_argument("run", help="survey run to replay")
    p.add_argument("--method", choices=METHODS, default="signatures")
    p.add_argument("--out", required=True, help="output folder")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--every", type=positive_int, default=4, help="detector on every N-th frame (deterministic)")
    mode.add_argument("--realtime", action="store_true", help="threads and queues, stale frames dropped")
    p.add_argument("--speed", type=float, default=1.0,
                   help="with --realtime: replay speed as a multiple of the recorded rate (default 1)")
    p.add_argument("--oracle", choices=("ins", "none"), default="ins",
                   help="ins (default, the paper's protocol): start and reset from the run's INS/GPS; none: no "
                        "INS/GPS -- global localisation from the map at start-up, relocalisation when lost")
    p.set_defaults(_run=run)


def run(args) -> int:
    from localiser.replay import localise

    metrics = localise(args.map, args.run, args.out, method=args.method, every=args.every or 4,
                       realtime=bool(args.realtime), speed=float(args.speed or 1.0), oracle=args.oracle)
    keys = ("method", "run", "oracle", "lateral_error_m", "heading_error_deg", "localised_fraction", "failures",
            "blind_fraction_over_20m", "first_fix_m", "relocalisations", "false_fixes", "realtime_factor")
    print(json.dumps({k: metrics[k] for k in keys}, indent=1))
    return 0
